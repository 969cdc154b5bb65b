//! One home for fault kinds: what `--fault` can ask for (its syntax and the roles it
//! allows, [`parse_fault`]), when each part is due ([`FaultSchedule`]), and a fault as it
//! happened ([`FaultEvent`]), whether the schedule injected it or the supervisor saw it.
//! What each fault cost is computed after the run in [`report`].
//!
//! Each kind is one row of [`KINDS`]: its syntax, the roles it allows, its help line (the
//! `--help` of `--fault` is made from them), how its start and end are applied
//! ([`Apply`]: a signal, a restart, or an argument the role applies itself) and the word
//! its events and report rows use. The launcher carries out the due [`Action`]s by that
//! column in `run::supervise`. `--corrupt` ([`parse_corrupt`]) takes the same time syntax
//! ([`parse_run_time`]): the role corrupts its own sample of that tick
//! (`rotorloop_common::role::inject`, with the tests' hidden hooks).
//!
//! Every time is on the run's own clock, the plant's ticks: `@T` is the tick T·rate, and
//! a part is due once the plant has published that tick, in real time and in lockstep
//! alike (in lockstep the plant holds at that tick until the launcher has carried it out:
//! [`FaultSchedule::gate_ticks`]). Only the end of a fault that stops that clock (the
//! plant's own kill or stop; in lockstep every role the plant waits for: [`stops_the_clock`])
//! is timed otherwise: its role stays down or stopped for T2 − T1 seconds of wall time,
//! since the plant's tick cannot move until it ends.

pub mod report;

use rotorloop_common::clock::now_ns;

use crate::run::member::Member;
use rotorloop_common::graph::Role;
use rotorloop_common::role::UsageError;
use rotorloop_common::role::inject::Corrupt;

/// What a `--fault` does (its row in [`KINDS`] says everything else).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FaultKind {
    /// SIGKILL, then (if given) start it again.
    Kill,
    /// SIGSTOP (a hang), then (if given) SIGCONT.
    Stop,
    /// The controller sends each answer this many seconds late (a slow network or an
    /// overloaded computer), from the fault's time until its end (if given). The
    /// controller applies it itself, by the states' times (`--inject-delay`).
    Delay(f64),
}

/// How the launcher carries out the start or the end of a fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Apply {
    /// Send this signal to the role's process (`SIGKILL`, `SIGSTOP`, `SIGCONT`).
    Signal(libc::c_int, &'static str),
    /// Start the role again with its original arguments.
    Restart,
    /// The role applies it itself from an argument it was started with (the launcher
    /// only reports it).
    ByTheRole(&'static str),
}

/// Which roles a fault kind may target.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Targets {
    /// Any role, and with `--split` a link gateway (`link-HOST`).
    AnyProcess,
    /// Only this role.
    Only(Role),
}

/// One kind of `--fault`, all of it in one row: its syntax, the roles it allows, its help,
/// how its start and end are applied, and the word its report and events use.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KindSpec {
    /// The word of its start, before `@T` (also the kind of its [`FaultEvent`] and of its
    /// row in the report).
    pub start: &'static str,
    /// The word of its optional end, before `@T2`.
    pub end: &'static str,
    /// A value after the start time (`=SECONDS`): its name and the range allowed.
    pub value: Option<(&'static str, f64, f64)>,
    /// Which roles it may target.
    pub targets: Targets,
    /// How the start and the end are applied.
    pub apply: (Apply, Apply),
    /// One line of `--help`.
    pub help: &'static str,
}

/// Every `--fault` kind. A new kind is a row here, a variant of [`FaultKind`] and, when
/// the role applies it itself, the role's side (the controller's `--inject-delay`).
pub const KINDS: [KindSpec; 3] = [
    KindSpec {
        start: "kill",
        end: "restart",
        value: None,
        targets: Targets::AnyProcess,
        apply: (Apply::Signal(libc::SIGKILL, "SIGKILL"), Apply::Restart),
        help: "ROLE:kill@T[:restart@T2]: SIGKILL at T; at T2 start it again",
    },
    KindSpec {
        start: "stop",
        end: "cont",
        value: None,
        targets: Targets::AnyProcess,
        apply: (Apply::Signal(libc::SIGSTOP, "SIGSTOP"), Apply::Signal(libc::SIGCONT, "SIGCONT")),
        help: "ROLE:stop@T[:cont@T2]: SIGSTOP (a hang) at T; SIGCONT at T2",
    },
    KindSpec {
        start: "delay",
        end: "until",
        value: Some(("SECONDS", 0.0, 60.0)),
        targets: Targets::Only(Role::Controller),
        apply: (Apply::ByTheRole("--inject-delay"), Apply::ByTheRole("--inject-delay")),
        help: "controller:delay@T=SECONDS[:until@T2]: each answer sent SECONDS late (> 0, ≤ 60) from T to T2",
    },
];

impl FaultKind {
    /// Its row in [`KINDS`].
    pub fn spec(self) -> &'static KindSpec {
        &KINDS[match self {
            Self::Kill => 0,
            Self::Stop => 1,
            Self::Delay(_) => 2,
        }]
    }

    fn of(spec: &KindSpec, value: Option<f64>) -> Self {
        match (spec.start, value) {
            ("stop", _) => Self::Stop,
            ("delay", Some(d)) => Self::Delay(d),
            _ => Self::Kill,
        }
    }
}

/// The `--help` of `--fault`, from [`KINDS`].
pub fn help() -> String {
    let kinds: Vec<&str> = KINDS.iter().map(|k| k.help).collect();
    format!(
        "Inject a fault at T of the run's own clock, the plant's ticks, in real time and in \
         lockstep alike: T is SECONDS of the run (`4`, `4.5`, `4s`: the tick T·rate) or a tick \
         (`4000t`); it is carried out once the plant has published that tick (in lockstep the \
         plant is held there meanwhile, so the fault lands at that tick every time). {}. The \
         end of the plant's own kill or stop (in lockstep: of any role but the monitor) is a \
         down time: T2 − T1 seconds of wall time, the run's clock standing still. ROLE is \
         plant, reference, controller, monitor or, with --split, a gateway (link-HOST). A \
         fault that cannot happen (after the run's end, a stop that never ends) is refused \
         (exit 2). Repeatable; one role takes one fault at a time",
        kinds.join("; ")
    )
}

/// A time of the run as `--fault` and `--corrupt` take it: `SECONDS` of the run (`4`,
/// `4.5`, `4s`) or a tick (`4000t`). Returns the seconds and the tick: the first tick at or
/// after those seconds (`T·rate`, rounded up; a millionth of a tick of slack absorbs the
/// binary rounding of `0.6 × 1000`), or the tick and its time.
pub fn parse_run_time(p: &str, rate_hz: f64) -> Result<(f64, u64), String> {
    let why = || format!("`{p}` must be SECONDS ≥ 0 (4, 4.5, 4s) or a tick (4000t)");
    if let Some(t) = p.strip_suffix('t') {
        let tick: u64 = t.parse().map_err(|_| why())?;
        return Ok((tick as f64 / rate_hz, tick));
    }
    let s: f64 = p.strip_suffix('s').unwrap_or(p).parse().map_err(|_| why())?;
    if !(s.is_finite() && s >= 0.0 && s * rate_hz < 1e15) {
        return Err(why());
    }
    Ok((s, (s * rate_hz - 1e-6).ceil().max(0.0) as u64))
}

/// Whether a kill or stop of `role` stops the run's clock (the plant's ticks) while the
/// role is down: the plant's own, and in lockstep every role the plant waits for (all but
/// the monitor, an observer). The end of such a fault cannot wait for a tick: it comes
/// after T2 − T1 seconds of wall time.
pub fn stops_the_clock(role: &Member, kind: FaultKind, lockstep: bool) -> bool {
    let down = matches!(kind, FaultKind::Kill | FaultKind::Stop);
    down && (role.is(Role::Plant) || (lockstep && !role.is(Role::Monitor)))
}

/// One `--fault`: a row of [`KINDS`] for a role, its start and its optional end.
#[derive(Debug, Clone, PartialEq)]
pub struct Fault {
    /// The role (or gateway).
    pub role: Member,
    /// What it does.
    pub kind: FaultKind,
    /// When it starts: seconds of the run (the time asked, or its tick's time).
    pub kill_s: f64,
    /// When it ends: restart, SIGCONT, or the delay's end (s of the run), if at all.
    pub restart_s: Option<f64>,
    /// The tick whose publication starts it ([`parse_run_time`]).
    pub at_tick: u64,
    /// The tick whose publication ends it, if it ends.
    pub until_tick: Option<u64>,
    /// When the launcher carried out its start (monotonic ns).
    killed: Option<u64>,
    restarted: bool,
}

impl Fault {
    /// The fault as `summary.json`'s `fault_schedule` lists it (the incidents read it).
    pub fn scheduled(&self) -> serde_json::Value {
        let value = match self.kind {
            FaultKind::Delay(d) => Some(d),
            _ => None,
        };
        serde_json::json!({
            "role": self.role.to_string(),
            "kind": self.kind.spec().start,
            "at_s": self.kill_s,
            "until_s": self.restart_s,
            "at_tick": self.at_tick,
            "until_tick": self.until_tick,
            "value_s": value,
        })
    }

    /// The argument a role that applies this fault itself is started with (the
    /// controller's `--inject-delay FROM=SECONDS[:UNTIL]` of a delay).
    pub fn role_arg(&self) -> Option<(&'static str, String)> {
        match (self.kind, self.kind.spec().apply.0) {
            (FaultKind::Delay(d), Apply::ByTheRole(flag)) => Some((
                flag,
                match self.restart_s {
                    Some(u) => format!("{}={d}:{u}", self.kill_s),
                    None => format!("{}={d}", self.kill_s),
                },
            )),
            _ => None,
        }
    }
}

/// Parses a `--fault` by the rows of [`KINDS`], its times on a run of `rate_hz`.
pub fn parse_fault(s: &str, rate_hz: f64) -> Result<Fault, UsageError> {
    let forms: Vec<&str> =
        KINDS.iter().map(|k| k.help.split_once(':').map_or(k.help, |(f, _)| f)).collect();
    let bad = |why: &str| {
        UsageError(format!(
            "--fault `{s}` is not allowed: {why} (form {}, e.g. controller:kill@2:restart@2.5)",
            forms.join(", ")
        ))
    };
    let parts: Vec<&str> = s.split(':').collect();
    if parts.len() < 2 || parts.len() > 3 {
        return Err(bad("two or three parts"));
    }
    let role: Member = parts[0].parse().map_err(|_| {
        bad("ROLE is plant, reference, controller, monitor or (with --split) link-HOST")
    })?;
    let seconds = |p: &str, what: &str| -> Result<f64, UsageError> {
        p.parse::<f64>()
            .ok()
            .filter(|t| t.is_finite() && *t >= 0.0)
            .ok_or_else(|| bad(&format!("`{p}` must be {what}, seconds ≥ 0")))
    };
    let run_time = |p: &str, what: &str| -> Result<(f64, u64), UsageError> {
        parse_run_time(p, rate_hz).map_err(|e| bad(&format!("the time of {what}: {e}")))
    };
    let kinds: Vec<&str> = KINDS.iter().map(|k| k.start).collect();
    let Some((word, rest)) = parts[1].split_once('@') else {
        return Err(bad(&format!(
            "`{}` must be KIND@SECONDS, KIND {}",
            parts[1],
            kinds.join(", ")
        )));
    };
    let spec = KINDS
        .iter()
        .find(|k| k.start == word)
        .ok_or_else(|| bad(&format!("`{word}` is not a kind: {}", kinds.join(", "))))?;
    let (at, value) = match spec.value {
        None => (rest, None),
        Some((name, lo, hi)) => {
            let (at, v) = rest.split_once('=').ok_or_else(|| bad(&format!("{word}@T={name}")))?;
            let v = seconds(v, &format!("the {word}"))?;
            if !(v > lo && v <= hi) {
                return Err(bad(&format!("the {word} must be > {lo} and ≤ {hi} s")));
            }
            (at, Some(v))
        }
    };
    if let Targets::Only(only) = spec.targets
        && !role.is(only)
    {
        return Err(bad(&format!("only the {}'s answers can take a {word}", only.name())));
    }
    let (kill_s, at_tick) = run_time(at, &format!("{word}@"))?;
    let time = |p: &str, key: &str| match p.strip_prefix(key).and_then(|p| p.strip_prefix('@')) {
        Some(t) => run_time(t, &format!("{key}@")),
        None => Err(bad(&format!("`{p}` must be {key}@T"))),
    };
    let end = parts.get(2).map(|p| time(p, spec.end)).transpose()?;
    if end.is_some_and(|(r, k)| r <= kill_s || k < at_tick) {
        return Err(bad(&format!("the {} must come after the {}", spec.end, spec.start)));
    }
    let kind = FaultKind::of(spec, value);
    let (restart_s, until_tick) = (end.map(|e| e.0), end.map(|e| e.1));
    let (killed, restarted) = (None, false);
    Ok(Fault { role, kind, kill_s, restart_s, at_tick, until_tick, killed, restarted })
}

/// Parses `--corrupt ROLE:KIND@T` on a run of `rate_hz` with `ticks` ticks: a fault the
/// role applies to its own sample of the tick T (the same time syntax as `--fault`,
/// [`parse_run_time`]), which must be within the run.
pub fn parse_corrupt(s: &str, rate_hz: f64, ticks: u64) -> Result<(String, Corrupt), UsageError> {
    use rotorloop_common::role::inject::CorruptKind;
    let bad = |why: &str| {
        UsageError(format!(
            "--corrupt `{s}` is not allowed: {why} (form ROLE:KIND@T, T seconds of the run or \
             a tick: controller:nan@0.5, controller:nan@500t)"
        ))
    };
    let (role, rest) = s.split_once(':').ok_or_else(|| bad("no ROLE:"))?;
    if ![Role::Plant, Role::Reference, Role::Controller].map(Role::name).contains(&role) {
        return Err(bad("ROLE is plant, reference or controller"));
    }
    let (kind, at) = rest.split_once('@').ok_or_else(|| bad("no @T"))?;
    let (at_s, tick) = parse_run_time(at, rate_hz).map_err(|e| bad(&e))?;
    if tick > ticks {
        return Err(bad(&format!(
            "it is after the run's end: tick {tick} ({at_s} s), the last tick is {ticks} ({} s)",
            ticks as f64 / rate_hz
        )));
    }
    let c: Corrupt = format!("{kind}@{tick}").parse().map_err(|e: String| bad(&e))?;
    if role == Role::Controller.name() && c.kind == CorruptKind::Skew {
        return Err(bad("`skew` needs an attitude: plant or reference"));
    }
    Ok((role.to_owned(), c))
}

/// Refuses `--fault`s that overlap for one role: a kill or stop while the role is
/// already down from another (a kill with no restart keeps it down to the end), or two
/// delays of the controller at once. What a second kill of a dead role or a second
/// restart of a running one would mean is not defined, so such a schedule is a usage
/// error naming both faults (`specs[i]` is the text of `faults[i]`).
pub fn check_overlaps(specs: &[String], faults: &[Fault]) -> Result<(), UsageError> {
    let window = |f: &Fault| (f.kill_s, f.restart_s.unwrap_or(f64::INFINITY));
    let delays = |f: &Fault| matches!(f.kind, FaultKind::Delay(_));
    for (i, a) in faults.iter().enumerate() {
        for (j, b) in faults.iter().enumerate().skip(i + 1) {
            if a.role != b.role || delays(a) != delays(b) {
                continue;
            }
            let ((a0, a1), (b0, b1)) = (window(a), window(b));
            if a0 < b1 && b0 < a1 {
                let what = if delays(a) { "delayed" } else { "down" };
                let until = |t: f64| match t.is_finite() {
                    true => format!("{t} s"),
                    false => "the end".to_owned(),
                };
                return Err(UsageError(format!(
                    "--fault `{}` and --fault `{}` overlap: {} is {what} from {a0} s to {} and \
                     from {b0} s to {}; one role takes one fault at a time (end the first \
                     before the second starts)",
                    specs[i],
                    specs[j],
                    a.role,
                    until(a1),
                    until(b1)
                )));
            }
        }
    }
    Ok(())
}

/// What a run is, for the faults that cannot happen in it ([`check_against_run`]).
#[derive(Debug, Clone, Copy)]
pub struct RunShape {
    /// Its last tick (the plant publishes ticks 0 to `ticks`).
    pub ticks: u64,
    /// Its rate (Hz).
    pub rate_hz: f64,
    /// Lockstep (the plant waits for every role but the monitor).
    pub lockstep: bool,
    /// `--watchdog-ms` is 0: a stopped role is never judged hung.
    pub no_watchdog: bool,
}

/// Refuses, before the run, every `--fault` that cannot happen in it (`specs[i]` is the
/// text of `faults[i]`): a start or an end at or after the run's end (an end that is a down
/// time, [`stops_the_clock`], excepted: it always comes); a stop with no `cont@` and the
/// watchdog off that would hold the loop for ever (the plant's own; in lockstep any role
/// but the monitor's); a delay as long as the run or longer (no answer it holds back would
/// reach the plant within the run, and in lockstep, where the plant waits for each answer,
/// the run would take the delay times its ticks: `controller:delay@0=60` on a 2 s run, 33
/// hours).
pub fn check_against_run(
    specs: &[String],
    faults: &[Fault],
    run: RunShape,
) -> Result<(), UsageError> {
    let duration_s = run.ticks as f64 / run.rate_hz;
    let refuse =
        |spec: &str, why: String| Err(UsageError(format!("--fault `{spec}` cannot happen: {why}")));
    for (spec, f) in specs.iter().zip(faults) {
        let KindSpec { start, end, .. } = f.kind.spec();
        let after_end = |word: &str, tick: u64| {
            format!(
                "its {word} is at tick {tick} ({} s), at or after the run's end (tick {}, {duration_s} s)",
                tick as f64 / run.rate_hz,
                run.ticks
            )
        };
        if f.at_tick >= run.ticks {
            return refuse(spec, after_end(start, f.at_tick));
        }
        let by_tick = !stops_the_clock(&f.role, f.kind, run.lockstep);
        if let Some(u) = f.until_tick.filter(|u| by_tick && *u >= run.ticks) {
            return refuse(spec, after_end(end, u));
        }
        if f.kind == FaultKind::Stop && f.until_tick.is_none() && run.no_watchdog && !by_tick {
            return refuse(
                spec,
                format!(
                    "a stop with no cont@ and the watchdog off (--watchdog-ms 0) never ends: \
                     the plant's clock would stand still at tick {} for ever (give it a cont@ \
                     or a watchdog)",
                    f.at_tick
                ),
            );
        }
        if let FaultKind::Delay(d) = f.kind
            && d >= duration_s
        {
            return Err(UsageError(format!(
                "--fault `{spec}` is not allowed: the delay ({d} s) must be shorter than the \
                 run ({duration_s} s)"
            )));
        }
    }
    Ok(())
}

/// What the schedule asks the launcher to do now: the start or the end of a fault of
/// `role`, applied as its row of [`KINDS`] says.
#[derive(Debug, Clone, PartialEq)]
pub struct Action {
    /// The role (or gateway).
    pub role: Member,
    /// The fault's kind.
    pub kind: FaultKind,
    /// Its start (`true`) or its end.
    pub starts: bool,
    /// The fault has an end (`restart@`, `cont@`, `until@`): a kill without one leaves the
    /// role down to the end of the run.
    pub ends: bool,
}

impl Action {
    /// How to apply it.
    pub fn apply(&self) -> Apply {
        let (start, end) = self.kind.spec().apply;
        if self.starts { start } else { end }
    }
}

/// The `--fault` schedule, on the run's clock: each part due once the plant has published
/// its tick, but the end of a fault that stops that clock ([`stops_the_clock`]), due its
/// down time (T2 − T1 s of wall time) after its start was carried out.
#[derive(Debug, Clone, Default)]
pub struct FaultSchedule {
    faults: Vec<Fault>,
    lockstep: bool,
}

impl FaultSchedule {
    /// The schedule of these faults, in lockstep or in real time.
    pub fn new(faults: Vec<Fault>, lockstep: bool) -> Self {
        Self { faults, lockstep }
    }

    /// Whether `f`'s end waits for a tick (not a down time).
    fn ends_by_tick(&self, f: &Fault) -> bool {
        !stops_the_clock(&f.role, f.kind, self.lockstep)
    }

    /// What is due now (`now_ns`, monotonic) with the plant's newest published tick
    /// `tick` (`None`: tick 0 not yet published, so nothing is due by tick): each fault's
    /// start once, then its end once.
    pub fn due(&mut self, tick: Option<u64>, now_ns: u64) -> Vec<Action> {
        let mut actions = Vec::new();
        for i in 0..self.faults.len() {
            let by_tick = self.ends_by_tick(&self.faults[i]);
            let f = &mut self.faults[i];
            let (kind, ends) = (f.kind, f.until_tick.is_some());
            let reached = |k: u64| tick.is_some_and(|t| t >= k);
            if f.killed.is_none() && reached(f.at_tick) {
                f.killed = Some(now_ns);
                actions.push(Action { role: f.role.clone(), kind, starts: true, ends });
            }
            let end_due = match (f.killed, f.until_tick, f.restart_s) {
                (Some(_), Some(u), _) if by_tick => reached(u),
                (Some(at), Some(_), Some(r)) => {
                    now_ns >= at.saturating_add(((r - f.kill_s) * 1e9) as u64)
                }
                _ => false,
            };
            if end_due && !f.restarted {
                f.restarted = true;
                actions.push(Action { role: f.role.clone(), kind, starts: false, ends });
            }
        }
        actions
    }

    /// Lockstep: the ticks at which a part is due by tick, in order; the plant holds at
    /// each (`--gate-ticks`) until the launcher has carried it out. None in real time.
    pub fn gate_ticks(&self) -> Vec<u64> {
        if !self.lockstep {
            return Vec::new();
        }
        let mut ticks: Vec<u64> = self
            .faults
            .iter()
            .flat_map(|f| [Some(f.at_tick), f.until_tick.filter(|_| self.ends_by_tick(f))])
            .flatten()
            .collect();
        ticks.sort_unstable();
        ticks.dedup();
        ticks
    }

    /// The next tick at which a part not yet carried out is due, if any (real time: the
    /// launcher looks more often as the plant nears it).
    pub fn next_tick(&self) -> Option<u64> {
        let pending = |f: &Fault| {
            let start = f.killed.is_none().then_some(f.at_tick);
            let end = f.until_tick.filter(|_| !f.restarted && self.ends_by_tick(f));
            start.or(end)
        };
        self.faults.iter().filter_map(pending).min()
    }

    /// A fault that stops the run's clock has started and its end is still to come: in
    /// lockstep the launcher keeps the plant held at the tick of its start meanwhile.
    pub fn holding(&self) -> bool {
        self.faults.iter().any(|f| {
            f.killed.is_some() && !f.restarted && f.until_tick.is_some() && !self.ends_by_tick(f)
        })
    }

    /// The parts of faults not carried out (the run ended first: a failure or a signal), in
    /// words.
    pub fn not_done(&self) -> Vec<String> {
        let mut out = Vec::new();
        for f in &self.faults {
            let KindSpec { start, end, .. } = f.kind.spec();
            if f.killed.is_none() {
                out.push(format!("{}:{start}@{}", f.role, f.kill_s));
            } else if let Some(r) = f.restart_s.filter(|_| !f.restarted) {
                out.push(format!("{}:…:{end}@{r}", f.role));
            }
        }
        out
    }

    /// A role was killed and its restart is still to come: the run is not over even if
    /// no child runs.
    pub fn awaiting_restart(&self) -> bool {
        self.faults.iter().any(|f| {
            f.kind == FaultKind::Kill && f.killed.is_some() && !f.restarted && f.restart_s.is_some()
        })
    }
}

/// A fault as it happened (monotonic ns): injected (`kill`, `stop`) or not (`killed`,
/// `crash`, `exited`, `hang`: what the supervisor saw).
#[derive(Debug, Clone, PartialEq)]
pub struct FaultEvent {
    /// The role.
    pub role: String,
    /// `kill` or `stop` (injected by `--fault`), `killed`, `crash`, `exited` or `hang`;
    /// `resume-refused` when a restarted role's resume slot failed its check (the role
    /// started as a fresh one).
    pub kind: &'static str,
    /// What happened, in words (the exit status, what the watchdog did).
    pub detail: String,
    /// When it was killed, stopped, or found dead or hung.
    pub kill_ns: u64,
    /// When it was started again (or continued).
    pub restart_ns: Option<u64>,
    /// The signal, where it is known (`SIGSTOP`, `SIGTSTP`, `SIGKILL`, …).
    pub signal: Option<&'static str>,
    /// A stop's end: how (`continued`, `killed`, `crash`, `exited`, `hung`, or `run ended`
    /// when the launcher continued it after the last tick) and when (ns).
    pub ended: Option<(&'static str, u64)>,
    /// Whether the `--fault` schedule asked for it (the launcher did it), not something
    /// from outside the launcher or found by its supervisor.
    pub scheduled: bool,
}

impl FaultEvent {
    /// A fault of `role` happening now, not (yet) followed by a restart.
    pub(crate) fn now(role: impl Into<String>, kind: &'static str, detail: String) -> Self {
        let (role, kill_ns) = (role.into(), now_ns());
        let (restart_ns, signal, ended, scheduled) = (None, None, None, false);
        Self { role, kind, detail, kill_ns, restart_ns, signal, ended, scheduled }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn act(role: &str, kind: FaultKind, starts: bool) -> Action {
        Action { role: role.parse().expect("a member"), kind, starts, ends: true }
    }

    fn fault(s: &str) -> Fault {
        parse_fault(s, 1000.0).expect("valid")
    }

    fn schedule(faults: &[&str], lockstep: bool) -> FaultSchedule {
        FaultSchedule::new(faults.iter().map(|f| fault(f)).collect(), lockstep)
    }

    const S: u64 = 1_000_000_000;

    #[test]
    fn nothing_is_due_before_tick_zero_however_late() {
        let mut s = schedule(&["controller:kill@0"], false);
        assert!(s.due(None, 100 * S).is_empty());
        let kill = Action { ends: false, ..act("controller", FaultKind::Kill, true) };
        assert_eq!(s.due(Some(0), 100 * S), [kill]);
    }

    #[test]
    fn a_time_is_seconds_of_the_run_or_a_tick_and_both_name_one_tick() {
        assert_eq!(parse_run_time("4", 1000.0), Ok((4.0, 4000)));
        assert_eq!(parse_run_time("4s", 1000.0), Ok((4.0, 4000)));
        assert_eq!(parse_run_time("4000t", 1000.0), Ok((4.0, 4000)));
        // 0.6 × 1000 is 600.0000000000001 in binary: still tick 600, not 601.
        assert_eq!(parse_run_time("0.6", 1000.0).map(|t| t.1), Ok(600));
        // Between two ticks: the first one at or after it.
        assert_eq!(parse_run_time("4.0005", 1000.0).map(|t| t.1), Ok(4001));
        assert_eq!(parse_run_time("1", 250.0).map(|t| t.1), Ok(250));
        for bad in ["-1", "x", "4ms", "1.5t", "inf", "NaN"] {
            let e = parse_run_time(bad, 1000.0).expect_err(bad);
            assert!(e.contains("SECONDS") && e.contains("4000t"), "{bad}: {e}");
        }
        let f = fault("controller:kill@4000t:restart@4.5");
        assert_eq!((f.at_tick, f.until_tick, f.kill_s), (4000, Some(4500), 4.0));
    }

    #[test]
    fn a_kill_then_its_restart_are_due_once_each_at_their_ticks() {
        // The controller in real time: the plant's clock goes on while it is down.
        let mut s = schedule(&["controller:kill@1:restart@1.5"], false);
        assert!(s.due(Some(999), 0).is_empty());
        assert_eq!(s.next_tick(), Some(1000));
        assert_eq!(s.due(Some(1000), 0), [act("controller", FaultKind::Kill, true)]);
        assert!(s.awaiting_restart());
        assert!(!s.holding(), "the plant's clock goes on");
        assert_eq!(s.next_tick(), Some(1500));
        assert!(s.due(Some(1499), 100 * S).is_empty(), "by tick, not by wall time");
        assert_eq!(s.due(Some(1500), 0), [act("controller", FaultKind::Kill, false)]);
        assert!(!s.awaiting_restart());
        assert!(s.due(Some(9000), 0).is_empty());
        assert_eq!(s.next_tick(), None);
        // A late look that passes both ticks at once does both, kill first.
        let mut late = schedule(&["monitor:kill@1:restart@2"], true);
        let both = late.due(Some(5000), 0);
        assert_eq!(
            both,
            [act("monitor", FaultKind::Kill, true), act("monitor", FaultKind::Kill, false)]
        );
    }

    #[test]
    fn the_end_of_a_fault_that_stops_the_plants_clock_is_its_down_time() {
        // The plant's own kill, in either mode: its tick cannot reach 1500 while it is down.
        for lockstep in [false, true] {
            let mut s = schedule(&["plant:kill@1:restart@1.5"], lockstep);
            assert_eq!(s.gate_ticks(), if lockstep { vec![1000] } else { vec![] });
            assert_eq!(s.due(Some(1000), 7 * S), [act("plant", FaultKind::Kill, true)]);
            assert!(s.holding());
            assert!(s.due(Some(1000), 7 * S + S / 2 - 1).is_empty());
            assert_eq!(s.due(Some(1000), 7 * S + S / 2), [act("plant", FaultKind::Kill, false)]);
            assert!(!s.holding());
        }
        // In lockstep the controller too (the plant waits for its torque); the monitor is
        // an observer, and a delay is applied by the controller by the states' times.
        let s = schedule(
            &[
                "controller:kill@1:restart@1.5",
                "monitor:stop@2:cont@3",
                "controller:delay@4=0.1:until@5",
            ],
            true,
        );
        assert_eq!(s.gate_ticks(), [1000, 2000, 3000, 4000, 5000]);
        let mut s = schedule(&["controller:kill@1:restart@1.5"], true);
        s.due(Some(1000), 0);
        assert!(s.holding() && s.next_tick().is_none());
        assert_eq!(s.due(Some(1000), S / 2), [act("controller", FaultKind::Kill, false)]);
    }

    #[test]
    fn faults_that_cannot_happen_are_refused_before_the_run() {
        let run = |lockstep, no_watchdog| RunShape {
            ticks: 10_000,
            rate_hz: 1000.0,
            lockstep,
            no_watchdog,
        };
        let check = |f: &str, shape: RunShape| {
            check_against_run(&[f.to_owned()], &[fault(f)], shape).map_err(|e| e.0)
        };
        for f in
            ["controller:kill@10", "controller:kill@12:restart@13", "monitor:kill@2:restart@10"]
        {
            let e = check(f, run(true, false)).expect_err(f);
            assert!(e.contains(f) && e.contains("after the run's end"), "{e}");
        }
        // A down time may end after the run's time: the plant's clock stood still.
        assert!(check("plant:kill@9:restart@11", run(false, false)).is_ok());
        assert!(check("controller:kill@9:restart@11", run(true, false)).is_ok());
        assert!(check("controller:kill@9:restart@11", run(false, false)).is_err());
        // A stop that never ends.
        let e = check("plant:stop@0", run(false, true)).expect_err("plant stop");
        assert!(e.contains("never ends") && e.contains("--watchdog-ms 0"), "{e}");
        assert!(check("controller:stop@1", run(true, true)).is_err());
        assert!(check("controller:stop@1", run(false, true)).is_ok(), "real time goes on");
        assert!(check("plant:stop@0", run(false, false)).is_ok(), "the watchdog ends it");
        assert!(check("monitor:stop@1", run(true, true)).is_ok(), "continued at the end");
        // --corrupt takes the same times, and refuses one after the end.
        let (_, c) = parse_corrupt("controller:nan@0.5", 1000.0, 10_000).expect("valid");
        assert_eq!(c.tick, 500);
        assert_eq!(parse_corrupt("plant:skew@700t", 1000.0, 10_000).expect("ok").1.tick, 700);
        let e = parse_corrupt("plant:nan@11", 1000.0, 10_000).expect_err("late").to_string();
        assert!(e.contains("after the run's end"), "{e}");
    }

    #[test]
    fn overlapping_faults_of_one_role_are_refused_naming_both() {
        let check = |specs: &[&str]| {
            let specs: Vec<String> = specs.iter().map(|s| s.to_string()).collect();
            let faults: Vec<Fault> =
                specs.iter().map(|s| parse_fault(s, 1000.0).expect("valid")).collect();
            check_overlaps(&specs, &faults)
        };
        let e = check(&["plant:kill@5.47:restart@5.86", "plant:kill@5.83:restart@6.02"])
            .expect_err("overlap");
        assert!(e.0.contains("plant:kill@5.47:restart@5.86"), "{e}");
        assert!(e.0.contains("plant:kill@5.83:restart@6.02"), "{e}");
        // A kill with no restart keeps the role down to the end.
        assert!(check(&["monitor:kill@1", "monitor:stop@9:cont@10"]).is_err());
        assert!(check(&["controller:delay@1=0.01", "controller:delay@2=0.02:until@3"]).is_err());
        // Back to back, other roles, or a delay during a kill: each is well defined.
        assert!(check(&["plant:kill@1:restart@2", "plant:kill@2:restart@3"]).is_ok());
        assert!(check(&["plant:kill@1:restart@2", "controller:kill@1:restart@2"]).is_ok());
        assert!(check(&["controller:kill@1:restart@2", "controller:delay@1=0.01"]).is_ok());
    }

    #[test]
    fn a_delay_as_long_as_the_run_is_refused_naming_both() {
        let specs = ["controller:delay@0=60".to_owned(), "controller:kill@1".to_owned()];
        let faults: Vec<Fault> =
            specs.iter().map(|s| parse_fault(s, 1000.0).expect("valid")).collect();
        let run = |ticks| RunShape { ticks, rate_hz: 1000.0, lockstep: true, no_watchdog: false };
        let e = check_against_run(&specs, &faults, run(2000)).expect_err("longer than the run");
        assert!(e.0.contains("controller:delay@0=60") && e.0.contains("(2 s)"), "{e}");
        assert!(check_against_run(&specs[..1], &faults[..1], run(60_500)).is_ok());
    }

    #[test]
    fn a_kill_without_restart_is_not_awaited() {
        let mut s = schedule(&["monitor:kill@1"], false);
        s.due(Some(2000), 0);
        assert!(!s.awaiting_restart());
    }

    #[test]
    fn bad_faults_are_refused_naming_what_is_allowed() {
        for (f, why) in [
            ("pilot:kill@1", "ROLE is plant"),
            ("plant:kill@-1", "SECONDS ≥ 0"),
            ("plant:kill@2:restart@1", "after the kill"),
            ("plant", "two or three parts"),
        ] {
            let e = parse_fault(f, 1000.0).expect_err(f).to_string();
            assert!(e.contains(why) && e.contains(f), "{f}: {e}");
        }
    }

    #[test]
    fn a_stop_and_its_cont_are_due_like_a_kill_and_its_restart() {
        let mut s = schedule(&["controller:stop@1:cont@3"], false);
        assert_eq!(s.due(Some(1000), 0), [act("controller", FaultKind::Stop, true)]);
        assert!(!s.awaiting_restart(), "a stopped role is still there");
        assert_eq!(s.due(Some(3000), 0), [act("controller", FaultKind::Stop, false)]);
        let e =
            parse_fault("controller:stop@2:cont@1", 1000.0).expect_err("cont first").to_string();
        assert!(e.contains("cont must come after the stop"), "{e}");
        assert!(parse_fault("controller:stop@2:restart@3", 1000.0).is_err());
    }

    #[test]
    fn an_injected_delay_is_the_controllers_and_is_reported_at_its_start_and_end() {
        let f = parse_fault("controller:delay@1=0.005:until@3", 1000.0).expect("valid");
        assert_eq!((f.kind, f.kill_s, f.restart_s), (FaultKind::Delay(0.005), 1.0, Some(3.0)));
        assert_eq!(f.role_arg(), Some(("--inject-delay", "1=0.005:3".to_owned())));
        let mut s = FaultSchedule::new(vec![f], true);
        assert_eq!(s.due(Some(1000), 0), [act("controller", FaultKind::Delay(0.005), true)]);
        assert_eq!(s.due(Some(3000), 0), [act("controller", FaultKind::Delay(0.005), false)]);
        for (bad, why) in [
            ("plant:delay@1=0.005", "only the controller"),
            ("plant:zap@1", "not a kind: kill, stop, delay"),
            ("controller:delay@1", "delay@T=SECONDS"),
            ("controller:delay@1=0", "> 0"),
            ("controller:delay@2=0.1:until@1", "until must come after the delay"),
        ] {
            let e = parse_fault(bad, 1000.0).expect_err(bad).to_string();
            assert!(e.contains(why), "{bad}: {e}");
        }
    }
}
