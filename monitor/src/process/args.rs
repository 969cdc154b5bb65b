//! `monitor` arguments (the same for the `monitor` binary and `rotorloop role monitor`).

use std::path::PathBuf;

use clap::Args;
use rotorloop_common::role::args::RoleArgs;

impl MonitorArgs {
    /// Refuses what cannot be honoured: `--no-csv` without the flight records.
    pub fn check(&self) -> Result<(), rotorloop_common::role::UsageError> {
        if self.no_csv && self.role.record.is_none() {
            return Err(rotorloop_common::role::UsageError(
                "--no-csv needs the flight records (--record DIR): without them the trace \
                 would be lost"
                    .into(),
            ));
        }
        Ok(())
    }
}

/// `monitor` arguments.
#[derive(Debug, Clone, Args)]
pub struct MonitorArgs {
    /// What every role takes (scenario, mode, domain, wait, core, records).
    #[command(flatten)]
    pub role: RoleArgs,
    /// Output directory for trace, histograms, logs, plots and summary.
    #[arg(long)]
    pub out: PathBuf,
    /// Write no `trace.csv` or `timing.csv`: a long run's output (`rotorloop export OUT
    /// --csv` derives them from the flight records, which `sim --replay` and `export
    /// --mcap` read directly). Needs the flight records (`--record`).
    #[arg(long)]
    pub no_csv: bool,
    /// Print a live status line on stderr.
    #[arg(long)]
    pub status: bool,
    /// Poll period (µs), 50 to 100000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 2000, value_parser = rotorloop_common::input::whole_in(50u64, 100_000, "µs"))]
    pub poll_us: u64,
    /// The host of each role when the run spans hosts (`plant=a,controller=b,…`): hops
    /// between two hosts' clocks are then left out (`rotorloop run --split` sets it).
    #[arg(long, value_parser = crate::hosts::Hosts::parse)]
    pub hosts: Option<crate::hosts::Hosts>,
}
