//! `reference` arguments (the same for the `reference` binary and `rotorloop role
//! reference`).

use clap::Args;
use rotorloop_common::role::{Corrupt, RoleArgs};

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
