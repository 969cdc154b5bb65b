//! What the bench measures: its arguments, its cells (rate × wait × placement × load), the
//! cells it cannot measure on this machine and why, and one measured row.

use std::path::PathBuf;

use clap::Args;

use crate::cpus::{Shape, Topology, place};
use rotorloop_common::ipc::wait::Wait;

use rotorloop_common::role::UsageError;

/// What `bench --before-after` compares.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BeforeAfter {
    /// Without and with the flight recorders.
    Record,
    /// Without and with `run --foxglove` and a viewer subscribed to every topic.
    Foxglove,
    /// Without and with the launcher's sampling of each role's scheduling (`sched.csv`,
    /// the default; `run --no-sched-sample` without).
    Sched,
    /// Without and with `run --trace-sched` (root).
    TraceSched,
    /// The hot path before and after its overhead was cut (`run --plain-hot-path`
    /// before: the reference woken by every state, the reference topic read every tick,
    /// the samples loaned and the plant's state made after the wake).
    HotPath,
    /// Raw and packed flight segments (`run --raw-segments` before), both sides with
    /// rings of 4096 ticks so that the launcher moves (and packs) a half every 2048 ticks.
    Pack,
    /// The plant's tick loop without and with the lockstep fault gate's check (`run
    /// --no-gate` before): one comparison of two integers a tick, in real time too.
    Gate,
    /// Without and with the journal of the newest ticks, made durable every 200 ms
    /// (`run --no-journal` before).
    Journal,
}

/// `rotorloop bench` arguments.
#[derive(Debug, Clone, Args)]
pub struct BenchArgs {
    /// Tick rates (Hz).
    #[arg(
        long,
        allow_hyphen_values = true,
        value_delimiter = ',',
        default_value = "1000,2000,5000,10000,20000",
        value_parser = rotorloop_common::role::args::rate_hz()
    )]
    pub rates: Vec<f64>,
    /// Wait strategies.
    #[arg(long, value_delimiter = ',', default_value = "event,spin,hybrid")]
    pub wait: Vec<Wait>,
    /// Core placements of plant and controller: same-core, cross-core, unpinned,
    /// dedicated (every role on its own core, all spinning: `rotorloop run --preset
    /// dedicated`; needs 4 cores, measured once per rate whatever `--wait` says), or
    /// cross-host (unpinned, the controller on another "host" joined by two link gateways
    /// over Zenoh on loopback: `rotorloop run --split`; needs `rotorloop-link`).
    #[arg(long, value_delimiter = ',', default_value = "same-core,cross-core,unpinned")]
    pub placement: Vec<String>,
    /// Seconds per measurement, 0.05 to 3600.
    #[arg(long, allow_hyphen_values = true, default_value_t = 3.0,
          value_parser = rotorloop_common::input::number_in(0.05, 3600.0, "seconds"))]
    pub seconds: f64,
    /// Load: none, or other-core (a CPU hog on the core the loop is not pinned to).
    #[arg(long, value_delimiter = ',', default_value = "none")]
    pub load: Vec<String>,
    /// Baselines: atomic, iceoryx2, uds, timer (a bare thread sleeping to the plant's grid
    /// on its core, with its priority: what the kernel allows the plant's tick).
    #[arg(long, value_delimiter = ',', default_value = "atomic,iceoryx2,uds")]
    pub baselines: Vec<String>,
    /// SCHED_FIFO priority of every role of the loop and of the timer baseline (default:
    /// the normal policy), 1 to 99.
    #[arg(long, allow_hyphen_values = true,
          value_parser = rotorloop_common::role::args::rt_priority())]
    pub rt_priority: Option<i32>,
    /// The plant sleeps until this many µs before each tick and spins the rest, 0 to
    /// 1000000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 0,
          value_parser = rotorloop_common::role::args::spin_us())]
    pub spin_before_tick_us: u64,
    /// Hold `/dev/cpu_dma_latency` at this many µs for the whole invocation (the loop and every baseline): no CPU enters an idle
    /// state that takes longer to leave (0: idle CPUs poll instead of halting, as
    /// cyclictest asks by default; sharper timer wake-ups on a VM, idle cores kept busy).
    /// Needs root; without it a warning, and the idle states stay as they are. 0 to
    /// 1000000.
    #[arg(long, allow_hyphen_values = true,
          value_parser = rotorloop_common::role::args::dma_latency_us())]
    pub cpu_dma_latency: Option<u32>,
    /// Also run each loop cell without the monitor and report the change of the
    /// plant-measured sense-to-actuate p50 (`loop-nomon` rows).
    #[arg(long)]
    pub monitor_cost: bool,
    /// Also run each loop cell before and after a change, in the same invocation:
    /// `record` (the default) without the flight recorders and with them (`loop-before`
    /// rows; `rotorloop run --no-record`); `foxglove` without and with the live Foxglove
    /// server (`run --foxglove`) and a viewer subscribed to every topic
    /// (`loop-foxglove` rows); `sched`, `trace-sched`; `hot-path` the hot path before
    /// its overhead was cut (`run --plain-hot-path`, `loop-plain` rows) and after; `pack`
    /// rings of 4096 ticks moved raw (`run --raw-segments`, `loop-raw` rows) and packed
    /// (`loop-packed` rows); `gate` the plant's tick loop without the lockstep fault
    /// gate's check (`loop-nogate` rows) and with it; `journal` without the durable
    /// journal of the newest ticks (`run --no-journal`, `loop-nojournal` rows) and with it.
    #[arg(long, num_args = 0..=1, default_missing_value = "record", value_name = "CHANGE")]
    pub before_after: Option<BeforeAfter>,
    /// With `--before-after`: measure before and after this many times each, alternating
    /// (before, after, before, …), and report the run with the median p50 of each (the
    /// difference between two runs of one loop here is often larger than the change), 1 to
    /// 99.
    #[arg(long, allow_hyphen_values = true, default_value_t = 1,
          value_parser = rotorloop_common::input::whole_in(1u64, 99, "pairs"))]
    pub pairs: u64,
    /// Scale: also run 2, 4, … up to N independent loops (domains) at once per cell, each
    /// with its own four processes (`-xN` cells, a `loop-I` row per loop), and report the
    /// largest N at which every loop has no more misses than the bare iceoryx2 baseline.
    /// 1 to 64.
    #[arg(long, allow_hyphen_values = true, default_value_t = 1,
          value_parser = rotorloop_common::input::whole_in(1usize, 64, "loops"))]
    pub loops: usize,
    /// With SMT, what the scale cells (`--loops`) do with sibling hyperthreads: `idle`
    /// (one role per physical core while the physical cores suffice) or `use` (every
    /// hyperthread a core, both hyperthreads of a physical core to the same loop). Measure
    /// both on a machine with SMT; without SMT they are the same.
    #[arg(long, value_enum, default_value = "idle")]
    pub smt: crate::cpus::Smt,
    /// Also run each loop cell with another controller (`loop-<name>` rows), against
    /// the same baselines: `mrp-pid` (the second law, Basilisk's MRP feedback, with
    /// `mrp-regulation`'s gains, on the bench's scenario) and `python` (the Python
    /// example, `examples/python/controller.py`, through `run --controller-cmd`) and `c`
    /// (the C example, `examples/c/controller.c` against the C API, built with `make`
    /// against the `librotorloop_c.so` beside this executable). The plain `loop` row is
    /// the built-in geometric PID.
    #[arg(long, value_delimiter = ',')]
    pub controllers: Vec<String>,
    /// The Python that runs the `python` controller (with `python/requirements.txt`
    /// installed).
    #[arg(long, default_value = "python3")]
    pub python: String,
    /// Measure the loop and each baseline this many times, interleaved (loop, baselines,
    /// loop, baselines, …), and give each ratio (loop / baseline p50 and p99, the plant's
    /// tick lateness / the timer's) as the median of the paired ratios with its 95 %
    /// confidence interval and a verdict (bench.csv's `…_ci_low`, `…_ci_high` columns,
    /// bench.md's "Repetitions"; 6 or more for a 95 % interval, fewer give the range and
    /// its lower level, said). 1 to 99.
    #[arg(long, allow_hyphen_values = true, default_value_t = 1,
          value_parser = rotorloop_common::input::whole_in(1usize, 99, "repeat"))]
    pub repeat: usize,
    /// Rebuild bench.md and the plots from an existing `--out` directory, measuring nothing.
    #[arg(long)]
    pub replot: bool,
    /// Scenario the loop runs.
    #[arg(long, default_value = "paper-sinusoid")]
    pub scenario: String,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
}

/// One measurement (a loop cell or a baseline), as a row of `bench.csv`.
#[derive(Debug, Clone, Default)]
pub struct Row {
    /// Cell identifier.
    pub cell: String,
    /// `loop`, `atomic`, `iceoryx2`, `uds`, `timer` (its figures: the wake-up lateness).
    pub kind: String,
    /// Rate (Hz).
    pub rate: f64,
    /// Wait strategy.
    pub wait: String,
    /// Placement.
    pub placement: String,
    /// Load.
    pub load: String,
    /// Samples.
    pub count: u64,
    /// µs.
    pub p50: f64,
    /// µs.
    pub p99: f64,
    /// µs.
    pub p99_9: f64,
    /// µs.
    pub max: f64,
    /// Ticks without a fresh answer in time.
    pub misses: u64,
    /// Achieved rate (Hz).
    pub achieved: f64,
    /// Tick lateness p99 (µs), loop only.
    pub lateness_p99: f64,
    /// Tick lateness p50 (µs), loop only.
    pub lateness_p50: f64,
    /// Tick lateness p99.9 (µs), loop only.
    pub lateness_p99_9: f64,
    /// Why the measurement was skipped, if it was.
    pub skipped: String,
    /// Tracking error at the end of the run (degrees), loop only.
    pub err_deg_final: f64,
    /// Root mean square of the tracking error over the run (degrees), loop only.
    pub err_deg_rms: f64,
    /// The controller's law stage p50 (µs), loop only: the loop's p50 less it is the
    /// loop with the law taken off ([`super::repeat`]; not in bench.csv, NaN there).
    pub law_p50: f64,
    /// Cell number (for short domain names).
    pub index: usize,
    /// Which repetition of the cell (`--repeat`), from 0.
    pub repeat: usize,
    /// On the loop rows of a cell measured more than once: the values of [`ci_columns`]
    /// (empty: none).
    pub ci: Vec<String>,
}

/// The ratios whose median over repetitions and interval the bench gives: the loop over
/// each pair baseline at p50 and p99, the plant's tick lateness over the timer's.
pub const RATIOS: [(&str, &str, &str); 8] = [
    ("loop_over_atomic_p50", "atomic", "p50"),
    ("loop_over_atomic_p99", "atomic", "p99"),
    ("loop_over_iceoryx2_p50", "iceoryx2", "p50"),
    ("loop_over_iceoryx2_p99", "iceoryx2", "p99"),
    ("loop_over_uds_p50", "uds", "p50"),
    ("loop_over_uds_p99", "uds", "p99"),
    ("plant_over_timer_lateness_p50", "timer", "p50"),
    ("plant_over_timer_lateness_p99", "timer", "p99"),
];

/// The interval columns of bench.csv: per ratio its median, interval and verdict, then
/// the interval's confidence level and the number of repetitions.
pub fn ci_columns() -> Vec<String> {
    let mut c: Vec<String> = RATIOS
        .iter()
        .flat_map(|(name, _, _)| {
            ["median", "ci_low", "ci_high", "verdict"].map(|s| format!("{name}_{s}"))
        })
        .collect();
    c.extend(["ci_level".to_owned(), "repetitions".to_owned()]);
    c
}

pub(super) const CSV_HEADER: &str = "cell,kind,rate_hz,wait,placement,load,count,p50_us,p99_us,p99_9_us,max_us,misses,achieved_rate_hz,tick_lateness_p99_us,skipped,err_deg_final,err_deg_rms,tick_lateness_p50_us,tick_lateness_p99_9_us,repeat";

/// bench.csv's header: [`CSV_HEADER`] and the interval columns.
pub(super) fn csv_header() -> String {
    format!("{CSV_HEADER},{}", ci_columns().join(","))
}

impl Row {
    /// A row of bench.csv (any of its past column counts); `None` for another line.
    pub fn parse(line: &str) -> Option<Self> {
        let f: Vec<&str> = line.split(',').collect();
        // Bench files written before `err_deg_final` have 15 columns, before `err_deg_rms`
        // 16, before the lateness p50 and p99.9 17, before `--repeat` 19.
        let full = 20 + ci_columns().len();
        if !(15..=19).contains(&f.len()) && f.len() != full {
            return None;
        }
        let num = |i: usize| f.get(i).map_or(f64::NAN, |v| v.parse::<f64>().unwrap_or(f64::NAN));
        Some(Self {
            cell: f[0].into(),
            kind: f[1].into(),
            rate: num(2),
            wait: f[3].into(),
            placement: f[4].into(),
            load: f[5].into(),
            count: f[6].parse().unwrap_or(0),
            p50: num(7),
            p99: num(8),
            p99_9: num(9),
            max: num(10),
            misses: f[11].parse().unwrap_or(0),
            achieved: num(12),
            lateness_p99: num(13),
            skipped: f[14].into(),
            err_deg_final: num(15),
            err_deg_rms: num(16),
            lateness_p50: num(17),
            lateness_p99_9: num(18),
            law_p50: f64::NAN,
            index: 0,
            repeat: f.get(19).and_then(|v| v.parse().ok()).unwrap_or(0),
            // The first ratios are empty where their baseline was not measured.
            ci: match f.len() == full && f[20..].iter().any(|v| !v.is_empty()) {
                true => f[20..].iter().map(|v| v.to_string()).collect(),
                false => Vec::new(),
            },
        })
    }

    pub(super) fn csv(&self) -> String {
        let ci = match self.ci.is_empty() {
            true => vec![String::new(); ci_columns().len()],
            false => self.ci.clone(),
        };
        let Row { cell, kind, rate, wait, placement, load, count, p50, p99, p99_9, max, .. } = self;
        let Row { misses, achieved, lateness_p99, err_deg_final, err_deg_rms, .. } = self;
        let Row { lateness_p50, lateness_p99_9, repeat, .. } = self;
        let (skipped, ci) = (self.skipped.replace(',', ";"), ci.join(","));
        format!(
            "{cell},{kind},{rate},{wait},{placement},{load},{count},{p50},{p99},{p99_9},{max},\
             {misses},{achieved},{lateness_p99},{skipped},{err_deg_final},{err_deg_rms},\
             {lateness_p50},{lateness_p99_9},{repeat},{ci}"
        )
    }
}

/// Cores of plant/controller (and ping/pong) for a placement of one loop among the CPUs
/// of `t` ([`crate::cpus::place`]); `None` = unpinned.
pub(super) fn cores(placement: &str, t: &Topology) -> Option<(usize, usize)> {
    match placement {
        "same-core" | "cross-core" => {
            place(t, 1, Shape::of_placement(placement)).loops[0].roles.map(|r| (r[0], r[1]))
        }
        "dedicated" => crate::run::args::dedicated_cores(t).ok().map(|c| (c[0], c[1])),
        _ => None, // unpinned, cross-host
    }
}

/// Why a combination cannot work on this machine, if it cannot.
pub fn skip_reason(
    kind: &str,
    wait: Wait,
    placement: &str,
    load: &str,
    ncores: usize,
) -> Option<String> {
    if placement == "dedicated" {
        return (ncores < 4)
            .then(|| format!("dedicated needs 4 cores (one per role); this machine has {ncores}"));
    }
    let spins = matches!(wait, Wait::Spin) || kind == "atomic";
    if spins && placement == "same-core" {
        return Some(
            "busy-wait with both ends on one core: each hand-off waits for a scheduler time slice"
                .into(),
        );
    }
    if spins && ncores < 2 {
        return Some(format!("busy-wait needs 2 dedicated cores; this machine has {ncores}"));
    }
    if load == "other-core" && placement != "same-core" {
        return Some("other-core load needs the loop on one core (same-core placement)".into());
    }
    if placement == "cross-host" {
        return cross_host_skip(kind, spins, ncores);
    }
    None
}

/// Why a cross-host cell cannot be measured here, if it cannot.
pub(super) fn cross_host_skip(kind: &str, spins: bool, ncores: usize) -> Option<String> {
    if kind == "atomic" || kind == "uds" {
        return Some("shared-memory atomics and a Unix socket do not cross hosts".into());
    }
    if spins && ncores < 6 {
        return Some(format!(
            "busy-wait across hosts needs a core for each role and each gateway (6); this \
             machine has {ncores}"
        ));
    }
    crate::run::split::link_binary().err().map(|e| e.0)
}

pub(super) fn validate(a: &BenchArgs) -> Result<(), UsageError> {
    for p in &a.placement {
        if !["same-core", "cross-core", "unpinned", "dedicated", "cross-host"].contains(&p.as_str())
        {
            return Err(UsageError(format!(
                "--placement `{p}` is not allowed: same-core, cross-core, unpinned, dedicated or \
                 cross-host"
            )));
        }
    }
    for l in &a.load {
        if !["none", "other-core"].contains(&l.as_str()) {
            return Err(UsageError(format!("--load `{l}` is not allowed: none or other-core")));
        }
    }
    for b in &a.baselines {
        if !["atomic", "iceoryx2", "uds", "timer"].contains(&b.as_str()) {
            return Err(UsageError(format!(
                "--baselines `{b}` is not allowed: atomic, iceoryx2, uds, timer"
            )));
        }
    }
    for c in &a.controllers {
        if !["mrp-pid", "python", "c"].contains(&c.as_str()) {
            return Err(UsageError(format!(
                "--controllers `{c}` is not allowed: mrp-pid, python, c"
            )));
        }
    }
    Ok(())
}

/// The cells to measure: rate × wait × placement × load, the dedicated preset once per
/// rate (it spins, whatever `--wait` lists).
pub(super) fn cells(a: &BenchArgs) -> Vec<(f64, Wait, String, String)> {
    let mut cells = Vec::new();
    for &rate in &a.rates {
        for &wait in &a.wait {
            for placement in &a.placement {
                // The dedicated preset spins: one cell per rate, whatever `--wait` lists.
                let wait = if placement == "dedicated" { Wait::Spin } else { wait };
                for load in &a.load {
                    let cell = (rate, wait, placement.clone(), load.clone());
                    if !cells.contains(&cell) {
                        cells.push(cell);
                    }
                }
            }
        }
    }
    cells
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A loop row's intervals survive bench.csv when the first ratios (`atomic`, not
    /// measured) are empty: `--replot` and `compare` lost them all before.
    #[test]
    fn a_rows_intervals_survive_bench_csv_when_the_first_baseline_was_not_measured() {
        let mut ci = vec![String::new(); ci_columns().len()];
        let at = |c: &str| ci_columns().iter().position(|x| x == c).expect("a column of bench.csv");
        ci[at("loop_over_iceoryx2_p50_median")] = "0.9828".into();
        ci[at("repetitions")] = "6".into();
        let row = Row { cell: "c".into(), kind: "loop".into(), repeat: 2, ci, ..Row::default() };
        let back = Row::parse(&row.csv()).expect("a bench.csv row");
        assert_eq!(back.ci, row.ci);
        assert_eq!(back.repeat, 2);
        let none = Row { ci: Vec::new(), ..row };
        assert!(Row::parse(&none.csv()).expect("a bench.csv row").ci.is_empty());
    }
}
