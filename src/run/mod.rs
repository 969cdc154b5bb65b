//! `rotorloop run`: the four processes started, pinned, supervised and ended.
//!
//! - [`launch`]: `rotorloop run` itself: the faults checked, the roles started, supervised
//!   and ended, and the report (the flight records moved, memory, faults);
//! - [`args`]: its arguments, `--preset` and `--pin`;
//! - [`spawn`]: what the launcher starts and how: each role's command line, the domains
//!   of each host, the gateways of a split run, the flight records' staging;
//! - [`supervise`]: the supervision loop while the roles run: faults applied, restarts,
//!   the watchdog, stops, the link rule, the clean end;
//! - [`policy`]: the launcher's decisions as plain structs with the time passed in:
//!   restart policy and intensity, the watchdog and its blame rule, the link rule of a
//!   split run;
//! - [`fault`]: every fault kind in one table (`--fault`), their schedule, a fault as it
//!   happened, and the fault report;
//! - [`resources`]: each role's resident memory, sampled and reported;
//! - [`member`]: a process of a run (a role, or a split run's gateway), as one type;
//! - [`split`]: a loop over two hosts joined by link gateways (`--split`);
//! - [`clean`]: `rotorloop clean`, a domain's leftovers removed and its records named;
//! - [`recover`]: `rotorloop recover`, the report of a run whose launcher was killed.

pub mod args;
pub mod budget;
pub mod clean;
pub mod external;
pub mod fault;
pub mod launch;
pub mod member;
pub mod mover;
pub mod policy;
pub mod recover;
pub mod resources;
pub mod sched;
pub mod spawn;
pub mod split;
pub mod supervise;
pub mod tracesched;
