//! What every role process shares beyond the wire: the arguments all four take
//! ([`RoleArgs`]), the run mode, how a process starts and reports its errors
//! ([`role_main`]), how it ends without losing data ([`linger`]), how it counts what it
//! received ([`SeqCounter`]), how it learns that the run is over ([`PlantEnd`]), and
//! fault injection of corrupted samples ([`corrupted`]).
//!
//! Ending without losing data: when a role has done its last tick it first drops its
//! subscribers, then keeps its publisher until nobody subscribes to it any more (at most
//! [`LINGER_S`] seconds), so every sample it published can still be read.

use std::time::Duration;

use std::path::Path;

use anyhow::Context;
use clap::{Args, ValueEnum};
use serde::Serialize;

use crate::ipc::{Domain, RtSetup, Wait, now_ns, shutdown_requested};
use crate::resume::ResumeSlot;
use crate::scenario::RunFile;
use crate::wire::{FLAG_LAST, ReferenceSample, StateSample, TorqueSample};
use crate::{Actuation, Scenario};

/// An error the user caused (bad argument or scenario value): exit code 2.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct UsageError(pub String);

impl From<crate::ScenarioError> for UsageError {
    fn from(e: crate::ScenarioError) -> Self {
        Self(e.to_string())
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

/// The error of a run whose state stopped being finite: a configuration the integrator
/// or the loop cannot handle (exit code 2, like any other bad scenario value).
pub fn diverged(tick: u64, t: f64) -> UsageError {
    UsageError(format!(
        "the run diverged at tick {tick} (t = {t} s): the plant's state is no longer finite. \
         The scenario is valid but unstable at this tick rate (gains, rates or torques too \
         large for dt?); no summary.json was written"
    ))
}

/// Writes `value` as pretty JSON (a summary), with a trailing newline. All or nothing: it
/// is written beside `path` and renamed into place, so a full disk never leaves a
/// truncated file where a reader expects a whole one.
pub fn write_json(path: &Path, value: &impl Serialize) -> anyhow::Result<()> {
    let text = serde_json::to_string_pretty(value).context("cannot serialise summary")?;
    let tmp = path.with_extension("json.partial");
    let written = std::fs::write(&tmp, text + "\n").and_then(|()| std::fs::rename(&tmp, path));
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written.with_context(|| format!("cannot write {}", path.display()))
}

/// Changes `out/summary.json` with `change`; nothing when there is no summary (the
/// monitor was stopped early: nothing to add to).
pub fn patch_summary(
    out: &std::path::Path,
    change: impl FnOnce(&mut serde_json::Value),
) -> anyhow::Result<()> {
    let path = out.join("summary.json");
    let Ok(text) = std::fs::read_to_string(&path) else { return Ok(()) };
    let mut j: serde_json::Value = serde_json::from_str(&text)?;
    change(&mut j);
    write_json(&path, &j)
}

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
    /// (default: `default` for a role started by hand, `run-<pid>` for `rotorloop run`).
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
    /// Simulated seconds (default: the scenario's).
    #[arg(long, allow_negative_numbers = true)]
    pub duration: Option<f64>,
    /// Tick rate in Hz (default: the scenario's).
    #[arg(long, allow_negative_numbers = true)]
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
    /// Pin the process to this core.
    #[arg(long, allow_negative_numbers = true)]
    pub core: Option<usize>,
    /// SCHED_FIFO priority 1–99 (a warning and the default policy when not permitted).
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(i32).range(1..=99))]
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
    /// `DIR/*.flight` (`common::flight`); `rotorloop run` records into `OUT/flight`.
    #[arg(long, value_name = "DIR")]
    pub record: Option<std::path::PathBuf>,
    /// Slots of each flight record's ring on tmpfs (rounded up to a power of two; 1224
    /// bytes a tick for the four streams): the RAM the records take whatever the run's
    /// duration. A run longer than that has the finished halves moved into `OUT/flight`
    /// while it goes on.
    #[arg(long, value_name = "TICKS", default_value_t = crate::flight::DEFAULT_RING_TICKS,
          value_parser = clap::value_parser!(u64).range(crate::flight::MIN_RING_TICKS..))]
    pub flight_ring_ticks: u64,
}

impl RoleArgs {
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
    pub fn open_domain(&self) -> Result<crate::ipc::Domain, UsageError> {
        crate::ipc::Domain::on_host(self.domain(), self.host.as_deref())
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
        a
    }
}

/// Whether the plant has published its last tick, read from its resume slot (written just
/// before each publish, kept after the plant exits). A role restarted after the run's end
/// gets no more states: with this it learns that it has nothing left to do, instead of
/// waiting for a plant that is gone.
#[derive(Debug)]
pub struct PlantEnd(ResumeSlot<StateSample>);

impl PlantEnd {
    /// Opens the plant's slot of `domain` (created empty if the plant has not yet).
    pub fn open(domain: &Domain) -> anyhow::Result<Self> {
        Ok(Self(ResumeSlot::open(domain, "plant").context("the plant's resume slot")?))
    }

    /// The plant published its last tick.
    pub fn ended(&self) -> bool {
        self.0.load().is_some_and(|s| s.flags & FLAG_LAST != 0)
    }
}

/// How a role that follows the plant's states (controller, reference) notices that the
/// plant is gone: after 1 s without a state it says so once (and says when the plant is
/// back); if the plant's resume slot then says the run is over, the role stops (a role
/// restarted after the end gets no more states and would otherwise wait forever).
#[derive(Debug)]
pub struct PlantWatch {
    role: &'static str,
    end: PlantEnd,
    last_state_ns: u64,
    gone: bool,
}

impl PlantWatch {
    /// Watches the plant of `domain` for `role` (named in its messages).
    pub fn open(domain: &Domain, role: &'static str) -> anyhow::Result<Self> {
        Ok(Self { role, end: PlantEnd::open(domain)?, last_state_ns: now_ns(), gone: false })
    }

    /// A state of tick `tick` arrived.
    pub fn saw_state(&mut self, tick: u64) {
        self.last_state_ns = now_ns();
        if std::mem::take(&mut self.gone) {
            eprintln!("{}: plant back at tick {tick}", self.role);
        }
    }

    /// A wait ended without a state: whether the run is over (stop).
    pub fn run_over(&mut self) -> bool {
        if now_ns() - self.last_state_ns <= 1_000_000_000 {
            return false;
        }
        if self.end.ended() {
            eprintln!("{}: the plant has ended the run; nothing left to do", self.role);
            return true;
        }
        if !std::mem::replace(&mut self.gone, true) {
            eprintln!("{}: no state from the plant for 1 s (plant gone?)", self.role);
        }
        false
    }
}

/// The absolute time grid of a real-time run: tick `k` is due at `start_ns + (k − first)`
/// periods (rounded to the ns, never accumulated, so the rate does not drift).
#[derive(Debug, Clone, Copy)]
pub struct TickGrid {
    start_ns: u64,
    first: u64,
    period_ns: f64,
}

impl TickGrid {
    /// Tick `first` at `start_ns`, then one tick every `1 / rate_hz` seconds.
    pub fn new(start_ns: u64, first: u64, rate_hz: f64) -> Self {
        Self { start_ns, first, period_ns: 1e9 / rate_hz }
    }

    /// When tick `k` is due (monotonic ns).
    pub fn at(&self, k: u64) -> u64 {
        self.start_ns + ((k - self.first) as f64 * self.period_ns).round() as u64
    }
}

/// Waits until `done()` or [`LINGER_S`] seconds or a termination signal.
pub fn linger(mut done: impl FnMut() -> bool) {
    let until = now_ns() + LINGER_S * 1_000_000_000;
    while !done() && now_ns() < until && !shutdown_requested() {
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// How long a finished publisher gives a link gateway's subscriber (which never leaves:
/// it lives as long as the gateway) to take its last samples.
pub const LINK_GRACE_NS: u64 = 300_000_000;

/// [`linger`] for a publisher: until every subscriber but a link gateway's has left, and,
/// when a gateway carries the topic to another host, at least [`LINK_GRACE_NS`].
pub fn linger_publisher<T>(out: &crate::ipc::Outbox<T>, role: &RoleArgs)
where
    T: iceoryx2::prelude::ZeroCopySend + std::fmt::Debug + Copy + 'static,
{
    let links = role.open_domain().map(|d| d.link_node_ids()).unwrap_or_default();
    let start = now_ns();
    linger(|| {
        out.subscribers_except(&links) == 0
            && (links.is_empty() || now_ns() - start > LINK_GRACE_NS)
    });
}

/// Counts samples received and samples lost (gaps in the tick sequence) on one subscriber.
/// Every topic of a run starts at tick 0: a fresh counter counts the ticks before its first
/// sample as lost (a starved subscriber whose small buffer overflowed before it first
/// looked loses the oldest, and they are losses like any gap). A restart that does not
/// know its predecessor's last tick ([`SeqCounter::resume_unanchored`]) cannot, and does
/// not count the gap before its first sample.
#[derive(Debug, Clone, Copy, Default)]
pub struct SeqCounter {
    /// Samples of new ticks taken.
    pub received: u64,
    /// Ticks skipped between consecutive samples.
    pub lost: u64,
    /// Samples of a tick already seen (a restarted publisher repeating its last one).
    pub repeated: u64,
    last: Option<u64>,
    /// Resumed without the predecessor's last tick: the first gap is unknown.
    unanchored: bool,
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
                if !self.unanchored {
                    self.lost += tick;
                }
                self.last = Some(tick);
            }
        }
    }

    /// Continue counting from these totals without the predecessor's last tick (its
    /// resume slot names none): the gap before the first sample is not counted.
    pub fn resume_unanchored(received: u64, lost: u64) -> Self {
        Self { received, lost, repeated: 0, last: None, unanchored: true }
    }

    /// Continue counting after `last` (a restarted subscriber).
    pub fn resume(received: u64, lost: u64, last: u64) -> Self {
        Self { received, lost, repeated: 0, last: Some(last), unanchored: false }
    }

    /// The newest tick seen.
    pub fn last(&self) -> Option<u64> {
        self.last
    }
}

/// A test hook's tick or duration from the environment variable `name` (the fault tests
/// use them to stall or skip at a chosen moment); `None` when unset or not a number.
pub fn test_hook(name: &str) -> Option<u64> {
    std::env::var(name).ok().and_then(|v| v.parse().ok())
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
    let relay = crate::relay::Stdio::relay();
    let code = run_role(name, &args, run);
    relay.finish();
    code
}

/// Runs a role with signal handling and error reporting (shared by the role binaries
/// and `rotorloop role`).
pub fn run_role<A>(
    name: &str,
    args: &A,
    run: fn(&A) -> anyhow::Result<()>,
) -> std::process::ExitCode {
    crate::ipc::install_signal_handlers();
    crate::ipc::quiet_iceoryx_logs();
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

/// How to corrupt a published sample (fault injection: `rotorloop run --corrupt`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CorruptKind {
    /// A NaN in the first vector the receiver uses.
    Nan,
    /// `+∞` there.
    Inf,
    /// `1e12` there: finite but absurd.
    Huge,
    /// An attitude that is not a rotation (a row scaled by 1.5): state and reference only.
    Skew,
}

/// One `--corrupt KIND@TICK`: publish tick `tick` corrupted instead of the true sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Corrupt {
    /// What to do to the sample.
    pub kind: CorruptKind,
    /// Which tick's sample.
    pub tick: u64,
}

impl std::str::FromStr for Corrupt {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("`{s}` is not allowed: KIND@TICK with KIND nan, inf, huge or skew");
        let (kind, tick) = s.split_once('@').ok_or_else(bad)?;
        let kind = match kind {
            "nan" => CorruptKind::Nan,
            "inf" => CorruptKind::Inf,
            "huge" => CorruptKind::Huge,
            "skew" => CorruptKind::Skew,
            _ => return Err(bad()),
        };
        Ok(Self { kind, tick: tick.parse().map_err(|_| bad())? })
    }
}

impl std::fmt::Display for Corrupt {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let kind = match self.kind {
            CorruptKind::Nan => "nan",
            CorruptKind::Inf => "inf",
            CorruptKind::Huge => "huge",
            CorruptKind::Skew => "skew",
        };
        write!(f, "{kind}@{}", self.tick)
    }
}

/// A sample that fault injection can corrupt.
pub trait Corruptible: Copy {
    /// The sample's tick.
    fn tick(&self) -> u64;
    /// The vector a receiver reads first, and the attitude (if the sample has one).
    fn targets(&mut self) -> (&mut [f64; 3], Option<&mut [f64; 9]>);
}

impl Corruptible for StateSample {
    fn tick(&self) -> u64 {
        self.tick
    }
    fn targets(&mut self) -> (&mut [f64; 3], Option<&mut [f64; 9]>) {
        (&mut self.omega_body_rad_s, Some(&mut self.r_row_major))
    }
}

impl Corruptible for ReferenceSample {
    fn tick(&self) -> u64 {
        self.tick
    }
    fn targets(&mut self) -> (&mut [f64; 3], Option<&mut [f64; 9]>) {
        (&mut self.omega_d_rad_s, Some(&mut self.r_d_row_major))
    }
}

impl Corruptible for TorqueSample {
    fn tick(&self) -> u64 {
        self.tick
    }
    fn targets(&mut self) -> (&mut [f64; 3], Option<&mut [f64; 9]>) {
        (&mut self.rotor_torque_nm, None)
    }
}

/// The sample to publish: `sample` itself, or a corrupted copy when `--corrupt` names
/// its tick. The caller keeps (and stores for a restart) the true sample.
#[inline]
pub fn corrupted<T: Corruptible>(corrupt: &[Corrupt], mut sample: T) -> T {
    let tick = sample.tick();
    for c in corrupt.iter().filter(|c| c.tick == tick) {
        let (v, r) = sample.targets();
        match (c.kind, r) {
            (CorruptKind::Nan, _) => v[0] = f64::NAN,
            (CorruptKind::Inf, _) => v[0] = f64::INFINITY,
            (CorruptKind::Huge, _) => v[0] = 1e12,
            (CorruptKind::Skew, Some(r)) => r[..3].iter_mut().for_each(|x| *x *= 1.5),
            (CorruptKind::Skew, None) => v[0] = f64::NAN,
        }
    }
    sample
}

#[cfg(test)]
mod tests {
    use super::SeqCounter;

    #[test]
    fn every_tick_is_received_lost_or_repeated_from_tick_zero() {
        // A starved subscriber whose buffer overflowed before it first looked: 0-3 lost.
        let mut c = SeqCounter::default();
        for k in [4, 5, 5, 8, 7, 9] {
            c.see(k);
        }
        assert_eq!((c.received, c.lost, c.repeated), (4, 6, 2), "0-3 and 6-7 lost");
        assert_eq!(c.received + c.lost, 9 + 1);
        // A restart that does not know its predecessor's last tick cannot count the first
        // gap; an anchored one continues after that tick.
        let mut u = SeqCounter::resume_unanchored(4, 0);
        u.see(10);
        assert_eq!((u.received, u.lost), (5, 0));
        let mut a = SeqCounter::resume(10, 2, 11);
        a.see(13);
        assert_eq!((a.received, a.lost, a.last()), (11, 3, Some(13)));
    }
}
