//! The four roles of the loop live in their own crates, each with its mathematics, its
//! policy (the rules, as plain tested structs) and its process shell:
//! [`plant`] (`rotorloop_plant::process`), [`controller`], [`reference`], [`monitor`].
//! What every role shares (arguments, start, counting, ending, fault injection) is in
//! `rotorloop_common::role`, re-exported here. This module adds what only the root
//! crate runs: the bench's ping-pong baselines ([`pingpong`]) and the access probe
//! ([`probe`]).

pub mod pingpong;
pub mod probe;

pub use rotorloop_common::role::*;
pub use rotorloop_controller::process as controller;
pub use rotorloop_monitor::process as monitor;
pub use rotorloop_plant::process as plant;
pub use rotorloop_reference::process as reference;
