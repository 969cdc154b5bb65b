//! The arguments every role takes ([`RoleArgs`]), the run mode, and the scenario they
//! name with the command line's overrides.

use clap::{Args, ValueEnum};

use crate::ipc::wait::Wait;
use crate::rt::RtSetup;
use crate::scenario::RunFile;
use crate::scenario::{Actuation, Scenario};

use super::UsageError;
use crate::input::{number_in, whole_in};
use crate::scenario::{DURATION_RANGE_S, RATE_RANGE_HZ};

/// `T` as the command line `args` gives it, every other option at its default: clap's,
/// the one place a default is written (for the runs `paper` and `bench` start).
pub fn with_defaults<T: Args + clap::FromArgMatches>(args: &[&str]) -> T {
    let command = T::augment_args(clap::Command::new("rotorloop"));
    let matches = command.try_get_matches_from(std::iter::once("rotorloop").chain(args.to_vec()));
    matches.and_then(|m| T::from_arg_matches(&m)).expect("the defaults of the command line")
}

/// The largest `--flight-ring-ticks` (2²⁴: about 20 GB of tmpfs for the four streams).
/// Above 2⁶³ the power of two it is rounded up to wrapped to 0, and the plant crashed.
pub const MAX_RING_TICKS: u64 = 1 << 24;

/// The parser of `--duration` (s): the range a scenario's `run.duration_s` has.
pub fn duration_s() -> impl clap::builder::TypedValueParser<Value = f64> {
    number_in(DURATION_RANGE_S.0, DURATION_RANGE_S.1, "seconds")
}

/// The parser of `--rate` (Hz): the range a scenario's `run.rate_hz` has.
pub fn rate_hz() -> impl clap::builder::TypedValueParser<Value = f64> {
    number_in(RATE_RANGE_HZ.0, RATE_RANGE_HZ.1, "Hz")
}

/// `--spin-before-tick-us` (of `run`, `bench` and the plant): 0 to 1 s.
pub fn spin_us() -> impl clap::builder::TypedValueParser<Value = u64> {
    whole_in(0u64, 1_000_000, "µs")
}

/// `--cpu-dma-latency` (of `run` and `bench`): 0 to 1 s.
pub fn dma_latency_us() -> impl clap::builder::TypedValueParser<Value = u32> {
    whole_in(0u32, 1_000_000, "µs")
}

/// `--rt-priority` (of every role, `bench` and the timer baseline): SCHED_FIFO's 1 to 99.
pub fn rt_priority() -> impl clap::builder::TypedValueParser<Value = i32> {
    whole_in(1i32, 99, "priority")
}

/// `--core` (of every role and the baselines): a CPU number, 0 to 4095.
pub fn core() -> impl clap::builder::TypedValueParser<Value = usize> {
    whole_in(0usize, 4095, "cores")
}

/// `--hold-ticks` (of `run` and the plant): 0 to a million ticks.
pub fn hold_ticks() -> impl clap::builder::TypedValueParser<Value = u64> {
    whole_in(0u64, 1_000_000, "ticks")
}

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
    /// (default: `default` for a role started by hand; for `rotorloop run`, `run-` and 7
    /// random characters, drawn again while anything of that name exists in /dev/shm).
    #[arg(long)]
    pub domain: Option<String>,
    /// The host this process runs on, when a run spans hosts joined by link gateways
    /// (`rotorloop link`): its own iceoryx2 prefix and root, so that two "hosts" on one
    /// machine share nothing but the link (default: none, this machine is the only host).
    #[arg(long)]
    pub host: Option<String>,
    /// Built-in scenario name or TOML path (every role reads the same one).
    #[arg(long)]
    pub scenario: String,
    /// Simulated seconds, 0.001 to 86400 (default: the scenario's).
    #[arg(long, allow_hyphen_values = true, value_parser = duration_s())]
    pub duration: Option<f64>,
    /// Tick rate in Hz, 1 to 100000 (default: the scenario's).
    #[arg(long, allow_hyphen_values = true, value_parser = rate_hz())]
    pub rate: Option<f64>,
    /// `internal` or `external` (default: the scenario's).
    #[arg(long)]
    pub actuation: Option<Actuation>,
    /// `lockstep` or `realtime`.
    #[arg(long, value_enum, default_value_t = Mode::Lockstep)]
    pub mode: Mode,
    /// How to wait for input: `event` (block), `spin` (busy-poll), `hybrid` (spin 50 µs, then block).
    #[arg(long, default_value = "event")]
    pub wait: Wait,
    /// Pin the process to this core (a role started by hand; `rotorloop run` pins with
    /// `--pin`).
    #[arg(long, allow_hyphen_values = true, value_parser = core())]
    pub core: Option<usize>,
    /// SCHED_FIFO priority, 1 to 99 (a warning and the default policy when not permitted).
    #[arg(long, allow_hyphen_values = true, value_parser = rt_priority())]
    pub rt_priority: Option<i32>,
    /// Lock the process's memory (mlockall).
    #[arg(long)]
    pub mlock: bool,
    /// The hot path as it was before its overhead was cut (for `rotorloop bench
    /// --before-after`): the real-time reference woken by every state, and the controller
    /// reading the reference topic every tick.
    #[arg(long, hide = true)]
    pub plain_hot_path: bool,
    /// Flight-record what this role publishes (the plant: also what it receives) into
    /// `DIR/*.flight` (`common::flight`); `rotorloop run` records into `OUT/flight`. A
    /// directory this user can write into, or a path whose nearest existing directory is
    /// one (checked before the role makes anything).
    #[arg(long, value_name = "DIR", value_parser = crate::input::dir_to_write)]
    pub record: Option<std::path::PathBuf>,
    /// Slots of each flight record's ring on tmpfs, 512 to 16777216 (rounded up to a power
    /// of two; 1224 bytes a tick for the four streams, so at most about 20 GB): the RAM the
    /// records take whatever the run's duration. A run longer than that has the finished
    /// halves moved into `OUT/flight` while it goes on.
    #[arg(long, value_name = "TICKS", default_value_t = crate::flight::DEFAULT_RING_TICKS,
          allow_hyphen_values = true,
          value_parser = whole_in(crate::flight::MIN_RING_TICKS, MAX_RING_TICKS, "ticks"))]
    pub flight_ring_ticks: u64,
    /// The launcher moves the rings' finished halves (`common::flight::Mover`): in
    /// lockstep the plant waits for it rather than let a ring come round unmoved.
    #[arg(long, hide = true)]
    pub flight_moved: bool,
    /// The tests' hooks (hidden flags).
    #[command(flatten)]
    pub hooks: super::inject::TestHooks,
}

impl RoleArgs {
    /// A real-time run of `scenario` for `duration_s` at `rate_hz` with `wait`, every other
    /// option at its command-line default (what `paper` and `bench` start).
    pub fn realtime(scenario: &str, duration_s: f64, rate_hz: f64, wait: Wait) -> Self {
        let (duration, rate, mode) = (Some(duration_s), Some(rate_hz), Mode::Realtime);
        Self { duration, rate, mode, wait, ..with_defaults(&[&format!("--scenario={scenario}")]) }
    }

    /// The validated scenario with the overrides.
    pub fn scenario(&self) -> Result<Scenario, UsageError> {
        scenario_with_overrides(&self.scenario, self.duration, self.rate, self.actuation)
    }

    /// The recorder of `stream` for this run's ticks (off without `--record`).
    pub fn flight<T: crate::flight::Record>(
        &self,
        stream: crate::flight::Stream,
        ticks: u64,
        role: &str,
    ) -> crate::flight::FlightRecorder<T> {
        let capacity = crate::flight::ring_capacity(ticks, self.flight_ring_ticks);
        crate::flight::FlightRecorder::open(self.record.as_deref(), stream, capacity, role)
    }

    /// The run domain (`default` unless given).
    pub fn domain(&self) -> &str {
        self.domain.as_deref().unwrap_or("default")
    }

    /// The run domain, validated.
    pub fn open_domain(&self) -> Result<crate::ipc::domain::Domain, UsageError> {
        crate::ipc::domain::Domain::on_host(self.domain(), self.host.as_deref())
            .map_err(|e| UsageError(e.to_string()))
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
        if let Some(h) = &self.host {
            a.extend(["--host".into(), h.clone()]);
        }
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
        if self.plain_hot_path {
            a.push("--plain-hot-path".into());
        }
        if let Some(d) = &self.record {
            a.extend(["--record".into(), d.display().to_string()]);
        }
        if self.flight_ring_ticks != crate::flight::DEFAULT_RING_TICKS {
            a.extend(["--flight-ring-ticks".into(), self.flight_ring_ticks.to_string()]);
        }
        if self.flight_moved {
            a.push("--flight-moved".into());
        }
        a.extend(self.hooks.to_args());
        a
    }
}

/// Loads a built-in scenario or a TOML file and applies the command line's overrides
/// (then validates again).
pub fn scenario_with_overrides(
    name_or_path: &str,
    duration_s: Option<f64>,
    rate_hz: Option<f64>,
    actuation: Option<Actuation>,
) -> Result<Scenario, UsageError> {
    let base = Scenario::load(name_or_path)?;
    let run = RunFile {
        duration_s: duration_s.unwrap_or(base.file.run.duration_s),
        rate_hz: rate_hz.unwrap_or(base.file.run.rate_hz),
        actuation: actuation.unwrap_or(base.file.run.actuation),
    };
    Ok(base.with_run(run)?)
}
