//! What the launcher decides about its children, as plain structs with the time passed in:
//! [`FaultSchedule`] says which `--fault` kill or restart is due (seconds since the plant
//! published tick 0), and [`exit_verdict`] says whether a child's exit fails the run. The
//! launcher ([`crate::launch`]) spawns, signals and reaps; [`Children`] holds the
//! processes and stops them all when dropped.

use std::os::unix::process::ExitStatusExt;
use std::process::{Child, ExitStatus};

use crate::UsageError;

/// The roles, in start order (the monitor first, so it sees tick 0).
pub const ROLES: [&str; 4] = ["monitor", "reference", "controller", "plant"];

/// One `--fault ROLE:kill@T[:restart@T2]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Fault {
    /// The role to kill.
    pub role: String,
    /// When to SIGKILL it (s after tick 0).
    pub kill_s: f64,
    /// When to start it again (s), if at all.
    pub restart_s: Option<f64>,
    killed: bool,
    restarted: bool,
}

/// Parses `ROLE:kill@T[:restart@T2]`.
pub fn parse_fault(s: &str) -> Result<Fault, UsageError> {
    let bad = |why: &str| {
        UsageError(format!(
            "--fault `{s}` is not allowed: {why} (form ROLE:kill@T[:restart@T2], e.g. controller:kill@2:restart@2.5)"
        ))
    };
    let parts: Vec<&str> = s.split(':').collect();
    if parts.len() < 2 || parts.len() > 3 {
        return Err(bad("two or three parts"));
    }
    if !ROLES.contains(&parts[0]) {
        return Err(bad("ROLE is plant, reference, controller or monitor"));
    }
    let time = |p: &str, key: &str| -> Result<f64, UsageError> {
        p.strip_prefix(key)
            .and_then(|t| t.parse::<f64>().ok())
            .filter(|t| t.is_finite() && *t >= 0.0)
            .ok_or_else(|| bad(&format!("`{p}` must be {key}SECONDS with SECONDS ≥ 0")))
    };
    let kill_s = time(parts[1], "kill@")?;
    let restart_s = parts.get(2).map(|p| time(p, "restart@")).transpose()?;
    if restart_s.is_some_and(|r| r <= kill_s) {
        return Err(bad("the restart must come after the kill"));
    }
    Ok(Fault { role: parts[0].to_owned(), kill_s, restart_s, killed: false, restarted: false })
}

/// What the schedule asks the launcher to do now.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Action {
    /// SIGKILL this role.
    Kill(String),
    /// Start this role again with its original arguments.
    Restart(String),
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
            if !f.killed && t >= f.kill_s {
                f.killed = true;
                actions.push(Action::Kill(f.role.clone()));
            }
            if f.killed && !f.restarted && f.restart_s.is_some_and(|r| t >= r) {
                f.restarted = true;
                actions.push(Action::Restart(f.role.clone()));
            }
        }
        actions
    }

    /// A role was killed and its restart is still to come: the run is not over even if
    /// no child runs.
    pub fn awaiting_restart(&self) -> bool {
        self.faults.iter().any(|f| f.killed && !f.restarted && f.restart_s.is_some())
    }
}

/// Whether a child's exit fails the run: a failure message, or `None` for a clean exit,
/// an exit during the launcher's own stop, or the SIGKILL of a fault it injected.
pub fn exit_verdict(
    role: &str,
    status: ExitStatus,
    killed_by_us: bool,
    stopping: bool,
) -> Option<String> {
    let planned = killed_by_us && status.signal() == Some(libc::SIGKILL);
    (!status.success() && !stopping && !planned).then(|| format!("{role} exited with {status}"))
}

/// The launcher's children, by role. Dropping it SIGKILLs and reaps any still running.
#[derive(Debug, Default)]
pub struct Children(pub Vec<(String, Child)>);

impl Children {
    /// The child of `role`.
    pub fn get_mut(&mut self, role: &str) -> Option<&mut Child> {
        self.0.iter_mut().find(|(r, _)| r == role).map(|(_, c)| c)
    }

    /// Sends `sig` to every child.
    pub fn signal_all(&self, sig: libc::c_int) {
        for (_, c) in &self.0 {
            signal(c, sig);
        }
    }
}

impl Drop for Children {
    fn drop(&mut self) {
        for (_, c) in &mut self.0 {
            if let Ok(None) = c.try_wait() {
                let _ = c.kill();
                let _ = c.wait();
            }
        }
    }
}

/// Sends `sig` to `child`.
pub fn signal(child: &Child, sig: libc::c_int) {
    // SAFETY: sends a signal to our own child's pid.
    unsafe { libc::kill(child.id() as libc::pid_t, sig) };
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
    fn a_kill_without_restart_is_not_awaited() {
        let mut s = FaultSchedule::new(vec![parse_fault("monitor:kill@1").expect("valid")]);
        s.due(Some(2.0));
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
            let e = parse_fault(f).expect_err(f).to_string();
            assert!(e.contains(why) && e.contains(f), "{f}: {e}");
        }
    }

    #[test]
    fn only_an_unplanned_abnormal_exit_fails_the_run() {
        let exited = |code: i32| ExitStatus::from_raw(code << 8);
        let killed = ExitStatus::from_raw(libc::SIGKILL);
        assert_eq!(exit_verdict("plant", exited(0), false, false), None);
        assert!(
            exit_verdict("plant", exited(1), false, false).is_some_and(|m| m.contains("plant"))
        );
        assert_eq!(exit_verdict("plant", killed, true, false), None, "our own fault injection");
        assert!(exit_verdict("plant", killed, false, false).is_some(), "killed by someone else");
        assert_eq!(exit_verdict("plant", exited(1), false, true), None, "while stopping");
    }
}
