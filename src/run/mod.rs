//! `rotorloop run`: the four processes started, pinned, supervised and ended.
//!
//! - [`launch`]: the launcher: arguments, start order, the supervision loop that spawns,
//!   signals and reaps, and the end of a run (the report, the flight records moved);
//! - [`supervise`]: the launcher's decisions as plain structs with the time passed in:
//!   restart policy and intensity, the watchdog and its blame rule, the link rule of a
//!   split run;
//! - [`fault`]: fault kinds (`--fault`), their schedule, a fault as it happened, and the
//!   fault report;
//! - [`split`]: a loop over two hosts joined by link gateways (`--split`);
//! - [`recover`]: `rotorloop recover`, the report of a run whose launcher was killed.

pub mod fault;
pub mod launch;
pub mod recover;
pub mod split;
pub mod supervise;
