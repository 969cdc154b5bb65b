//! After the last tick: what turns a finished run's records into its analyses and files,
//! in a room beneath both [`crate::run`] (which calls [`finish`] at the end of every run
//! and in `rotorloop recover`) and [`crate::study`] (whose bench and paper study call the
//! launcher, and read what it wrote). Nothing here imports `run` or `study`, so the two no
//! longer import each other (a test of the crate's layout checks it).
//!
//! - [`incidents`]: why a run's ticks were late, and what it cost (also `rotorloop
//!   explain`);
//! - [`sched_csv`]: the format of `sched.csv`, which the launcher's sampler writes and the
//!   incidents read;
//! - [`finish`]: the steps after the last tick that read the records (the incidents, then
//!   `run.mcap`).

use std::path::Path;

pub mod incidents;

/// The format of `OUT/sched.csv` (written by `crate::run::sched`, read by [`incidents`]).
pub mod sched_csv {
    /// How often each role is looked at (ns).
    pub const PERIOD_NS: u64 = 1_000_000;

    /// The header of `sched.csv`.
    pub const HEADER: &str = "t_ns,role,pid,state,cpu,on_cpu_ns,wait_ns,steal_ns";

    /// The file's name.
    pub const FILE: &str = "sched.csv";
    /// Its name compressed with zstd (`run --no-csv`).
    pub const ZST: &str = "sched.csv.zst";

    /// The run directory `dir`'s scheduler samples: `sched.csv`, else `sched.csv.zst`
    /// (the plain one where neither is there).
    pub fn path(dir: &std::path::Path) -> std::path::PathBuf {
        let zst = dir.join(ZST);
        if !dir.join(FILE).exists() && zst.exists() { zst } else { dir.join(FILE) }
    }
}

/// Which steps [`finish`] takes.
#[derive(Debug, Clone, Copy)]
pub struct Steps {
    /// Find the run's incidents, their causes and costs (`incidents.md`, `summary.json`).
    pub incidents: bool,
    /// Write `run.mcap`.
    pub mcap: bool,
    /// Print only warnings.
    pub quiet: bool,
}

/// The steps after the last tick of the finished run in `out`, each reading its records a
/// block at a time: the incidents (printed as the worst one), then `run.mcap` (which shows
/// them). A step that fails says why on stderr; the run's other files stay as they are.
pub fn finish(out: &Path, steps: Steps) {
    if !out.join("summary.json").exists() {
        return;
    }
    if steps.incidents {
        match incidents::explain_yielding(out, incidents::Options::default()) {
            Ok(found) if !steps.quiet => println!("incidents: {}", found.describe_worst()),
            Ok(_) => {}
            Err(e) => eprintln!("warning: no incidents report: {e:#}"),
        }
    }
    if steps.mcap {
        crate::export::mcap_after_run(out, steps.quiet);
    }
}
