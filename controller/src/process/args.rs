//! `controller` arguments (the same for the `controller` binary and `rotorloop role
//! controller`).

use clap::Args;
use rotorloop_common::role::args::RoleArgs;
use rotorloop_common::role::inject::Corrupt;

use crate::policy::InjectedDelay;

/// `controller` arguments.
#[derive(Debug, Clone, Args)]
pub struct ControllerArgs {
    /// What every role takes (scenario, mode, domain, wait, core, records).
    #[command(flatten)]
    pub role: RoleArgs,
    /// Fault injection: publish this tick's sample corrupted (`nan@TICK`, `inf@TICK`,
    /// `huge@TICK`, `skew@TICK`). Repeatable. Set by `rotorloop run --corrupt`.
    #[arg(long)]
    pub corrupt: Vec<Corrupt>,
    /// Fault injection: send the answers to states of times FROM to UNTIL (s) SECONDS late
    /// (`FROM=SECONDS[:UNTIL]`; repeatable). Set by `rotorloop run --fault
    /// controller:delay@T=SECONDS[:until@T2]`.
    #[arg(long)]
    pub inject_delay: Vec<InjectedDelay>,
    /// Real time: ticks to propagate the last reference when it is missing, 0 to 1000000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 1000,
          value_parser = rotorloop_common::role::args::hold_ticks())]
    pub reference_hold_ticks: u64,
}
