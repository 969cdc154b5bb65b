//! `reference` arguments (the same for the `reference` binary and `rotorloop role
//! reference`).

use clap::Args;
use rotorloop_common::ipc::{REFERENCE_LEAD, Wait};
use rotorloop_common::role::{Corrupt, Mode, RoleArgs};

/// `reference` arguments.
#[derive(Debug, Clone, Args)]
pub struct ReferenceArgs {
    #[command(flatten)]
    pub role: RoleArgs,
    /// Fault injection: publish this tick's sample corrupted (`nan@TICK`, `inf@TICK`,
    /// `huge@TICK`, `skew@TICK`). Repeatable. Set by `rotorloop run --corrupt`.
    #[arg(long)]
    pub corrupt: Vec<Corrupt>,
}

impl ReferenceArgs {
    /// How the reference waits for states of ticks `dt` apart. In real time it looks every
    /// quarter of its lead and nobody wakes it: a listener would make the plant's every
    /// notify wake a third process, on the plant's core or the controller's (the stage
    /// breakdown measured that notify at 8–17 µs p50 on 2 vCPUs). In lockstep (which
    /// runs as fast as the processes go) and with `--plain-hot-path` it listens.
    pub fn wait(&self, dt: f64) -> Wait {
        if self.role.mode == Mode::Realtime && !self.role.plain_hot_path {
            let period_ns = (REFERENCE_LEAD as f64 * dt / 4.0 * 1e9) as u64;
            Wait::Poll { period_ns: period_ns.clamp(50_000, 10_000_000) }
        } else {
            Wait::Event
        }
    }
}
