//! What a run will write, said before it starts: `rotorloop run` prints an estimate of the
//! disk space of its output and of the RAM its flight rings take on tmpfs, and refuses to
//! start (exit 2) when the output's filesystem or `/dev/shm` cannot hold it, unless
//! `--force` is given (a disk that fills up mid-run stops the files, never the loop).
//!
//! The estimate is per tick of the run: the flight records (the ring moved in beside its
//! segments at its raw size, an upper bound: it is packed as it is moved where it was
//! staged on tmpfs, a slot of each stream a tick, [`flight::bytes_per_tick`]; the packed
//! segments at [`PACKED_PERCENT`] of that), the report's files by what they measured on
//! runs of this build (docs/measurements.md, "A run's disk and memory"), rounded up:
//! `trace.csv` 800 B, `run.mcap` 1000 B (its overview, for a run of an hour of ticks or
//! more, 25 B), `timing.csv` 60 B a tick, `sched.csv` 100 kB a second of wall time (30 kB
//! compressed, `--no-csv`).

use std::path::Path;

use rotorloop_common::flight::{self, DEFAULT_RING_TICKS};
use rotorloop_common::role::UsageError;
use rotorloop_common::scenario::Scenario;

use crate::export::mcap::LONG_RUN_TICKS;
use crate::run::args::RunArgs;

/// `trace.csv`'s bytes per tick (measured: 783 on `paper-sinusoid`, rounded up).
const TRACE_PER_TICK: u64 = 800;
/// `run.mcap`'s bytes per tick (measured: 983).
const MCAP_PER_TICK: u64 = 1000;
/// An overview `run.mcap`'s bytes per tick (from [`LONG_RUN_TICKS`] on): measured 11.0 on
/// a 6 000 s lockstep run without incidents, and the incidents' ticks at full rate, at
/// most a hundredth of the run's, add at most 10.
const MCAP_OVERVIEW_PER_TICK: u64 = 25;
/// `timing.csv`'s bytes per tick (measured: 51).
const TIMING_PER_TICK: u64 = 60;
/// A packed segment's bytes, in percent of its raw slots (measured: 24 on the one-hour
/// soak of `paper-sinusoid`, 281 of 1176 bytes a tick; rounded up, as data noisier than a
/// smooth trajectory packs less).
pub const PACKED_PERCENT: u64 = 30;
/// `sched.csv`'s bytes per second of the run (a row per role when its state changed,
/// sampled every millisecond: at most about 280 kB if every role changed every
/// millisecond; measured 26–29 kB in the one-hour real-time soaks, 2.8 kB in lockstep).
const SCHED_PER_S: u64 = 100_000;
/// `sched.csv.zst`'s (`--no-csv`): zstd left 26 % of the one-hour soak's 128.5 MB.
const SCHED_ZST_PER_S: u64 = 30_000;

/// From this many seconds on, `run` says what `--no-csv --no-mcap` would write instead.
const LONG_RUN_S: f64 = 600.0;

/// A run's output, estimated before it starts (bytes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Estimate {
    /// Into `--out`: the records, the report's files, `run.mcap`.
    pub out: u64,
    /// Of that, the flight records.
    pub flight: u64,
    /// On tmpfs while the run goes on: the rings.
    pub staging: u64,
}

/// The estimate for `args` running `scenario`.
pub fn estimate(args: &RunArgs, scenario: &Scenario) -> Estimate {
    let ticks = scenario.ticks();
    let per_tick = flight::bytes_per_tick();
    let ring = flight::ring_capacity(ticks, args.role.flight_ring_ticks.max(1));
    let (flight, staging) = match args.no_record {
        true => (0, 0),
        // Every tick in a segment, and the ring moved in beside them at the end (at most
        // its raw size).
        false if flight::ring_wraps(ticks, ring) => {
            (ticks * per_tick / 100 * PACKED_PERCENT + ring * per_tick, ring * per_tick)
        }
        false => (ring * per_tick, ring * per_tick),
    };
    let report = match args.no_monitor || args.no_csv {
        true => 0,
        false => ticks * (TRACE_PER_TICK + TIMING_PER_TICK),
    };
    let mcap = match (args.no_mcap || args.no_monitor, ticks >= LONG_RUN_TICKS) {
        (true, _) => 0,
        (false, true) => ticks * MCAP_OVERVIEW_PER_TICK,
        (false, false) => ticks * MCAP_PER_TICK,
    };
    let seconds = (ticks as f64 * scenario.dt()).ceil() as u64;
    let sched = match (args.no_sched_sample, args.no_csv) {
        (true, _) => 0,
        (false, true) => seconds * SCHED_ZST_PER_S,
        (false, false) => seconds * SCHED_PER_S,
    };
    let out = flight.saturating_add(report).saturating_add(mcap).saturating_add(sched);
    Estimate { out, flight, staging }
}

fn size(bytes: u64) -> String {
    match bytes {
        b if b >= 10_000_000_000 => format!("{:.0} GB", b as f64 / 1e9),
        b if b >= 1_000_000_000 => format!("{:.1} GB", b as f64 / 1e9),
        b => format!("{:.0} MB", (b as f64 / 1e6).ceil()),
    }
}

/// Says what the run will write (unless `--quiet`) and refuses it where it cannot fit.
pub fn check(args: &RunArgs, scenario: &Scenario) -> anyhow::Result<()> {
    let e = estimate(args, scenario);
    let seconds = scenario.file.run.duration_s;
    if !args.quiet {
        eprintln!(
            "run: {seconds} s at {} Hz writes about {} into {} (flight records {}), and \
             takes {} of /dev/shm while it runs",
            scenario.file.run.rate_hz,
            size(e.out),
            args.out.display(),
            size(e.flight),
            size(e.staging)
        );
        // A long run with the short run's files: say what the long run's output takes
        // (from an hour of ticks on, `run.mcap` is an overview, and kept).
        let overview = scenario.ticks() >= LONG_RUN_TICKS;
        let no_mcap = args.no_mcap || !overview;
        let long = RunArgs { no_csv: !args.no_record, no_mcap, ..args.clone() };
        let lean = estimate(&long, scenario);
        if seconds >= LONG_RUN_S && lean.out < e.out / 2 {
            let flags = if no_mcap { "--no-csv --no-mcap" } else { "--no-csv" };
            eprintln!(
                "run: with {flags} it would write about {} (trace.csv, timing.csv and a full \
                 run.mcap derived from the records when wanted: docs/running.md)",
                size(lean.out)
            );
        }
    }
    let places = [(args.out.as_path(), e.out, "--out"), (Path::new("/dev/shm"), e.staging, "")];
    for (path, need, flag) in places {
        let Some(free) = crate::doctor::probe::free_bytes(path) else { continue };
        if need <= free {
            continue;
        }
        let what = if flag.is_empty() { "its flight rings need" } else { "its output needs" };
        let msg = format!(
            "--duration {seconds} s at {} Hz: {what} about {} in {} ({} free there); \
             shorten the run, {}or give --force to run anyway (a full disk stops the files, \
             never the loop)",
            scenario.file.run.rate_hz,
            size(need),
            path.display(),
            size(free),
            if flag.is_empty() {
                format!("take smaller rings (--flight-ring-ticks, default {DEFAULT_RING_TICKS}), ")
            } else {
                "point --out at a larger disk, ".to_owned()
            }
        );
        if !args.force {
            return Err(UsageError(msg).into());
        }
        eprintln!("warning (--force): {msg}");
    }
    Ok(())
}
