//! One home for fault kinds: what `--fault` can ask for (its syntax and the roles it
//! allows, [`parse_fault`]), when each part is due ([`FaultSchedule`]), and a fault as it
//! happened ([`FaultEvent`]), whether the schedule injected it or the supervisor saw it.
//! What each fault cost is computed after the run in [`report`].
//!
//! Each kind is one row of [`KINDS`]: its syntax, the roles it allows, its help line (the
//! `--help` of `--fault` is made from them), how its start and end are applied
//! ([`Apply`]: a signal, a restart, or an argument the role applies itself) and the word
//! its events and report rows use. The launcher carries out the due [`Action`]s by that
//! column in `run::launch`. `--corrupt` ([`parse_corrupt`]) is addressed by tick, not by
//! time: the role corrupts its own sample (`rotorloop_common::role::inject`, with the
//! tests' hidden hooks).

pub mod report;

use rotorloop_common::clock::now_ns;

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
        "Inject a fault at T seconds after the plant published tick 0 (so a slow start never \
         moves a fault before the run): {}. ROLE is plant, reference, controller, monitor or, \
         with --split, a gateway (link-HOST). Repeatable; one role takes one fault at a time",
        kinds.join("; ")
    )
}

/// One `--fault`: a row of [`KINDS`] for a role, its start and its optional end.
#[derive(Debug, Clone, PartialEq)]
pub struct Fault {
    /// The role.
    pub role: String,
    /// What it does.
    pub kind: FaultKind,
    /// When it starts (s after tick 0).
    pub kill_s: f64,
    /// When it ends: restart, SIGCONT, or the delay's end (s), if at all.
    pub restart_s: Option<f64>,
    killed: bool,
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
            "role": self.role,
            "kind": self.kind.spec().start,
            "at_s": self.kill_s,
            "until_s": self.restart_s,
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

/// Parses a `--fault` by the rows of [`KINDS`].
pub fn parse_fault(s: &str) -> Result<Fault, UsageError> {
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
    let gateway = parts[0].strip_prefix("link-").is_some_and(|h| !h.is_empty());
    if parts[0].parse::<Role>().is_err() && !gateway {
        return Err(bad(
            "ROLE is plant, reference, controller, monitor or (with --split) link-HOST",
        ));
    }
    let seconds = |p: &str, what: &str| -> Result<f64, UsageError> {
        p.parse::<f64>()
            .ok()
            .filter(|t| t.is_finite() && *t >= 0.0)
            .ok_or_else(|| bad(&format!("`{p}` must be {what}, seconds ≥ 0")))
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
    if let Targets::Only(role) = spec.targets
        && parts[0] != role.name()
    {
        return Err(bad(&format!("only the {}'s answers can take a {word}", role.name())));
    }
    let kill_s = seconds(at, &format!("the time of {word}@"))?;
    let time = |p: &str, key: &str| match p.strip_prefix(key).and_then(|p| p.strip_prefix('@')) {
        Some(t) => seconds(t, &format!("the time of {key}@")),
        None => Err(bad(&format!("`{p}` must be {key}@SECONDS"))),
    };
    let restart_s = parts.get(2).map(|p| time(p, spec.end)).transpose()?;
    if restart_s.is_some_and(|r| r <= kill_s) {
        return Err(bad(&format!("the {} must come after the {}", spec.end, spec.start)));
    }
    let kind = FaultKind::of(spec, value);
    let (killed, restarted) = (false, false);
    Ok(Fault { role: parts[0].to_owned(), kind, kill_s, restart_s, killed, restarted })
}

/// Parses `--corrupt ROLE:KIND@TICK`: a fault the role applies to its own sample of
/// that tick (`rotorloop_common::role::inject`), so it is addressed by tick, not by time.
pub fn parse_corrupt(s: &str) -> Result<(String, Corrupt), UsageError> {
    use rotorloop_common::role::inject::CorruptKind;
    let bad = |why: &str| {
        UsageError(format!(
            "--corrupt `{s}` is not allowed: {why} (form ROLE:KIND@TICK, e.g. controller:nan@500)"
        ))
    };
    let (role, rest) = s.split_once(':').ok_or_else(|| bad("no ROLE:"))?;
    if ![Role::Plant, Role::Reference, Role::Controller].map(Role::name).contains(&role) {
        return Err(bad("ROLE is plant, reference or controller"));
    }
    let c: Corrupt = rest.parse().map_err(|e: String| bad(&e))?;
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

/// Refuses a `--fault` delay as long as the run or longer (`duration_s`, the run's
/// simulated length): no answer it holds back would reach the plant within the run, and
/// in lockstep, where the plant waits for each answer, the run would take the delay times
/// its ticks (`controller:delay@0=60` on a 2 s run: 33 hours).
pub fn check_against_run(
    specs: &[String],
    faults: &[Fault],
    duration_s: f64,
) -> Result<(), UsageError> {
    for (spec, f) in specs.iter().zip(faults) {
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
    /// The role.
    pub role: String,
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

/// The `--fault` schedule.
#[derive(Debug, Clone, Default)]
pub struct FaultSchedule {
    faults: Vec<Fault>,
}

impl FaultSchedule {
    /// The schedule of these faults.
    pub fn new(faults: Vec<Fault>) -> Self {
        Self { faults }
    }

    /// What is due at `elapsed_s` seconds after tick 0 (`None`: tick 0 not yet published,
    /// so nothing is due), each fault's kill once, then its restart once.
    pub fn due(&mut self, elapsed_s: Option<f64>) -> Vec<Action> {
        let Some(t) = elapsed_s else { return Vec::new() };
        let mut actions = Vec::new();
        for f in &mut self.faults {
            let (role, kind, ends) = (&f.role, f.kind, f.restart_s.is_some());
            if !f.killed && t >= f.kill_s {
                f.killed = true;
                actions.push(Action { role: role.clone(), kind, starts: true, ends });
            }
            if f.killed && !f.restarted && f.restart_s.is_some_and(|at| t >= at) {
                f.restarted = true;
                actions.push(Action { role: role.clone(), kind, starts: false, ends });
            }
        }
        actions
    }

    /// The parts of faults not carried out (the run ended first), in words.
    pub fn not_done(&self) -> Vec<String> {
        let mut out = Vec::new();
        for f in &self.faults {
            let KindSpec { start, end, .. } = f.kind.spec();
            if !f.killed {
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
        self.faults
            .iter()
            .any(|f| f.kind == FaultKind::Kill && f.killed && !f.restarted && f.restart_s.is_some())
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
}

impl FaultEvent {
    /// A fault of `role` happening now, not (yet) followed by a restart.
    pub(crate) fn now(role: impl Into<String>, kind: &'static str, detail: String) -> Self {
        let (role, kill_ns) = (role.into(), now_ns());
        Self { role, kind, detail, kill_ns, restart_ns: None, signal: None, ended: None }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn act(role: &str, kind: FaultKind, starts: bool) -> Action {
        Action { role: role.to_owned(), kind, starts, ends: true }
    }

    #[test]
    fn nothing_is_due_before_tick_zero_however_late() {
        let mut s = FaultSchedule::new(vec![parse_fault("controller:kill@0").expect("valid")]);
        assert!(s.due(None).is_empty());
        let kill = Action { ends: false, ..act("controller", FaultKind::Kill, true) };
        assert_eq!(s.due(Some(0.0)), [kill]);
    }

    #[test]
    fn a_kill_then_its_restart_are_due_once_each_in_order() {
        let mut s =
            FaultSchedule::new(vec![parse_fault("plant:kill@1:restart@1.5").expect("valid")]);
        assert!(s.due(Some(0.9)).is_empty());
        assert_eq!(s.due(Some(1.0)), [act("plant", FaultKind::Kill, true)]);
        assert!(s.awaiting_restart());
        assert!(s.due(Some(1.2)).is_empty());
        assert_eq!(s.due(Some(1.6)), [act("plant", FaultKind::Kill, false)]);
        assert!(!s.awaiting_restart());
        assert!(s.due(Some(9.0)).is_empty());
        // A late poll that passes both times at once does both, kill first.
        let mut late =
            FaultSchedule::new(vec![parse_fault("monitor:kill@1:restart@2").expect("ok")]);
        let both = late.due(Some(5.0));
        assert_eq!(
            both,
            [act("monitor", FaultKind::Kill, true), act("monitor", FaultKind::Kill, false)]
        );
    }

    #[test]
    fn overlapping_faults_of_one_role_are_refused_naming_both() {
        let check = |specs: &[&str]| {
            let specs: Vec<String> = specs.iter().map(|s| s.to_string()).collect();
            let faults: Vec<Fault> = specs.iter().map(|s| parse_fault(s).expect("valid")).collect();
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
        let faults: Vec<Fault> = specs.iter().map(|s| parse_fault(s).expect("valid")).collect();
        let e = check_against_run(&specs, &faults, 2.0).expect_err("longer than the run");
        assert!(e.0.contains("controller:delay@0=60") && e.0.contains("(2 s)"), "{e}");
        assert!(check_against_run(&specs[..1], &faults[..1], 60.5).is_ok());
    }

    #[test]
    fn a_kill_without_restart_is_not_awaited() {
        let mut s = FaultSchedule::new(vec![parse_fault("monitor:kill@1").expect("valid")]);
        s.due(Some(2.0));
        assert!(!s.awaiting_restart());
    }

    #[test]
    fn bad_faults_are_refused_naming_what_is_allowed() {
        for (f, why) in [
            ("pilot:kill@1", "ROLE is plant"),
            ("plant:kill@-1", "seconds ≥ 0"),
            ("plant:kill@2:restart@1", "after the kill"),
            ("plant", "two or three parts"),
        ] {
            let e = parse_fault(f).expect_err(f).to_string();
            assert!(e.contains(why) && e.contains(f), "{f}: {e}");
        }
    }

    #[test]
    fn a_stop_and_its_cont_are_due_like_a_kill_and_its_restart() {
        let mut s =
            FaultSchedule::new(vec![parse_fault("controller:stop@1:cont@3").expect("valid")]);
        assert_eq!(s.due(Some(1.0)), [act("controller", FaultKind::Stop, true)]);
        assert!(!s.awaiting_restart(), "a stopped role is still there");
        assert_eq!(s.due(Some(3.0)), [act("controller", FaultKind::Stop, false)]);
        let e = parse_fault("controller:stop@2:cont@1").expect_err("cont first").to_string();
        assert!(e.contains("cont must come after the stop"), "{e}");
        assert!(parse_fault("controller:stop@2:restart@3").is_err());
    }

    #[test]
    fn an_injected_delay_is_the_controllers_and_is_reported_at_its_start_and_end() {
        let f = parse_fault("controller:delay@1=0.005:until@3").expect("valid");
        assert_eq!((f.kind, f.kill_s, f.restart_s), (FaultKind::Delay(0.005), 1.0, Some(3.0)));
        assert_eq!(f.role_arg(), Some(("--inject-delay", "1=0.005:3".to_owned())));
        let mut s = FaultSchedule::new(vec![f]);
        assert_eq!(s.due(Some(1.0)), [act("controller", FaultKind::Delay(0.005), true)]);
        assert_eq!(s.due(Some(3.0)), [act("controller", FaultKind::Delay(0.005), false)]);
        for (bad, why) in [
            ("plant:delay@1=0.005", "only the controller"),
            ("plant:zap@1", "not a kind: kill, stop, delay"),
            ("controller:delay@1", "delay@T=SECONDS"),
            ("controller:delay@1=0", "> 0"),
            ("controller:delay@2=0.1:until@1", "until must come after the delay"),
        ] {
            let e = parse_fault(bad).expect_err(bad).to_string();
            assert!(e.contains(why), "{bad}: {e}");
        }
    }
}
