//! rotorloop: attitude tracking of a rigid body with three internal rotors.
//!
//! This crate is the user's entry point (`rotorloop` binary) and holds what combines the
//! role crates: the closed loop in one process ([`closed_loop`]), the `sim` command and
//! its report ([`sim`]), the paper's gain analysis ([`gains`]) and the Monte Carlo study
//! of almost-global convergence ([`montecarlo`]).

pub mod bench;
pub mod cli;
pub mod closed_loop;
pub mod faults;
pub mod gains;
pub mod launch;
pub mod montecarlo;
pub mod paper;
pub mod process;
pub mod sim;

pub use closed_loop::ClosedLoop;

/// An error the user caused (bad argument or scenario value): exit code 2.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct UsageError(pub String);

impl From<rotorloop_common::ScenarioError> for UsageError {
    fn from(e: rotorloop_common::ScenarioError) -> Self {
        Self(e.to_string())
    }
}
