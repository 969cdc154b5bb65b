//! `reference` arguments (the same for the `reference` binary and `rotorloop role
//! reference`).

use clap::Args;
use rotorloop_common::ipc::wait::Wait;
use rotorloop_common::role::args::{Mode, RoleArgs};
use rotorloop_common::role::inject::Corrupt;
use rotorloop_common::wire::REFERENCE_LEAD;

/// `reference` arguments.
#[derive(Debug, Clone, Args)]
pub struct ReferenceArgs {
    /// What every role takes (scenario, mode, domain, wait, core, records).
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

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: ReferenceArgs,
    }

    fn args(extra: &[&str]) -> ReferenceArgs {
        let line = ["reference", "--scenario", "paper-zero"].iter().chain(extra);
        Cli::parse_from(line).args
    }

    #[test]
    fn the_realtime_reference_polls_a_quarter_of_its_lead_and_lockstep_listens() {
        let rt = args(&["--mode", "realtime"]);
        // 16 ticks of 1 ms ahead: a look every 4 ms, no listener for the plant to wake.
        assert_eq!(rt.wait(1e-3), Wait::Poll { period_ns: 4_000_000 });
        assert!(!rt.wait(1e-3).listens());
        assert_eq!(rt.wait(1e-6), Wait::Poll { period_ns: 50_000 }, "never busier than 20 kHz");
        assert_eq!(rt.wait(1.0), Wait::Poll { period_ns: 10_000_000 }, "signals seen in 10 ms");
        assert_eq!(args(&["--mode", "lockstep"]).wait(1e-3), Wait::Event);
        assert_eq!(args(&["--mode", "realtime", "--plain-hot-path"]).wait(1e-3), Wait::Event);
    }
}
