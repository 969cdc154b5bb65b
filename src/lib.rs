//! rotorloop: attitude tracking of a rigid body with three internal rotors, run as four
//! processes (plant, reference, controller, monitor) over iceoryx2 shared memory, or in
//! one process faster than real time.
//!
//! The four roles live in their own crates (`rotorloop_plant`, `rotorloop_reference`,
//! `rotorloop_controller`, `rotorloop_monitor`), each with its mathematics, its policy
//! (the rules, as plain tested structs) and its process shell; what they share is in
//! `rotorloop_common`. This crate is the user's entry point (the `rotorloop` binary,
//! [`cli`]) and holds what combines the roles, one room per application:
//!
//! - [`run`]: `rotorloop run` and what keeps a run honest: the launcher, supervision
//!   (restart policy, watchdog), cross-host placement (`--split`), recovery of a run
//!   whose launcher was killed, and [`run::fault`], the one home of fault kinds;
//! - [`sim`]: the loop in one process ([`sim::closed_loop`]), `rotorloop sim` and its
//!   report, and `--replay` of a real-time run from its flight records;
//! - [`study`]: what is computed from many runs: the paper's gain analysis, the delay
//!   margin, Monte Carlo of almost-global convergence, the paper's scenarios, and the
//!   latency bench;
//! - [`cpus`]: which CPUs a run or a bench's loops get (CPU lists, the process's CPU set,
//!   isolated CPUs, SMT siblings, disjoint placement), beneath `run`, `study` and `doctor`;
//! - [`doctor`]: `rotorloop doctor`, what this machine allows a real-time loop (also
//!   `doctor.json` in every run and bench directory);
//! - [`observe`]: `rotorloop ps` and `watch`, which see a live loop without touching it;
//! - [`pipeline`]: after the last tick, what turns a run's records into its analyses
//!   and files: the incidents (why a tick was late, what it cost) and `run.mcap`; beneath
//!   both `run` and `study`, so neither imports the other's callers;
//! - [`export`]: a finished run as an MCAP file for Foxglove (`rotorloop export`, and
//!   at the end of every `run`);
//! - [`baseline`]: what the bench compares the loop with (ping-pong over atomics, bare
//!   iceoryx2 and Unix sockets) and the access probe of the security tests.

pub mod baseline;
pub mod cli;
pub mod cpus;
pub mod doctor;
pub mod export;
pub mod observe;
pub mod pipeline;
pub mod run;
pub mod sim;
pub mod study;
