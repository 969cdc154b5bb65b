//! A run's `summary.json` read back ([`Summary::read`]): the one reader of what
//! [`crate::report`] writes and the launcher, the fault report and the incidents add to
//! (`rotorloop_common::summary_json` is its table of keys), for every command that reads a
//! run (`explain`, `export`, `sim --replay`, `compare`, `margin`, `bench`, `paper`) and
//! for the writers that add a key ([`patch`]). Every key is optional: an older summary,
//! or `sim`'s (another layout), reads; a key of another type than its writer's does not.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use rotorloop_common::input::InputError;
use rotorloop_common::scenario::Scenario;
use serde::Deserialize;
use serde_json::Value;

use crate::latency::Hop;
use crate::stages::Stage;

/// Why a run's `summary.json` cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum SummaryError {
    /// The file is not there, or not a regular file of UTF-8 text.
    #[error("cannot read {}: {}", .0.display(), .1)]
    Read(PathBuf, InputError),
    /// It is not JSON, or not the keys of a summary.
    #[error("{} is not a run's summary: {}", .0.display(), .1)]
    NotASummary(PathBuf, serde_json::Error),
}

/// A run's `summary.json`: the keys its readers use, typed, and the file as parsed.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(default)]
pub struct Summary {
    /// Plant steps in the run.
    pub ticks: Option<u64>,
    /// Ticks on which the plant had no fresh torque in time.
    pub misses: Option<u64>,
    /// Tick period (s; `sim`'s summary has it, not `rate_hz`).
    pub dt: Option<f64>,
    /// Requested rate (Hz).
    pub rate_hz: Option<f64>,
    /// Achieved tick rate (Hz).
    pub achieved_rate_hz: Option<f64>,
    /// Attitude error at the last row (deg).
    pub err_deg_final: Option<f64>,
    /// Root mean square of the attitude error over the rows recorded (deg).
    pub err_deg_rms: Option<f64>,
    /// Per hop, by [`Hop::name`]: [`Summary::hop`].
    pub hops: BTreeMap<String, Figures>,
    /// The stages of sense-to-actuate, in tick order: [`Summary::stage`].
    pub stages: Option<Vec<StageFigures>>,
    /// The flight records the report was assembled from.
    pub flight: Option<Flight>,
    /// What could not be written where it belonged, and why.
    pub storage_errors: Vec<String>,
    /// The launcher's warnings.
    pub warnings: Vec<String>,
    /// The faults the launcher saw.
    pub faults: Vec<FaultRow>,
    /// The `--fault` schedule.
    pub fault_schedule: Vec<Scheduled>,
    /// The run's incidents (absent: not computed).
    pub incidents: Option<Incidents>,
    /// The file as parsed, every key: for what is copied as it is (`export --mcap`'s
    /// metadata and attachment) and for a writer that adds a key ([`patch`]).
    #[serde(skip)]
    pub json: Value,
}

/// One hop's or stage's figures (ns). Floats, as their readers compute: a figure the
/// monitor cannot have written (−1) still reads, for `margin` to refuse it by name.
#[derive(Debug, Clone, Copy, Default, Deserialize)]
pub struct Figures {
    /// Samples recorded.
    pub count: Option<u64>,
    /// Median.
    pub p50: Option<f64>,
    /// 99th percentile.
    pub p99: Option<f64>,
    /// 99.9th percentile.
    pub p99_9: Option<f64>,
    /// Maximum.
    pub max: Option<f64>,
}

/// One stage's figures ([`crate::stages::StageStats`]).
#[derive(Debug, Clone, Deserialize)]
pub struct StageFigures {
    /// [`Stage::name`].
    pub stage: String,
    /// Its figures (ns).
    #[serde(flatten)]
    pub figures: Figures,
}

/// Where the flight records were ([`crate::report::FlightSummary`]).
#[derive(Debug, Clone, Deserialize)]
pub struct Flight {
    /// Their directory.
    pub dir: PathBuf,
    /// What of the run the record lost (a machine crash, damage); absent: nothing.
    #[serde(default)]
    pub lost: Option<Lost>,
}

/// What of the run its record lost ([`crate::report::LostSummary`]).
#[derive(Debug, Clone, Deserialize)]
pub struct Lost {
    /// `machine crash`, `record damaged`, or both.
    pub reason: String,
    /// The newest tick of the plant's states on disk.
    pub last_tick_recorded: Option<u64>,
}

/// A fault the launcher saw (a row of `faults`).
#[derive(Debug, Clone, Deserialize)]
pub struct FaultRow {
    /// The role.
    pub role: String,
    /// `kill`, `stop`, `killed`, `crash`, `exited`, `hang`, `link-lost`, `delay`.
    pub kind: String,
    /// In words.
    #[serde(default)]
    pub detail: String,
    /// When (s after the first state's publish).
    pub kill_s: f64,
    /// The tick the run had reached then.
    pub kill_tick: Option<u64>,
    /// Restarted or continued (s).
    pub restart_s: Option<f64>,
    /// How a stop ended.
    pub ended: Option<String>,
    /// A stop's end (s).
    pub ended_s: Option<f64>,
    /// The signal.
    pub signal: Option<String>,
    /// Whether the `--fault` schedule asked for it (absent from a `summary.json` written
    /// before the launcher said so).
    pub scheduled: Option<bool>,
}

/// A fault of the `--fault` schedule (a row of `fault_schedule`): what the launcher was
/// asked to do, the delays the controller applies itself among them.
#[derive(Debug, Clone, Deserialize)]
pub struct Scheduled {
    /// The role.
    pub role: String,
    /// `kill`, `stop` or `delay`.
    pub kind: String,
    /// Its start (s after tick 0).
    pub at_s: f64,
    /// Its end, if any (s).
    pub until_s: Option<f64>,
    /// A delay's seconds.
    pub value_s: Option<f64>,
}

/// The run's incidents (`incidents`, by `rotorloop explain` and after a run).
#[derive(Debug, Clone, Deserialize)]
pub struct Incidents {
    /// How many.
    pub count: Option<u64>,
    /// The costliest (absent: the run had none).
    pub worst: Option<Worst>,
}

/// The costliest incident, as a report quotes it.
#[derive(Debug, Clone, Deserialize)]
pub struct Worst {
    /// What it was.
    pub kind: Option<String>,
    /// Its start (s).
    pub start_s: Option<f64>,
    /// Its length (s).
    pub duration_s: Option<f64>,
    /// The process that held the loop up.
    pub cause_role: Option<String>,
    /// The stage, or what was done to the process.
    pub cause_stage: Option<String>,
    /// The stamps and kernel figures behind the cause.
    pub evidence: Option<String>,
    /// Peak deviation from the loop that had no incident (deg), if computed.
    pub peak_deviation_deg: Option<f64>,
    /// Until the deviation is below a tenth of its peak (s), if within the run.
    pub recovery_s: Option<f64>,
}

impl Summary {
    /// Reads `dir/summary.json`.
    pub fn read(dir: &Path) -> Result<Self, SummaryError> {
        Self::read_file(&dir.join("summary.json"))
    }

    /// Reads the summary at `path` (`margin --latency-from` names one).
    pub fn read_file(path: &Path) -> Result<Self, SummaryError> {
        let json = read_json(path)?;
        let typed =
            Self::deserialize(&json).map_err(|e| SummaryError::NotASummary(path.to_owned(), e))?;
        Ok(Self { json, ..typed })
    }

    /// Hop `hop`'s figures (none where the summary lacks the hop).
    pub fn hop(&self, hop: Hop) -> Figures {
        self.hops.get(hop.name()).copied().unwrap_or_default()
    }

    /// Stage `stage`'s figures, where the summary has its stages and that one among them.
    pub fn stage(&self, stage: Stage) -> Option<Figures> {
        let stages = self.stages.as_ref()?;
        stages.iter().find(|s| s.stage == stage.name()).map(|s| s.figures)
    }

    /// The scenario the run ran, validated as `Scenario::from_file` does, or why there is
    /// none, in words.
    pub fn scenario(&self) -> Result<Scenario, String> {
        let file = serde_json::from_value(self.json["scenario"].clone())
            .map_err(|e| format!("summary.json has no scenario as run: {e}"))?;
        Scenario::from_file(file).map_err(|e| e.to_string())
    }

    /// Key `key` as text (a string without its quotes, anything else as JSON), where it
    /// is there: for a metadata record that copies keys as they are.
    pub fn text(&self, key: &str) -> Option<String> {
        let v = &self.json[key];
        (!v.is_null()).then(|| v.to_string().trim_matches('"').to_owned())
    }
}

/// The summary at `path` as JSON, every key as it is (for a writer that adds one), read as
/// any input (`rotorloop_common::input`: a FIFO in its place is refused, not waited on).
pub fn read_json(path: &Path) -> Result<Value, SummaryError> {
    let text = rotorloop_common::input::read_text(path, 64 << 20)
        .map_err(|e| SummaryError::Read(path.to_owned(), e))?;
    serde_json::from_str(&text).map_err(|e| SummaryError::NotASummary(path.to_owned(), e))
}

/// Changes `out/summary.json` with `change` and writes it back whole; nothing when there
/// is no summary (the monitor was stopped early: nothing to add to).
pub fn patch(out: &Path, change: impl FnOnce(&mut Value)) -> anyhow::Result<()> {
    let path = out.join("summary.json");
    let mut j = match read_json(&path) {
        Err(SummaryError::Read(..)) => return Ok(()),
        j => j?,
    };
    change(&mut j);
    rotorloop_common::output::write_json(&path, &j)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A summary reads with the keys it lacks absent (an older one, `sim`'s): a figure it
    /// does not have is `None`, never 0. A file that is not JSON, or whose keys are not of
    /// their writer's types, is refused naming it; a missing one too, which [`patch`]
    /// leaves missing.
    #[test]
    fn a_summary_reads_without_the_keys_it_lacks_and_a_foreign_file_is_named() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("summary.json");
        let write = |text: &str| std::fs::write(&path, text).expect("write");
        patch(dir.path(), |j| j["ticks"] = 1.into()).expect("nothing to patch");
        let e = Summary::read(dir.path()).expect_err("no file").to_string();
        assert!(e.starts_with("cannot read ") && e.ends_with("summary.json: no such file"), "{e}");
        write(r#"{"ticks": 5, "dt": 0.001, "hops": {"sense_to_actuate": {"count": 3, "p50": 2}}}"#);
        let s = Summary::read(dir.path()).expect("a summary");
        let h = s.hop(Hop::SenseToActuate);
        assert_eq!((s.ticks, s.misses, h.count), (Some(5), None, Some(3)));
        assert!(h.p50.is_some_and(|v| (v - 2.0).abs() < 1e-12) && h.p99.is_none());
        assert!(s.hop(Hop::TickLateness).p50.is_none() && s.stage(Stage::Law).is_none());
        assert!(s.faults.is_empty() && s.incidents.is_none() && s.flight.is_none());
        assert_eq!(s.text("dt").as_deref(), Some("0.001"));
        patch(dir.path(), |j| j["warnings"] = serde_json::json!(["w"])).expect("patch");
        assert_eq!(Summary::read(dir.path()).expect("patched").warnings, ["w"]);
        for bad in ["{\"ticks\": ", r#"{"ticks": "many"}"#, "5"] {
            write(bad);
            let e = Summary::read(dir.path()).expect_err(bad).to_string();
            assert!(e.contains("summary.json is not a run's summary: "), "{bad}: {e}");
        }
    }
}
