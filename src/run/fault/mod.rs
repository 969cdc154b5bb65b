//! One home for fault kinds: what `--fault` can ask for (its syntax and the roles it
//! allows, [`parse_fault`]), when each part is due ([`FaultSchedule`]), and a fault as it
//! happened ([`FaultEvent`]), whether the schedule injected it or the supervisor saw it.
//! What each fault cost is computed after the run in [`report`].
//!
//! The launcher applies the due [`Action`]s (a signal to a child, or the controller's
//! `--inject-delay` for a delay) in `run::launch`.

pub mod report;

use rotorloop_common::ipc::now_ns;

use rotorloop_common::graph::Role;
use rotorloop_common::role::UsageError;

/// What a `--fault` does.
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

/// One `--fault`: `ROLE:kill@T[:restart@T2]`, `ROLE:stop@T[:cont@T2]` or
/// `controller:delay@T=SECONDS[:until@T2]`.
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
    /// The controller's `--inject-delay FROM=SECONDS[:UNTIL]` of a delay fault.
    pub fn inject_delay_arg(&self) -> Option<String> {
        match self.kind {
            FaultKind::Delay(d) => Some(match self.restart_s {
                Some(u) => format!("{}={d}:{u}", self.kill_s),
                None => format!("{}={d}", self.kill_s),
            }),
            _ => None,
        }
    }
}

/// Parses a `--fault` (see [`Fault`]).
pub fn parse_fault(s: &str) -> Result<Fault, UsageError> {
    let bad = |why: &str| {
        UsageError(format!(
            "--fault `{s}` is not allowed: {why} (form ROLE:kill@T[:restart@T2], \
             ROLE:stop@T[:cont@T2] or controller:delay@T=SECONDS[:until@T2], e.g. controller:kill@2:restart@2.5)"
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
    let time = |p: &str, key: &str| match p.strip_prefix(key) {
        Some(t) => seconds(t, &format!("the time of {key}")),
        None => Err(bad(&format!("`{p}` must be {key}SECONDS"))),
    };
    let (kind, first, then) = match parts[1].split_once('@').map(|(k, _)| k) {
        Some("stop") => (FaultKind::Stop, "stop@", "cont@"),
        Some("delay") => {
            let (_, spec) = parts[1].split_once('@').unwrap_or_default();
            let (_, d) = spec.split_once('=').ok_or_else(|| bad("delay@T=SECONDS"))?;
            let d = seconds(d, "the delay").and_then(|d| match d > 0.0 && d <= 60.0 {
                true => Ok(d),
                false => Err(bad("the delay must be > 0 and ≤ 60 s")),
            })?;
            if parts[0] != Role::Controller.name() {
                return Err(bad("only the controller's answers can be delayed"));
            }
            (FaultKind::Delay(d), "delay@", "until@")
        }
        _ => (FaultKind::Kill, "kill@", "restart@"),
    };
    let start = match kind {
        FaultKind::Delay(_) => parts[1].split_once('=').map_or(parts[1], |(t, _)| t),
        _ => parts[1],
    };
    let kill_s = time(start, first)?;
    let restart_s = parts.get(2).map(|p| time(p, then)).transpose()?;
    if restart_s.is_some_and(|r| r <= kill_s) {
        let (a, b) = (&then[..then.len() - 1], &first[..first.len() - 1]);
        return Err(bad(&format!("the {a} must come after the {b}")));
    }
    let (killed, restarted) = (false, false);
    Ok(Fault { role: parts[0].to_owned(), kind, kill_s, restart_s, killed, restarted })
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

/// What the schedule asks the launcher to do now.
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    /// SIGKILL this role.
    Kill(String),
    /// Start this role again with its original arguments.
    Restart(String),
    /// SIGSTOP this role (an injected hang).
    Stop(String),
    /// SIGCONT this role.
    Cont(String),
    /// The controller's injected delay starts (`true`) or ends (the controller applies
    /// it; the launcher reports it).
    Delay(String, f64, bool),
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
            let r = f.role.clone();
            if !f.killed && t >= f.kill_s {
                f.killed = true;
                actions.push(match f.kind {
                    FaultKind::Kill => Action::Kill(r.clone()),
                    FaultKind::Stop => Action::Stop(r.clone()),
                    FaultKind::Delay(d) => Action::Delay(r.clone(), d, true),
                });
            }
            if f.killed && !f.restarted && f.restart_s.is_some_and(|at| t >= at) {
                f.restarted = true;
                actions.push(match f.kind {
                    FaultKind::Kill => Action::Restart(r),
                    FaultKind::Stop => Action::Cont(r),
                    FaultKind::Delay(d) => Action::Delay(r, d, false),
                });
            }
        }
        actions
    }

    /// The parts of faults not carried out (the run ended first), in words.
    pub fn not_done(&self) -> Vec<String> {
        let mut out = Vec::new();
        for f in &self.faults {
            let (start, end) = match f.kind {
                FaultKind::Kill => ("kill", "restart"),
                FaultKind::Stop => ("stop", "cont"),
                FaultKind::Delay(_) => ("delay", "until"),
            };
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
    /// `kill` or `stop` (injected by `--fault`), `killed`, `crash`, `exited` or `hang`.
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

    #[test]
    fn nothing_is_due_before_tick_zero_however_late() {
        let mut s = FaultSchedule::new(vec![parse_fault("controller:kill@0").expect("valid")]);
        assert!(s.due(None).is_empty());
        assert_eq!(s.due(Some(0.0)), [Action::Kill("controller".into())]);
    }

    #[test]
    fn a_kill_then_its_restart_are_due_once_each_in_order() {
        let mut s =
            FaultSchedule::new(vec![parse_fault("plant:kill@1:restart@1.5").expect("valid")]);
        assert!(s.due(Some(0.9)).is_empty());
        assert_eq!(s.due(Some(1.0)), [Action::Kill("plant".into())]);
        assert!(s.awaiting_restart());
        assert!(s.due(Some(1.2)).is_empty());
        assert_eq!(s.due(Some(1.6)), [Action::Restart("plant".into())]);
        assert!(!s.awaiting_restart());
        assert!(s.due(Some(9.0)).is_empty());
        // A late poll that passes both times at once does both, kill first.
        let mut late =
            FaultSchedule::new(vec![parse_fault("monitor:kill@1:restart@2").expect("ok")]);
        let both = late.due(Some(5.0));
        assert_eq!(both, [Action::Kill("monitor".into()), Action::Restart("monitor".into())]);
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
        assert_eq!(s.due(Some(1.0)), [Action::Stop("controller".into())]);
        assert!(!s.awaiting_restart(), "a stopped role is still there");
        assert_eq!(s.due(Some(3.0)), [Action::Cont("controller".into())]);
        let e = parse_fault("controller:stop@2:cont@1").expect_err("cont first").to_string();
        assert!(e.contains("cont must come after the stop"), "{e}");
        assert!(parse_fault("controller:stop@2:restart@3").is_err());
    }

    #[test]
    fn an_injected_delay_is_the_controllers_and_is_reported_at_its_start_and_end() {
        let f = parse_fault("controller:delay@1=0.005:until@3").expect("valid");
        assert_eq!((f.kind, f.kill_s, f.restart_s), (FaultKind::Delay(0.005), 1.0, Some(3.0)));
        assert_eq!(f.inject_delay_arg().as_deref(), Some("1=0.005:3"));
        let mut s = FaultSchedule::new(vec![f]);
        assert_eq!(s.due(Some(1.0)), [Action::Delay("controller".into(), 0.005, true)]);
        assert_eq!(s.due(Some(3.0)), [Action::Delay("controller".into(), 0.005, false)]);
        for (bad, why) in [
            ("plant:delay@1=0.005", "only the controller"),
            ("controller:delay@1", "delay@T=SECONDS"),
            ("controller:delay@1=0", "> 0"),
            ("controller:delay@2=0.1:until@1", "until must come after the delay"),
        ] {
            let e = parse_fault(bad).expect_err(bad).to_string();
            assert!(e.contains(why), "{bad}: {e}");
        }
    }
}
