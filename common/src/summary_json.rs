//! `OUT/summary.json` of `rotorloop run`: every key, its unit and its meaning, as one
//! table ([`keys`]; docs/wire.md's "`summary.json`" section is made from it by `rotorloop
//! wire --format markdown`), and its layout version [`SUMMARY_JSON_VERSION`] (the file's
//! `layout_version` key), raised when a key is renamed, removed or changes meaning or
//! unit (a key added keeps it), as `controller.json`'s is.
//!
//! The file is written by several hands (the monitor's report, then the launcher, the fault
//! report and the incidents each add their keys), so the table is checked against real
//! files, not a type: [`check`] names every key of a file the table lacks and every key
//! the table says is always there that the file lacks (`tests/cli_outputs.rs`). A new key
//! is a row here.
//!
//! A path is keys joined by `.`; `<name>` stands for any key of a map (`hops.<hop>.p50`),
//! and `[]` for the elements of an array of objects (`faults[].kill_tick`). A row without
//! rows below it is a leaf: its value (a number, a string, an array of numbers, or an
//! object described elsewhere, such as `scenario`) is not looked into.

use std::collections::BTreeSet;

use serde_json::Value;

/// The layout version of `summary.json` (its `layout_version` key).
pub const SUMMARY_JSON_VERSION: u32 = 1;

/// Whether a key is in every file (of a run that got as far as its report).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Presence {
    /// Always there (inside its parent, where the parent is).
    Always,
    /// Only when (the words say when).
    When(&'static str),
}

/// One row of the table.
#[derive(Debug, Clone, Copy)]
pub struct Key {
    /// The key's path.
    pub path: &'static str,
    /// Its JSON type and unit.
    pub unit: &'static str,
    /// Whether it is always there.
    pub presence: Presence,
    /// What it is.
    pub meaning: &'static str,
}

const fn always(path: &'static str, unit: &'static str, meaning: &'static str) -> Key {
    Key { path, unit, presence: Presence::Always, meaning }
}

const fn when(
    path: &'static str,
    unit: &'static str,
    cond: &'static str,
    meaning: &'static str,
) -> Key {
    Key { path, unit, presence: Presence::When(cond), meaning }
}

/// The statistics of one latency hop or stage (ns), under `prefix`.
macro_rules! hop_stats {
    ($p:literal, $what:literal) => {
        [
            always(concat!($p, ".count"), "integer", concat!("samples of ", $what)),
            always(concat!($p, ".min"), "integer, ns", "the smallest"),
            always(concat!($p, ".mean"), "number, ns", "the mean"),
            always(
                concat!($p, ".p50"),
                "integer, ns",
                "the median (HdrHistogram, 3 significant digits)",
            ),
            always(concat!($p, ".p90"), "integer, ns", "the 90th percentile"),
            always(concat!($p, ".p99"), "integer, ns", "the 99th percentile"),
            always(concat!($p, ".p99_9"), "integer, ns", "the 99.9th percentile"),
            always(concat!($p, ".p99_99"), "integer, ns", "the 99.99th percentile"),
            always(concat!($p, ".max"), "integer, ns", "the largest"),
        ]
    };
}

const HOP: [Key; 9] =
    hop_stats!("hops.<hop>", "the hop (0 for a hop with none: all its stats are then 0)");
const STAGE: [Key; 9] = hop_stats!("stages[]", "the stage");

const MAIN: &[Key] = &[
    always(
        "layout_version",
        "integer",
        "this file's layout version (now 1); raised when a key is renamed, removed or changes meaning or unit",
    ),
    always("name", "string", "the scenario's name"),
    always(
        "scenario",
        "object",
        "the scenario as run, command-line overrides applied: `scenario.toml`'s tables and keys (docs/scenarios.md)",
    ),
    always("mode", "string", "`lockstep` or `realtime`"),
    always("wait", "string", "the wait strategy: `event`, `spin` or `hybrid`"),
    always(
        "ticks",
        "integer",
        "the run's last tick: states 0 to `ticks`, `ticks` + 1 rows when complete (as `controller.json`'s `ticks`)",
    ),
    always("trace_rows", "integer", "rows written to `trace.csv` (`ticks` + 1 when complete)"),
    always(
        "rows_lost",
        "integer",
        "ticks with no row in `trace.csv`: with flight records, ticks no role recorded (a sample never published); without, also what the live monitor missed. `trace_rows + rows_lost` = `ticks` + 1",
    ),
    always(
        "live_rows_lost",
        "integer",
        "rows the live monitor itself missed (its gaps, samples it fell behind on)",
    ),
    when(
        "flight",
        "object",
        "with flight records (not `--no-record`)",
        "the flight records the report was assembled from",
    ),
    always(
        "flight.dir",
        "string, path",
        "where the records are (`OUT/flight`, or the staging directory they stayed in)",
    ),
    always(
        "flight.assembled",
        "boolean",
        "whether the report was assembled from them (else the monitor's live view, and `flight.error` says why)",
    ),
    when("flight.error", "string", "when they could not be used", "why"),
    always("flight.streams", "array of objects", "per stream of records"),
    always(
        "flight.streams[].stream",
        "string",
        "`plant-state`, `plant-torque`, `controller-torque` or `reference`",
    ),
    always("flight.streams[].records", "integer", "ticks recorded"),
    always(
        "flight.streams[].missing",
        "array of [first, last] tick pairs",
        "ticks 0 to the last with no record (the first 16 ranges)",
    ),
    always(
        "flight.streams[].opens",
        "integer",
        "how often the file was opened for writing (1 + the writer's restarts)",
    ),
    always(
        "flight.streams[].beyond",
        "integer",
        "samples whose tick lay beyond the file (not recorded)",
    ),
    when(
        "flight.streams[].problems",
        "array of strings",
        "when something in its files could not be read",
        "what (a torn or foreign segment, ticks beyond the run); the stream was read as far as it is sound",
    ),
    always(
        "flight.torques_from_plant",
        "integer",
        "torques taken from the plant's record because the controller's had none (a controller of the user's own records none)",
    ),
    when(
        "flight.durable_lag_max_s",
        "number, s",
        "when the launcher moved the records and kept their journal (not after `recover`)",
        "the longest the record's newest ticks were from the disk: what a machine crash at the worst moment of the run would have lost (docs/flight-recorders.md)",
    ),
    always("monitor_kept_up", "boolean", "whether the live monitor saw every tick"),
    always(
        "misses",
        "integer, ticks",
        "ticks on which the plant had no fresh torque in time (real time; 0 in lockstep)",
    ),
    always(
        "reference_misses",
        "integer, ticks",
        "states the controller answered without their own reference sample at hand",
    ),
    always(
        "states_skipped_by_controller",
        "integer",
        "states the controller took but did not answer (a newer one was there)",
    ),
    always("rate_hz", "number, Hz", "the rate asked"),
    always(
        "achieved_rate_hz",
        "number, Hz",
        "ticks over the plant's wall time from tick 0 to the last (in lockstep: how fast it ran)",
    ),
    always(
        "subscribers",
        "object",
        "per subscriber (`controller.state`, `monitor.torque`, …): samples received and lost",
    ),
    always("subscribers.<subscriber>.received", "integer", "samples taken"),
    always(
        "subscribers.<subscriber>.lost",
        "integer",
        "samples known lost (gaps in the tick sequence)",
    ),
    always(
        "hops",
        "object",
        "per latency hop (docs/latency.md: `sense_to_actuate`, `state_delivery`, `controller_compute`, …), its statistics in ns",
    ),
];

const REST: &[Key] = &[
    always(
        "stages",
        "array of objects",
        "the stage breakdown of sense-to-actuate (docs/latency.md), in tick order",
    ),
    always("stages[].stage", "string", "the stage's name"),
    always(
        "stages[].in_loop",
        "boolean",
        "whether it lies on the loop's path (its medians add up to sense-to-actuate's)",
    ),
    when(
        "cross_host",
        "object",
        "a `--split` run",
        "the hosts of the roles, and the hops not computed because they span two clocks",
    ),
    always("cross_host.hosts", "object", "the host of each role (`plant`: `a`, …)"),
    always("cross_host.not_computed", "array of strings", "the hops and stages not computed"),
    always("cross_host.why", "string", "why"),
    always("err_deg_initial", "number, deg", "the attitude error at the first row"),
    always("err_deg_final", "number, deg", "the attitude error at the last row"),
    always(
        "err_deg_rms",
        "number, deg",
        "root mean square of the attitude error over the rows recorded",
    ),
    always(
        "momentum_drift_rel_max",
        "number, relative",
        "the largest relative drift of the spatial momentum",
    ),
    always("completed", "boolean", "whether the run reached its last tick (false after a signal)"),
    always(
        "monitor_gaps",
        "array of [first, last] tick pairs",
        "ticks the live monitor missed while it was down",
    ),
    always("monitor_restarts", "integer", "how often the monitor was restarted"),
    always("safe_mode_ticks", "integer, ticks", "ticks the plant spent in safe mode"),
    always(
        "wire_rejected",
        "object",
        "samples rejected by validation, per receiver (`plant.torque`, `controller.state`, `controller.reference`, `monitor.state`, `monitor.reference`, `monitor.torque`)",
    ),
    always("wire_rejected.<receiver>", "integer", "samples that receiver rejected"),
    always(
        "wire_faults",
        "array of objects",
        "the first rejected samples seen, with the reason (at most 32)",
    ),
    always("wire_faults[].topic", "string", "`state`, `reference` or `torque`"),
    always("wire_faults[].tick", "integer", "the sample's tick"),
    always(
        "wire_faults[].kind",
        "string",
        "`non-finite`, `absurd`, `non-orthonormal` or `future-tick`",
    ),
    always("wire_faults[].detail", "string", "the reason, naming the field"),
    always(
        "saturated_ticks",
        "integer, ticks",
        "ticks whose rotor torque the actuator limits changed",
    ),
    always("saturated_fraction", "number, 0 to 1", "`saturated_ticks / ticks`"),
    always(
        "faults",
        "array of objects",
        "the faults as they happened (`--fault`'s, and any role that died, stopped or hung), with what each cost; empty: none",
    ),
    always("faults[].role", "string", "the role (or gateway `link-HOST`)"),
    always(
        "faults[].kind",
        "string",
        "`kill`, `stop`, `delay` (by `--fault`), `killed`, `crash`, `exited`, `hang`, `rejected`, `link-lost`, `resume-refused` (docs/faults-and-supervision.md)",
    ),
    always("faults[].detail", "string", "what happened, in words"),
    always(
        "faults[].kill_s",
        "number, s of the run",
        "its start: in lockstep the time of `kill_tick`; in real time the wall time since the first tick was published",
    ),
    always(
        "faults[].restart_s",
        "number, s of the run, or null",
        "its restart (a stop's continue); null: none",
    ),
    always(
        "faults[].signal",
        "string or null",
        "the signal, where known (`SIGKILL`, `SIGSTOP`, …)",
    ),
    always(
        "faults[].ended",
        "string or null",
        "how a stop ended: `continued`, `killed`, `crash`, `exited`, `hung`, `still stopped when the launcher ended`",
    ),
    always("faults[].ended_s", "number, s of the run, or null", "when a stop ended"),
    always("faults[].kill_tick", "integer or null", "the newest tick published before it"),
    always(
        "faults[].restart_tick",
        "integer or null",
        "the first tick published after its restart or continue",
    ),
    always(
        "faults[].ticks_without_fresh_torque",
        "integer, ticks",
        "ticks after it whose preceding torque was not fresh (held or safe mode)",
    ),
    always(
        "faults[].ticks_to_first_fresh_torque",
        "integer, ticks, or null",
        "from its restart to the first fresh torque applied",
    ),
    always(
        "faults[].peak_deviation_deg",
        "number, deg, or null",
        "the peak attitude deviation from the run that had no incident, over the incident that holds it; null: not computed",
    ),
    always(
        "faults[].recovery_s",
        "number, s, or null",
        "from the incident's start until that deviation is below 10 % of its peak; null: not within the run",
    ),
    always(
        "faults[].incident",
        "integer or null",
        "its incident's row in `incidents.csv` (from 1)",
    ),
    always(
        "faults[].scheduled",
        "boolean",
        "whether the `--fault` schedule asked for it (false: from outside the launcher, or found by its supervisor)",
    ),
    always(
        "fault_schedule",
        "array of objects",
        "the `--fault`s as given, on the run's clock; empty: none",
    ),
    always("fault_schedule[].role", "string", "the role"),
    always("fault_schedule[].kind", "string", "`kill`, `stop` or `delay`"),
    always("fault_schedule[].at_s", "number, s of the run", "its start as asked"),
    always(
        "fault_schedule[].at_tick",
        "integer",
        "the tick its start is due at (the first at or after `at_s`)",
    ),
    always(
        "fault_schedule[].until_s",
        "number, s, or null",
        "its end as asked (a down time after `at_s` where the end stops the plant's clock: docs/faults-and-supervision.md)",
    ),
    always("fault_schedule[].until_tick", "integer or null", "the tick of `until_s`"),
    always("fault_schedule[].value_s", "number, s, or null", "a delay's length"),
    always("plant_stall", "string", "`--plant-stall`: `hold` or `pause`"),
    when("resources", "object", "with a monitor", "each process's resident memory"),
    always("resources.rss_csv", "string", "the file of every sample, `rss.csv`"),
    always("resources.rss", "object", "per role"),
    always("resources.rss.<role>.pid", "integer", "its pid (last life)"),
    always(
        "resources.rss.<role>.start_kib",
        "integer, KiB",
        "resident memory once started (the first sample 3 s after its start, or its first)",
    ),
    always(
        "resources.rss.<role>.start_at_s",
        "number, s",
        "when that sample was taken, after its start",
    ),
    always("resources.rss.<role>.end_kib", "integer, KiB", "the last sample before it ended"),
    always("resources.rss.<role>.end_at_s", "number, s", "when, after its start"),
    always("resources.rss.<role>.max_kib", "integer, KiB", "the largest sample"),
    always(
        "resources.rss.<role>.start_parts_kib",
        "3 integers, KiB",
        "`RssAnon`, `RssFile`, `RssShmem` of the start sample",
    ),
    always("resources.rss.<role>.end_parts_kib", "3 integers, KiB", "the same of the end sample"),
    always("resources.rss.<role>.samples", "integer", "samples taken"),
    when(
        "incidents",
        "object",
        "with a monitor and flight records",
        "the run's incidents (docs/incidents.md)",
    ),
    always("incidents.count", "integer", "incidents found"),
    always(
        "incidents.costed",
        "integer",
        "incidents costed: the launcher's faults' first, then the longest, as many as the costing's share of the run holds (docs/incidents.md)",
    ),
    always(
        "incidents.counterfactual_ticks",
        "integer",
        "the ticks the costed incidents' counterfactuals stepped, in all",
    ),
    always(
        "incidents.worst",
        "object or null",
        "the worst incident: its row of `incidents.csv` as an object (docs/incidents.md)",
    ),
    always("incidents.threshold_s", "number, s", "the lateness from which a tick is an incident's"),
    always("incidents.median_delay_s", "number, s", "the run's median sense-to-actuate"),
    always(
        "incidents.law_reproduced",
        "2 integers",
        "the controller's answers the law run in process reproduced bit for bit, and those it computed (equal: the counterfactual loop is trusted)",
    ),
    always(
        "incidents.kernel_view",
        "boolean",
        "whether the incidents had the kernel's view (`sched.csv`, `--trace-sched`)",
    ),
    always("incidents.files", "array of strings", "the incidents' files"),
    when(
        "warnings",
        "array of strings",
        "when something was not as asked (a live view not served, …)",
        "each warning, in words",
    ),
    when("recovered", "object", "a report written by `rotorloop recover`", "that it was, and why"),
    always("recovered.by", "string", "`rotorloop recover`"),
    always("recovered.launcher_pid", "integer", "the launcher that did not end normally"),
    always("recovered.why", "string", "why"),
    always("files", "array of strings", "the files written"),
    always(
        "trace_incomplete_from_tick",
        "integer or null",
        "the first tick missing from `trace.csv` when the output could not be written (a full disk); null: complete",
    ),
    always(
        "storage_errors",
        "array of strings",
        "what could not be written where it belonged, and why",
    ),
    when(
        "report_dir",
        "string, path",
        "when not the output directory (a fallback)",
        "where the report was written",
    ),
    when(
        "note",
        "string",
        "a run whose plant never published tick 0",
        "why there is no loop to report, only its faults",
    ),
];

/// Every row, in the order of the file: `MAIN`, the hop statistics, `REST` with the
/// stage statistics after `stages[].in_loop`.
pub fn keys() -> Vec<Key> {
    let mut k = MAIN.to_vec();
    k.extend(HOP);
    for r in REST {
        k.push(*r);
        if r.path == "stages[].in_loop" {
            k.extend(STAGE);
        }
    }
    k
}

/// [`keys`] as a markdown table.
pub fn keys_markdown() -> String {
    let mut md = String::from("| key | type, unit | present | meaning |\n|---|---|---|---|\n");
    for k in keys() {
        let present = match k.presence {
            Presence::Always => "always".to_owned(),
            Presence::When(w) => format!("only {w}"),
        };
        let esc = |s: &str| s.replace('|', "\\|");
        md.push_str(&format!(
            "| `{}` | {} | {} | {} |\n",
            k.path,
            esc(k.unit),
            esc(&present),
            esc(k.meaning)
        ));
    }
    md
}

/// What [`check`] found.
#[derive(Debug, Default, PartialEq)]
pub struct Checked {
    /// Keys of the file the table does not have (their concrete paths).
    pub undocumented: Vec<String>,
    /// Keys the table says are always there that the file lacks (where their parent is).
    pub missing: Vec<String>,
}

/// Checks a `summary.json` against the table ([`keys`]).
pub fn check(v: &Value) -> Checked {
    let keys = keys();
    let mut seen = BTreeSet::new();
    let mut out = Checked::default();
    walk(&keys, v, ("", ""), &mut seen, &mut out.undocumented);
    for k in keys.iter().filter(|k| k.presence == Presence::Always) {
        let (parent, last) = match k.path.rfind('.') {
            Some(i) => (&k.path[..i], &k.path[i + 1..]),
            None => ("", k.path),
        };
        // A map may be empty: its members are required only through their own keys.
        let member = last.starts_with('<');
        if !member && !seen.contains(k.path) && (parent.is_empty() || seen.contains(parent)) {
            out.missing.push(k.path.to_owned());
        }
    }
    out
}

/// Whether the table has rows below `path`.
fn has_children(keys: &[Key], path: &str) -> bool {
    keys.iter().any(|k| {
        k.path.strip_prefix(path).is_some_and(|r| r.starts_with('.') || r.starts_with("[]"))
    })
}

/// Walks object `v` at table path `pattern` (file path `concrete`).
fn walk(
    keys: &[Key],
    v: &Value,
    (pattern, concrete): (&str, &str),
    seen: &mut BTreeSet<String>,
    undocumented: &mut Vec<String>,
) {
    let Value::Object(m) = v else { return };
    let join = |a: &str, b: &str| if a.is_empty() { b.to_owned() } else { format!("{a}.{b}") };
    for (name, x) in m {
        let exact = join(pattern, name);
        let here = join(concrete, name);
        let placeholder = keys.iter().find_map(|k| {
            let rest = k.path.strip_prefix(pattern)?;
            let rest = if pattern.is_empty() { rest } else { rest.strip_prefix('.')? };
            let seg = rest.split('.').next()?;
            seg.starts_with('<').then(|| join(pattern, seg))
        });
        let path = match keys.iter().any(|k| k.path == exact) {
            true => exact,
            false => match placeholder {
                Some(p) => p,
                None => {
                    undocumented.push(here);
                    continue;
                }
            },
        };
        seen.insert(path.clone());
        let elements = format!("{path}[]");
        match x {
            Value::Object(_) if has_children(keys, &path) => {
                walk(keys, x, (&path, &here), seen, undocumented);
            }
            Value::Array(items) if has_children(keys, &elements) => {
                for (i, item) in items.iter().enumerate() {
                    seen.insert(elements.clone());
                    walk(keys, item, (&elements, &format!("{here}[{i}]")), seen, undocumented);
                }
            }
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_key_the_table_lacks_is_named_and_a_key_always_there_is_required() {
        let mut j = serde_json::json!({});
        let top = |k: &&Key| !k.path.contains(['.', '[']) && k.presence == Presence::Always;
        for k in keys().iter().filter(top) {
            j[k.path] = serde_json::json!(0);
        }
        j["hops"] = serde_json::json!({"sense_to_actuate": {"count": 1}});
        j["faults"] = serde_json::json!([{"role": "plant", "lost_ticks": 3}]);
        j["mystery"] = serde_json::json!(1);
        let c = check(&j);
        assert!(c.undocumented.contains(&"mystery".to_owned()), "{c:?}");
        assert!(c.undocumented.contains(&"faults[0].lost_ticks".to_owned()), "{c:?}");
        assert_eq!(c.undocumented.len(), 2, "{c:?}");
        // Inside a hop and a fault: the rest of their keys; none of an empty array's.
        assert!(c.missing.contains(&"hops.<hop>.p50".to_owned()), "{c:?}");
        assert!(c.missing.contains(&"faults[].kill_tick".to_owned()), "{c:?}");
        assert!(!c.missing.iter().any(|m| m.starts_with("stages[]")), "{c:?}");
        assert!(!c.missing.iter().any(|m| m.starts_with("flight")), "optional: {c:?}");
    }

    #[test]
    fn every_row_is_written_once_and_names_a_unit() {
        let keys = keys();
        let mut paths = BTreeSet::new();
        for k in &keys {
            assert!(paths.insert(k.path), "{} twice", k.path);
            assert!(!k.unit.is_empty() && !k.meaning.is_empty(), "{}", k.path);
        }
        assert!(keys_markdown().contains("| `hops.<hop>.p50` | integer, ns | always |"));
    }
}
