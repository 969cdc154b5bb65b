//! The controller: its laws behind one interface ([`law::Law`]: the paper's geometric PID
//! first), what it decides beyond the law ([`policy`]: pairing a state with its
//! reference, holding a missing one, skipping and answering again) and the `controller`
//! process around them ([`process`]). No IPC and no clock in the laws: the caller passes
//! the state, the reference and `dt`.

pub mod law;
pub mod policy;
pub mod process;

/// This crate's role in the loop, by name (its node, resume slot and flight record).
pub const ROLE: &str = rotorloop_common::graph::Role::Controller.name();
