//! The four processes of the loop: thin shells that receive, step the library structs,
//! and publish. Each role has the same life: create every resource up front, loop until
//! the run ends or SIGINT/SIGTERM, then drop cleanly so iceoryx2 removes what it made.
//!
//! Ending without losing data: when a role has done its last tick it first drops its
//! subscribers, then keeps its publisher until nobody subscribes to it any more (at most
//! [`LINGER_S`] seconds), so every sample it published can still be read.

pub mod controller;
pub mod monitor;
pub mod pingpong;
pub mod plant;
pub mod reference;

use std::time::Duration;

use clap::{Args, ValueEnum};
use rotorloop_common::ipc::{RtSetup, Wait, now_ns, shutdown_requested};
use rotorloop_common::{Actuation, Scenario};

use crate::UsageError;
use crate::sim::scenario_with_overrides;

/// Longest a finished role waits for its subscribers to leave (s).
pub const LINGER_S: u64 = 10;

/// Lockstep or real time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Mode {
    /// The plant does not step tick k until torque k has arrived: deterministic, as fast
    /// as the processes go, trace identical to `rotorloop sim`.
    Lockstep,
    /// The plant ticks on an absolute time grid and holds the last torque when a fresh one
    /// is late (a miss).
    Realtime,
}

/// Arguments every role takes. The launcher passes the same ones to all four.
#[derive(Debug, Clone, Args)]
pub struct RoleArgs {
    /// Run domain: services and shared memory of different domains never meet
    /// [default: `default` for a role started by hand, `run-<pid>` for `rotorloop run`].
    #[arg(long)]
    pub domain: Option<String>,
    /// Built-in scenario name or TOML path (every role reads the same one).
    #[arg(long)]
    pub scenario: String,
    /// Simulated seconds [default: the scenario's].
    #[arg(long, allow_negative_numbers = true)]
    pub duration: Option<f64>,
    /// Tick rate in Hz [default: the scenario's].
    #[arg(long, allow_negative_numbers = true)]
    pub rate: Option<f64>,
    /// `internal` or `external` [default: the scenario's].
    #[arg(long)]
    pub actuation: Option<Actuation>,
    /// `lockstep` or `realtime`.
    #[arg(long, value_enum, default_value_t = Mode::Lockstep)]
    pub mode: Mode,
    /// How to wait for input: `event` (block), `spin` (busy-poll), `hybrid` (spin 50 µs, then block).
    #[arg(long, default_value = "event")]
    pub wait: Wait,
    /// Pin the process to this core.
    #[arg(long)]
    pub core: Option<usize>,
    /// SCHED_FIFO priority 1–99 (a warning and the default policy when not permitted).
    #[arg(long, value_parser = clap::value_parser!(i32).range(1..=99))]
    pub rt_priority: Option<i32>,
    /// Lock the process's memory (mlockall).
    #[arg(long)]
    pub mlock: bool,
}

impl RoleArgs {
    /// The validated scenario with the overrides.
    pub fn scenario(&self) -> Result<Scenario, UsageError> {
        scenario_with_overrides(&self.scenario, self.duration, self.rate, self.actuation)
    }

    /// The run domain (`default` unless given).
    pub fn domain(&self) -> &str {
        self.domain.as_deref().unwrap_or("default")
    }

    /// The run domain, validated.
    pub fn open_domain(&self) -> Result<rotorloop_common::ipc::Domain, UsageError> {
        rotorloop_common::ipc::Domain::new(self.domain()).map_err(|e| UsageError(e.to_string()))
    }

    /// Applies pinning, priority and mlock; prints a warning for each refusal.
    pub fn setup(&self, role: &str) {
        let rt = RtSetup { core: self.core, rt_priority: self.rt_priority, mlock: self.mlock };
        for w in rt.apply(role) {
            eprintln!("warning: {w}");
        }
    }

    /// The arguments as a command line (for the launcher).
    pub fn to_args(&self) -> Vec<String> {
        let mut a = vec![
            "--domain".into(),
            self.domain().to_owned(),
            "--scenario".into(),
            self.scenario.clone(),
            "--mode".into(),
            match self.mode {
                Mode::Lockstep => "lockstep".into(),
                Mode::Realtime => "realtime".into(),
            },
            "--wait".into(),
            self.wait.to_string(),
        ];
        if let Some(d) = self.duration {
            a.extend(["--duration".into(), d.to_string()]);
        }
        if let Some(r) = self.rate {
            a.extend(["--rate".into(), r.to_string()]);
        }
        if let Some(x) = self.actuation {
            a.extend(["--actuation".into(), x.to_string()]);
        }
        if let Some(c) = self.core {
            a.extend(["--core".into(), c.to_string()]);
        }
        if let Some(p) = self.rt_priority {
            a.extend(["--rt-priority".into(), p.to_string()]);
        }
        if self.mlock {
            a.push("--mlock".into());
        }
        a
    }
}

/// Waits until `done()` or [`LINGER_S`] seconds or a termination signal.
pub fn linger(mut done: impl FnMut() -> bool) {
    let until = now_ns() + LINGER_S * 1_000_000_000;
    while !done() && now_ns() < until && !shutdown_requested() {
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// Counts samples received and samples lost (gaps in the tick sequence) on one subscriber.
#[derive(Debug, Clone, Copy, Default)]
pub struct SeqCounter {
    /// Samples of new ticks taken.
    pub received: u64,
    /// Ticks skipped between consecutive samples.
    pub lost: u64,
    /// Samples of a tick already seen (a restarted publisher repeating its last one).
    pub repeated: u64,
    last: Option<u64>,
}

impl SeqCounter {
    /// Accounts for a sample of tick `tick`. Repeated or older ticks (a restarted
    /// publisher re-sending its last sample) count as repeated, not received.
    #[inline]
    pub fn see(&mut self, tick: u64) {
        match self.last {
            Some(last) if tick <= last => self.repeated += 1,
            Some(last) => {
                self.received += 1;
                self.lost += tick - last - 1;
                self.last = Some(tick);
            }
            None => {
                self.received += 1;
                self.last = Some(tick);
            }
        }
    }

    /// Continue counting after `last` (a restarted subscriber).
    pub fn resume(received: u64, lost: u64, last: u64) -> Self {
        Self { received, lost, repeated: 0, last: Some(last) }
    }

    /// The newest tick seen.
    pub fn last(&self) -> Option<u64> {
        self.last
    }
}

/// `main` of a role binary: parse arguments, install signal handlers, run, print the
/// error chain, and return the exit code (2 for bad arguments or scenario values).
pub fn role_main<A: clap::Args + clap::FromArgMatches>(
    name: &'static str,
    run: fn(&A) -> anyhow::Result<()>,
) -> std::process::ExitCode {
    let cmd = A::augment_args(clap::Command::new(name));
    let matches = cmd.get_matches();
    let args = match A::from_arg_matches(&matches) {
        Ok(a) => a,
        Err(e) => e.exit(),
    };
    run_role(name, &args, run)
}

/// Runs a role with signal handling and error reporting (shared by the role binaries
/// and `rotorloop role`).
pub fn run_role<A>(
    name: &str,
    args: &A,
    run: fn(&A) -> anyhow::Result<()>,
) -> std::process::ExitCode {
    rotorloop_common::ipc::install_signal_handlers();
    rotorloop_common::ipc::quiet_iceoryx_logs();
    match run(args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("{name}: error: {e:#}");
            if e.downcast_ref::<UsageError>().is_some() {
                std::process::ExitCode::from(2)
            } else {
                std::process::ExitCode::FAILURE
            }
        }
    }
}
