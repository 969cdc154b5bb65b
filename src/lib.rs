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
pub mod margin;
pub mod montecarlo;
pub mod observe;
pub mod paper;
pub mod process;
pub mod recover;
pub mod replay;
pub mod sim;
pub mod split;
pub mod supervise;

pub use closed_loop::ClosedLoop;

pub use rotorloop_common::role::UsageError;
