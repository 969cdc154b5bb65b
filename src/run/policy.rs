//! What the launcher decides about its children, as plain structs with the time passed in
//! (seconds since the plant published tick 0):
//!
//! - [`FaultSchedule`](super::fault::FaultSchedule): which `--fault` kill, restart, stop (SIGSTOP) or continue
//!   (SIGCONT) is due.
//! - [`Supervisor`]: what happens when a role exits or hangs that nobody planned: started
//!   again by its [`RestartPolicy`] (systemd's `Restart=`), after a backoff, unless it
//!   restarted too often in the window ([`RestartLimit`], systemd's `StartLimitBurst` /
//!   `StartLimitIntervalSec`, Erlang's restart intensity): then the run stops, naming the
//!   role and its last exit.
//! - [`Watchdog`]: a role with work waiting that makes no progress (its resume slot's
//!   mark does not move) for the timeout is hung (systemd's `WatchdogSec`), whatever its
//!   process state.
//!
//! The launcher ([`crate::run::launch`]) spawns, signals and reaps; [`Children`] holds the
//! processes and stops them all when dropped.

use std::collections::BTreeMap;
use std::os::unix::process::ExitStatusExt;
use std::process::{Child, ExitStatus};

use rotorloop_common::graph::Role;

use rotorloop_common::role::UsageError;
use rotorloop_common::wire::Refusals;

/// When a role that ended on its own is started again (systemd's `Restart=`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RestartPolicy {
    /// After an abnormal exit: a signal (a `kill -9` by anyone, a crash), a non-zero exit
    /// code other than 2, or a hang found by the watchdog.
    OnFailure,
    /// As `on-failure`, and also after a clean exit before the plant's last tick.
    Always,
    /// Never: an abnormal exit stops the run.
    Never,
}

impl std::str::FromStr for RestartPolicy {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "on-failure" => Ok(Self::OnFailure),
            "always" => Ok(Self::Always),
            "never" => Ok(Self::Never),
            _ => Err(format!("`{s}` is not a restart policy: on-failure, always or never")),
        }
    }
}

impl std::fmt::Display for RestartPolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::OnFailure => "on-failure",
            Self::Always => "always",
            Self::Never => "never",
        })
    }
}

/// Parses `--restart POLICY` or `ROLE=POLICY,…` (or both: `never,monitor=always`); a
/// role not named gets the bare policy, `on-failure` by default.
pub fn parse_restart(s: &str) -> Result<BTreeMap<String, RestartPolicy>, UsageError> {
    let bad = |why: String| {
        UsageError(format!(
            "--restart `{s}` is not allowed: {why} (form POLICY or ROLE=POLICY,…, e.g. monitor=always,plant=never)"
        ))
    };
    let mut default = RestartPolicy::OnFailure;
    let mut by_role = BTreeMap::new();
    for part in s.split(',').filter(|p| !p.is_empty()) {
        match part.split_once('=') {
            Some((role, p)) if role.parse::<Role>().is_ok() => {
                by_role.insert(role.to_owned(), p.parse().map_err(bad)?);
            }
            Some((role, _)) => {
                return Err(bad(format!(
                    "`{role}` is not a role: plant, reference, controller or monitor"
                )));
            }
            None => default = part.parse().map_err(bad)?,
        }
    }
    Ok(Role::ALL
        .iter()
        .map(|r| (r.to_string(), by_role.get(r.name()).copied().unwrap_or(default)))
        .collect())
}

/// At most `burst` unplanned restarts of one role within `window_s` seconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RestartLimit {
    /// Restarts allowed in the window.
    pub burst: usize,
    /// The window (s).
    pub window_s: f64,
}

impl std::str::FromStr for RestartLimit {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad =
            || format!("`{s}` is not allowed: N/SECONDS with N ≥ 1 and SECONDS > 0, e.g. 5/10");
        let (n, w) = s.split_once('/').ok_or_else(bad)?;
        let burst = n.parse::<usize>().ok().filter(|n| *n >= 1).ok_or_else(bad)?;
        let window_s =
            w.parse::<f64>().ok().filter(|w| w.is_finite() && *w > 0.0).ok_or_else(bad)?;
        Ok(Self { burst, window_s })
    }
}

/// How a role ended, as far as the report goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ending {
    /// Killed by SIGKILL (by anyone: a user's `kill -9`, the OOM killer).
    Killed,
    /// Another signal, or a non-zero exit code.
    Crash,
    /// A clean exit (restarted only by `always`).
    Exited,
    /// Found hung by the watchdog and killed.
    Hang,
    /// A controller whose every answer the plant refused ([`RejectWatch`]), killed.
    Rejected,
}

impl Ending {
    /// The report's name of it.
    pub fn name(self) -> &'static str {
        match self {
            Self::Killed => "killed",
            Self::Crash => "crash",
            Self::Exited => "exited",
            Self::Hang => "hang",
            Self::Rejected => "rejected",
        }
    }

    /// How a process that exited with `status` ended.
    pub fn of(status: ExitStatus) -> Self {
        match status.signal() {
            Some(libc::SIGKILL) => Self::Killed,
            Some(_) => Self::Crash,
            None if status.success() => Self::Exited,
            None => Self::Crash,
        }
    }
}

/// What the supervisor decided about an unplanned ending.
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    /// Nothing to do: a clean end.
    Done,
    /// Start the role again at `at_s`.
    Restart {
        /// When (s after tick 0): now, or after the backoff.
        at_s: f64,
    },
    /// Stop the run: the message names the role and its last exit.
    Fail(String),
}

/// How a [`Verdict::Fail`] of a role that exited 2 ends (the launcher exits 2 on it too).
pub const REFUSED: &str = "a bad argument or scenario value, or the run diverged: not restarted";

/// The restart rule (module docs).
#[derive(Debug, Clone)]
pub struct Supervisor {
    policies: BTreeMap<String, RestartPolicy>,
    limit: RestartLimit,
    roles: BTreeMap<String, RestartRecord>,
}

/// One role's restarts, aged by the time it ran with progress (see [`Supervisor::on_end`]).
#[derive(Debug, Clone, Default)]
struct RestartRecord {
    /// Time run with progress so far (s): from the first progress after each start to the
    /// last progress before its end.
    healthy_s: f64,
    /// The first and the last progress of the current incarnation (s).
    progress: Option<(f64, f64)>,
    /// `healthy_s` at each restart still in the window.
    restarts: Vec<f64>,
}

/// The first restart of a role is immediate; each further one within the window waits
/// twice as long as the one before, from this, up to [`MAX_BACKOFF_S`].
pub const FIRST_BACKOFF_S: f64 = 0.1;
/// The longest backoff.
pub const MAX_BACKOFF_S: f64 = 2.0;

impl Supervisor {
    /// Restarts by `policies` (one per role) within `limit`.
    pub fn new(policies: BTreeMap<String, RestartPolicy>, limit: RestartLimit) -> Self {
        Self { policies, limit, roles: BTreeMap::new() }
    }

    /// The policy of `role`.
    pub fn policy(&self, role: &str) -> RestartPolicy {
        self.policies.get(role).copied().unwrap_or(RestartPolicy::OnFailure)
    }

    /// `role` made progress at `now_s` (its mark moved: for a controller, a torque the plant
    /// accepted).
    pub fn progressed(&mut self, role: &str, now_s: f64) {
        let r = self.roles.entry(role.to_owned()).or_default();
        r.progress = Some(r.progress.map_or((now_s, now_s), |(first, _)| (first, now_s)));
    }

    /// `role` ended unplanned (`how`, described by `what`, e.g. its exit status) at `now_s`;
    /// `run_over`: the plant has published its last tick. Exit code 2 (a bad argument or
    /// scenario value, or a run that diverged) is never restarted: it would fail again. A
    /// clean exit before the run's last tick is an end like any other (the role left work
    /// undone), restarted only by `always`: under `on-failure` and `never` it stops the run.
    ///
    /// The restart intensity counts a role's restarts within `window_s` of the time it ran
    /// *with progress* (its first to its last progress in each incarnation), not of the
    /// wall clock: a role that never makes progress is found hung only after the start
    /// timeout (10 s), so its restarts were never 5 within 10 s of wall time, and a lockstep
    /// run whose controller never answered was restarted every 10 s for ever.
    pub fn on_end(
        &mut self,
        role: &str,
        how: Ending,
        what: &str,
        code: Option<i32>,
        now_s: f64,
        run_over: bool,
    ) -> Verdict {
        let policy = self.policy(role);
        match how {
            Ending::Exited if run_over => return Verdict::Done,
            Ending::Exited if policy != RestartPolicy::Always => {
                return Verdict::Fail(format!(
                    "{role} {what} before the run's last tick (restart policy {policy} does not \
                     restart a clean exit; --restart {role}=always does)"
                ));
            }
            _ if code == Some(2) => {
                return Verdict::Fail(format!("{role} {what} ({REFUSED})"));
            }
            _ if policy == RestartPolicy::Never => {
                return Verdict::Fail(format!("{role} {what} (restart policy {policy})"));
            }
            _ => {}
        }
        let window = self.limit.window_s;
        let r = self.roles.entry(role.to_owned()).or_default();
        if let Some((first, last)) = r.progress.take() {
            r.healthy_s += last - first;
        }
        let healthy = r.healthy_s;
        r.restarts.retain(|h| healthy - h < window);
        if r.restarts.len() >= self.limit.burst {
            return Verdict::Fail(format!(
                "{role} {what}; its restart {} within {window} s of running would pass the limit {}/{window}: not restarted again",
                r.restarts.len() + 1,
                self.limit.burst,
            ));
        }
        let backoff = match r.restarts.len() {
            0 => 0.0,
            n => (FIRST_BACKOFF_S * 2f64.powi(n as i32 - 1)).min(MAX_BACKOFF_S),
        };
        r.restarts.push(healthy);
        Verdict::Restart { at_s: now_s + backoff }
    }
}

/// The rule for a controller that answers but is always refused: the plant rejects its
/// torques (NaN, infinite, absurd, for a tick the loop has not reached) and accepts none.
/// That is not a hang (it answers), and not a plant's fault (the plant publishes on
/// time): it is a fault of its own kind, `rejected`, of the controller. Fed with the plant's
/// newest state as the launcher polls it: once `hold_ticks` answers in a row were rejected
/// (the plant entered safe mode for them, `--hold-ticks`) with none accepted since, the
/// controller is at fault.
#[derive(Debug, Clone, Default)]
pub struct RejectWatch {
    hold_ticks: u64,
    /// Since the last torque accepted: its tick, the plant's tick and rejections count then.
    since: Option<Streak>,
    /// The plant's tick, accepted torque and rejections at the last look.
    last: Option<(u64, u64, Refusals)>,
}

/// Rejections since the last torque the plant accepted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Streak {
    /// The newest torque tick the plant accepted then (or [`rotorloop_common::wire::NO_TICK`]).
    pub accepted: u64,
    /// The plant's tick when the streak began.
    pub from_tick: u64,
    /// The plant's rejection count when it began.
    pub rejected_before: u64,
    /// The plant's rejections by kind when it began.
    pub kinds_before: Refusals,
    /// Rejections since (filled in by [`RejectWatch::check`]).
    pub rejected: u64,
    /// The same by kind.
    pub kinds: Refusals,
    /// The plant's tick at the last check.
    pub to_tick: u64,
}

impl RejectWatch {
    /// At fault after `hold_ticks` rejections in a row (at least 1).
    pub fn new(hold_ticks: u64) -> Self {
        Self { hold_ticks: hold_ticks.max(1), since: None, last: None }
    }

    /// The plant is at `tick`, has accepted torques up to `accepted` and rejected
    /// `refused.total` in all: the streak so far, if answers were rejected since the last
    /// one accepted.
    /// Before any torque was accepted, every rejection of the run is in the streak (the
    /// first look may come after them: in lockstep one answer for a tick not reached is all
    /// a controller sends).
    pub fn streak(&mut self, tick: u64, accepted: u64, refused: Refusals) -> Option<Streak> {
        self.last = Some((tick, accepted, refused));
        let never = accepted == rotorloop_common::wire::NO_TICK;
        let rejected = refused.total;
        let s = self.since.get_or_insert_with(|| match never {
            true => Streak::begin(accepted, 0, &Refusals::default()),
            false => Streak::begin(accepted, tick, &refused),
        });
        if s.accepted != accepted || rejected < s.rejected_before {
            *s = Streak::begin(accepted, tick, &refused);
        }
        s.rejected = rejected - s.rejected_before;
        s.kinds = refused.since(&s.kinds_before);
        s.to_tick = tick;
        (s.rejected > 0).then_some(*s)
    }

    /// As [`RejectWatch::streak`]: `Some` once the streak is `hold_ticks` long (the fault).
    pub fn check(&mut self, tick: u64, accepted: u64, refused: Refusals) -> Option<Streak> {
        self.streak(tick, accepted, refused).filter(|s| s.rejected >= self.hold_ticks)
    }

    /// The controller was started again: a new streak begins with its answers, from the
    /// plant's counts at the last look.
    pub fn reset(&mut self) {
        self.since =
            self.last.map(|(tick, accepted, refused)| Streak::begin(accepted, tick, &refused));
    }
}

impl Streak {
    /// A streak beginning at the plant's `tick`, after its torque `accepted`, with the
    /// plant's rejections `refused` before it.
    fn begin(accepted: u64, tick: u64, refused: &Refusals) -> Self {
        Self {
            accepted,
            from_tick: tick,
            rejected_before: refused.total,
            kinds_before: *refused,
            rejected: 0,
            kinds: Refusals::default(),
            to_tick: tick,
        }
    }
}

/// The hang rule (module docs): per role, the last progress mark and since when there has
/// been work waiting without the mark moving.
#[derive(Debug, Clone)]
pub struct Watchdog {
    timeout_s: f64,
    marks: BTreeMap<String, (Option<u64>, f64)>,
    /// Roles restarted that have not made progress since (systemd's start phase).
    starting: std::collections::BTreeSet<String>,
}

/// How long a restarted role may take to make its first progress before it counts as
/// hung (systemd's `TimeoutStartSec` beside `WatchdogSec`): starting a process, creating
/// its node and cleaning up after its dead predecessor took over 500 ms on a loaded
/// 2-core machine, and a `--watchdog-ms` meant for a running loop killed it again.
pub const START_TIMEOUT_S: f64 = 10.0;

impl Watchdog {
    /// Finds a role hung after `timeout_s` without progress while work waits (0: never);
    /// a restarted role, after [`START_TIMEOUT_S`] (or `timeout_s`, if longer) until its
    /// first progress.
    pub fn new(timeout_s: f64) -> Self {
        Self { timeout_s, marks: BTreeMap::new(), starting: Default::default() }
    }

    /// `role`'s progress mark is `mark` at `now_s`, and `pending` says whether work waits
    /// for it. Returns whether it is hung.
    pub fn check(&mut self, role: &str, mark: Option<u64>, pending: bool, now_s: f64) -> bool {
        let entry = self.marks.entry(role.to_owned()).or_insert((mark, now_s));
        if entry.0 != mark {
            self.starting.remove(role);
        }
        if entry.0 != mark || !pending {
            *entry = (mark, now_s);
        }
        let timeout = match self.starting.contains(role) {
            true => self.timeout_s.max(START_TIMEOUT_S),
            false => self.timeout_s,
        };
        self.timeout_s > 0.0 && pending && now_s - entry.1 > timeout
    }

    /// `role` was stopped (SIGSTOP) by the fault schedule: a stopped process makes no
    /// progress, however slowly it was starting, so it is judged by the running timeout
    /// from now on (a restarted controller stopped before its first progress was otherwise
    /// given the 10 s start timeout, past the end of the run).
    pub fn stopped(&mut self, role: &str) {
        self.starting.remove(role);
    }

    /// `role` was (re)started at `now_s`: its clock starts again, with the start timeout
    /// until it makes progress.
    pub fn reset(&mut self, role: &str, now_s: f64) {
        if let Some(e) = self.marks.get_mut(role) {
            e.1 = now_s;
        }
        self.starting.insert(role.to_owned());
    }
}

/// The rule for a loop carried over a link: after a role on the far host or a gateway is
/// started again, the plant must receive a torque again within the start timeout (the
/// [`Watchdog`]'s, [`START_TIMEOUT_S`] or `--watchdog-ms` if longer). A far-host controller
/// can be alive and answering every state it gets while none of its torques reach the
/// plant (a gateway that does not carry them): no watchdog of a role sees that, so this
/// rule does, and the run then ends as it does for any role that does not come back,
/// with its report and exit code 1, instead of running on without its loop.
#[derive(Debug, Clone, Default)]
pub struct LinkWatch {
    /// The restart being waited on: its role, its deadline (s), the plant's torque count
    /// at the restart.
    due: Option<(String, f64, u64)>,
    timeout_s: f64,
}

impl LinkWatch {
    /// Waits at most `timeout_s` for the loop after each restart.
    pub fn new(timeout_s: f64) -> Self {
        Self { due: None, timeout_s }
    }

    /// `role` was started again at `now_s`, when the plant had received `torques`. The
    /// first restart's deadline stands: restarting the same role again (a watchdog that
    /// blamed it for the link) does not put it off.
    pub fn restarted(&mut self, role: &str, now_s: f64, torques: u64) {
        self.due.get_or_insert_with(|| (role.to_owned(), now_s + self.timeout_s, torques));
    }

    /// The plant has received `torques` by `now_s`: `Some(the restarted role, why)` when
    /// the deadline has passed with no new torque (once; the rule is then disarmed).
    pub fn check(&mut self, torques: u64, now_s: f64) -> Option<(String, String)> {
        let (role, deadline, at_restart) = self.due.as_ref()?;
        if torques > *at_restart {
            self.due = None;
            return None;
        }
        if now_s <= *deadline {
            return None;
        }
        let t = self.timeout_s;
        let why = format!(
            "the link did not carry the loop again within {t:.1} s of restarting {role}: \
             the plant received no torque since"
        );
        let role = role.clone();
        self.due = None;
        Some((role, why))
    }
}

/// Each role's progress mark, from the resume slots: the plant's newest tick, the
/// controller's newest answer, the reference's next tick, the monitor's next row.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Marks {
    /// The plant's newest published tick.
    pub plant: Option<u64>,
    /// The tick of the controller's newest answer.
    pub controller: Option<u64>,
    /// The next tick the reference will publish.
    pub reference_next: Option<u64>,
    /// The next row the monitor will take.
    pub monitor_next: Option<u64>,
}

impl Marks {
    /// The mark of `role`.
    pub fn of(&self, role: Role) -> Option<u64> {
        match role {
            Role::Plant => self.plant,
            Role::Controller => self.controller,
            Role::Reference => self.reference_next,
            Role::Monitor => self.monitor_next,
        }
    }

    /// Whether work waits for `role`, that nothing but the role itself holds up: so the
    /// watchdog blames the role that hangs, not those waiting for it. Nothing waits before
    /// tick 0. The plant: always in real time (it ticks on its own); in lockstep once the
    /// controller has answered its newest state. The controller: a state newer than its
    /// last answer (in lockstep, only once that state's reference is there). The reference:
    /// the plant has reached the tick it has yet to publish. The monitor: rows of which
    /// every sample is out (two ticks behind the slowest of the others).
    pub fn work_waiting(&self, role: Role, lockstep: bool, lead: u64) -> bool {
        let Some(p) = self.plant else { return false };
        let answered = |c: Option<u64>| c.is_some_and(|c| c >= p);
        match role {
            Role::Plant => !lockstep || answered(self.controller),
            Role::Controller => {
                !answered(self.controller)
                    && (!lockstep || self.reference_next.is_some_and(|n| n > p))
            }
            Role::Reference => self.reference_next.is_none_or(|n| n <= p.min(p + lead)),
            Role::Monitor => {
                let out = p
                    .min(self.controller.unwrap_or(0))
                    .min(self.reference_next.unwrap_or(0).saturating_sub(1));
                self.monitor_next.unwrap_or(0) + 2 <= out
            }
        }
    }

    /// [`Marks::work_waiting`], given the roles stopped now (SIGSTOP or any stop, whoever
    /// sent it). A stopped role of the loop holds it up whatever its mark says, and the
    /// other roles wait for it. The marks alone cannot say so: a controller writes its
    /// resume slot just before it sends (its restart must resume with the law state of
    /// its last answer), so one stopped between the two looks as if it had answered; in
    /// lockstep the plant, waiting for that answer, was blamed instead, killed and
    /// restarted every 10 s while the run never ended (once in 20 rounds of the repeat
    /// harness under load). A stopped monitor holds up nothing but itself.
    pub fn work_waiting_with_stops(
        &self,
        role: Role,
        lockstep: bool,
        lead: u64,
        stopped: &[Role],
    ) -> bool {
        let holds_up_the_loop = |r: &Role| *r != Role::Monitor;
        if stopped.contains(&role) {
            holds_up_the_loop(&role) || self.work_waiting(role, lockstep, lead)
        } else if stopped.iter().any(holds_up_the_loop) {
            false
        } else {
            self.work_waiting(role, lockstep, lead)
        }
    }
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
    use rotorloop_common::wire::WireFault;

    #[test]
    fn a_restarted_role_has_the_start_timeout_until_its_first_progress() {
        let mut w = Watchdog::new(0.5);
        assert!(!w.check("controller", Some(10), true, 0.0));
        assert!(w.check("controller", Some(10), true, 0.6), "running: the watchdog's 0.5 s");
        w.reset("controller", 1.0);
        assert!(!w.check("controller", Some(10), true, 2.0), "starting: not yet");
        assert!(w.check("controller", Some(10), true, 1.0 + START_TIMEOUT_S + 0.1));
        w.reset("controller", 20.0);
        assert!(!w.check("controller", Some(11), true, 20.1), "first progress");
        assert!(w.check("controller", Some(11), true, 20.7), "running again: 0.5 s");
        // Restarted, then stopped by the schedule before its first progress: the running
        // timeout, from its restart.
        w.reset("controller", 30.0);
        assert!(!w.check("controller", Some(11), true, 30.2));
        w.stopped("controller");
        assert!(!w.check("controller", Some(11), true, 30.4));
        assert!(w.check("controller", Some(11), true, 30.6), "stopped: 0.5 s, not 10 s");
    }

    fn exited(code: i32) -> ExitStatus {
        ExitStatus::from_raw(code << 8)
    }

    fn supervisor(spec: &str, limit: &str) -> Supervisor {
        Supervisor::new(parse_restart(spec).expect("valid"), limit.parse().expect("valid"))
    }

    fn end(s: &mut Supervisor, role: &str, status: ExitStatus, now_s: f64) -> Verdict {
        s.on_end(
            role,
            Ending::of(status),
            &format!("exited with {status}"),
            status.code(),
            now_s,
            false,
        )
    }

    #[test]
    fn a_killed_or_crashed_role_is_restarted_at_once_then_with_growing_backoff() {
        let mut s = supervisor("on-failure", "5/10");
        let killed = ExitStatus::from_raw(libc::SIGKILL);
        assert_eq!(Ending::of(killed), Ending::Killed);
        assert_eq!(Ending::of(exited(1)), Ending::Crash);
        assert_eq!(Ending::of(ExitStatus::from_raw(libc::SIGSEGV)), Ending::Crash);
        assert_eq!(end(&mut s, "controller", killed, 1.0), Verdict::Restart { at_s: 1.0 });
        assert_eq!(end(&mut s, "controller", exited(1), 2.0), Verdict::Restart { at_s: 2.1 });
        assert_eq!(end(&mut s, "controller", killed, 3.0), Verdict::Restart { at_s: 3.2 });
        assert_eq!(end(&mut s, "controller", killed, 4.0), Verdict::Restart { at_s: 4.4 });
        assert_eq!(
            end(&mut s, "reference", killed, 4.0),
            Verdict::Restart { at_s: 4.0 },
            "per role"
        );
    }

    #[test]
    fn too_many_restarts_in_the_window_stop_the_run_naming_the_role_and_its_exit() {
        let mut s = supervisor("on-failure", "2/10");
        let killed = ExitStatus::from_raw(libc::SIGKILL);
        assert!(matches!(end(&mut s, "monitor", killed, 0.0), Verdict::Restart { .. }));
        assert!(matches!(end(&mut s, "monitor", killed, 1.0), Verdict::Restart { .. }));
        let Verdict::Fail(m) = end(&mut s, "monitor", exited(1), 2.0) else {
            panic!("not stopped")
        };
        assert!(m.contains("monitor") && m.contains("exit status: 1") && m.contains("2/10"), "{m}");
        // Outside the window of running with progress the count starts afresh.
        s.progressed("monitor", 3.0);
        s.progressed("monitor", 29.0);
        assert!(matches!(end(&mut s, "monitor", killed, 30.0), Verdict::Restart { .. }));
    }

    #[test]
    fn restarts_with_no_progress_between_them_never_leave_the_window() {
        // A controller that never answers is judged hung only after the start timeout,
        // 10 s after each restart: by the wall clock never 2 within 10 s.
        let mut s = supervisor("on-failure", "2/10");
        let hung =
            |s: &mut Supervisor, t| s.on_end("controller", Ending::Hang, "hung", None, t, false);
        assert!(matches!(hung(&mut s, 3.0), Verdict::Restart { .. }));
        assert!(matches!(hung(&mut s, 13.1), Verdict::Restart { .. }));
        assert!(matches!(hung(&mut s, 23.3), Verdict::Fail(m) if m.contains("2/10")));
        // One that answers once after each restart, and then too late again: no time run
        // with progress either (its first progress is its last).
        let mut late = supervisor("on-failure", "1/10");
        assert!(matches!(hung(&mut late, 0.5), Verdict::Restart { .. }));
        late.progressed("controller", 1.5);
        assert!(matches!(hung(&mut late, 2.1), Verdict::Fail(_)));
    }

    #[test]
    fn the_policy_decides_clean_exits_and_never() {
        let mut s = supervisor("never,monitor=always", "5/10");
        assert!(
            matches!(end(&mut s, "controller", ExitStatus::from_raw(libc::SIGKILL), 1.0), Verdict::Fail(m) if m.contains("never"))
        );
        let over = s.on_end("controller", Ending::Exited, "exited", Some(0), 9.0, true);
        assert_eq!(over, Verdict::Done, "a clean exit after the last tick is the end");
        // Before it, a clean exit left work undone: only `always` restarts it.
        let early = end(&mut s, "controller", exited(0), 1.0);
        assert!(matches!(early, Verdict::Fail(m) if m.contains("before the run's last tick")));
        let mut on_failure = supervisor("on-failure", "5/10");
        assert!(matches!(end(&mut on_failure, "plant", exited(0), 1.0), Verdict::Fail(_)));
        assert!(matches!(end(&mut s, "monitor", exited(0), 1.0), Verdict::Restart { .. }));
        let over = s.on_end("monitor", Ending::Exited, "exited", Some(0), 9.0, true);
        assert_eq!(over, Verdict::Done, "always does not restart a role the run is over for");
    }

    #[test]
    fn exit_code_2_is_never_restarted() {
        let mut s = supervisor("always", "5/10");
        assert!(
            matches!(end(&mut s, "plant", exited(2), 1.0), Verdict::Fail(m) if m.contains("diverged"))
        );
    }

    #[test]
    fn bad_restart_specs_are_refused_naming_what_is_allowed() {
        assert_eq!(parse_restart("monitor=always").expect("ok")["plant"], RestartPolicy::OnFailure);
        for (spec, why) in
            [("sometimes", "on-failure, always or never"), ("pilot=never", "not a role")]
        {
            let e = parse_restart(spec).expect_err(spec).to_string();
            assert!(e.contains(why) && e.contains(spec), "{e}");
        }
        for bad in ["0/10", "5/0", "5", "x/y"] {
            assert!(bad.parse::<RestartLimit>().is_err(), "{bad}");
        }
    }

    #[test]
    fn a_role_is_hung_only_when_work_waits_and_its_mark_stands_still() {
        let mut w = Watchdog::new(1.0);
        assert!(!w.check("controller", Some(5), true, 0.0));
        assert!(!w.check("controller", Some(5), true, 0.9));
        assert!(w.check("controller", Some(5), true, 1.1), "no progress for over 1 s");
        assert!(!w.check("controller", Some(6), true, 1.2), "progress resets the clock");
        assert!(!w.check("controller", Some(6), false, 5.0), "nothing waiting: not hung");
        assert!(!w.check("controller", Some(6), true, 5.5));
        w.reset("controller", 6.0);
        assert!(!w.check("controller", Some(6), true, 6.9));
        // Restarted and no progress yet: the start timeout, not the watchdog's.
        assert!(!w.check("controller", Some(6), true, 7.1));
        assert!(w.check("controller", Some(6), true, 6.0 + START_TIMEOUT_S + 0.1));
        let mut off = Watchdog::new(0.0);
        assert!(!off.check("plant", Some(1), true, 0.0) && !off.check("plant", Some(1), true, 1e9));
    }

    #[test]
    fn the_watchdog_blames_the_role_that_holds_the_loop_up_not_those_waiting_for_it() {
        let m = |plant, controller, reference_next, monitor_next| Marks {
            plant,
            controller,
            reference_next,
            monitor_next,
        };
        // Before tick 0 nothing waits.
        assert!(
            Role::ALL.iter().all(|r| !m(None, None, Some(17), None).work_waiting(*r, true, 16))
        );
        // Lockstep, the controller hangs at tick 10: it is to blame; the plant waits.
        let hung_controller = m(Some(10), Some(9), Some(27), Some(8));
        assert!(hung_controller.work_waiting(Role::Controller, true, 16));
        assert!(!hung_controller.work_waiting(Role::Plant, true, 16));
        assert!(!hung_controller.work_waiting(Role::Reference, true, 16));
        assert!(!hung_controller.work_waiting(Role::Monitor, true, 16));
        // Lockstep, the reference hangs before tick 10: it is to blame, not the controller.
        let hung_reference = m(Some(10), Some(9), Some(10), Some(8));
        assert!(hung_reference.work_waiting(Role::Reference, true, 16));
        assert!(!hung_reference.work_waiting(Role::Controller, true, 16));
        // Lockstep, the controller answered 10 and the plant has not moved on: the plant.
        assert!(m(Some(10), Some(10), Some(27), Some(8)).work_waiting(Role::Plant, true, 16));
        // Real time: the plant always has work; the monitor has rows waiting.
        let monitor_behind = m(Some(100), Some(100), Some(117), Some(50));
        assert!(monitor_behind.work_waiting(Role::Plant, false, 16));
        assert!(monitor_behind.work_waiting(Role::Monitor, false, 16));
        assert!(!m(Some(100), Some(100), Some(117), Some(99)).work_waiting(
            Role::Monitor,
            false,
            16
        ));
    }

    #[test]
    fn a_stopped_role_of_the_loop_is_to_blame_whatever_its_mark_says() {
        // Lockstep: the controller's slot says it answered 10 (it stopped between its slot
        // and its send), the plant waits for torque 10.
        let m = Marks {
            plant: Some(10),
            controller: Some(10),
            reference_next: Some(27),
            monitor_next: Some(8),
        };
        assert!(m.work_waiting(Role::Plant, true, 16), "by the marks alone: the plant");
        let stopped = [Role::Controller];
        assert!(m.work_waiting_with_stops(Role::Controller, true, 16, &stopped));
        for r in [Role::Plant, Role::Reference, Role::Monitor] {
            assert!(!m.work_waiting_with_stops(r, true, 16, &stopped), "{r:?} waits for it");
        }
        // Nothing stopped: the marks decide.
        assert!(m.work_waiting_with_stops(Role::Plant, true, 16, &[]));
        // A stopped monitor holds up only itself, and only with rows waiting.
        let behind = Marks { monitor_next: Some(2), ..m };
        assert!(behind.work_waiting_with_stops(Role::Plant, true, 16, &[Role::Monitor]));
        assert!(behind.work_waiting_with_stops(Role::Monitor, true, 16, &[Role::Monitor]));
        let caught_up = Marks { monitor_next: Some(9), ..m };
        assert!(!caught_up.work_waiting_with_stops(Role::Monitor, true, 16, &[Role::Monitor]));
    }

    #[test]
    fn a_controller_whose_every_answer_is_refused_is_at_fault_after_hold_ticks() {
        let none = rotorloop_common::wire::NO_TICK;
        let n = |total| Refusals { total, ..Refusals::default() };
        let mut r = RejectWatch::new(50);
        assert_eq!(r.check(0, none, n(0)), None);
        assert_eq!(r.check(30, none, n(30)), None, "30 refused: not yet");
        let s = r.check(50, none, n(50)).expect("50 in a row");
        assert_eq!((s.from_tick, s.to_tick, s.rejected), (0, 50, 50));
        // One accepted answer ends the streak: a controller refused every other tick is
        // counted (torques_rejected), never at fault.
        let mut every_other = RejectWatch::new(50);
        for k in 0..400u64 {
            assert_eq!(every_other.check(k, k - k % 2, n(k / 2)), None, "tick {k}");
        }
        // A restart starts a new streak, from the counts at the last look.
        r.reset();
        assert_eq!(r.check(60, none, n(55)), None);
        assert!(r.streak(61, none, n(56)).is_some_and(|s| s.rejected == 6));
        // A first look after the rejections (lockstep: one answer for a tick not reached).
        let mut late = RejectWatch::new(50);
        assert!(late.streak(0, none, n(1)).is_some_and(|s| s.rejected == 1));
        // The streak's kinds are those since it began, not the run's.
        let mut kinds = RejectWatch::new(2);
        let nan = WireFault::NonFinite { field: "torque.rotor_torque" };
        let future = WireFault::FutureTick { field: "torque.tick", tick: 99, allowed: 10 };
        let mut plant = Refusals::default();
        plant.count(1, &nan);
        assert_eq!(kinds.check(2, 1, plant), None, "after the torque of tick 1 accepted");
        plant.count(3, &future);
        plant.count(4, &future);
        let s = kinds.check(5, 1, plant).expect("two in a row");
        assert_eq!((s.kinds.total, s.kinds.non_finite, s.kinds.future_tick), (2, 0, 2));
    }

    #[test]
    fn a_restart_whose_loop_does_not_come_back_within_the_start_timeout_ends_the_run() {
        let mut l = LinkWatch::new(10.0);
        assert_eq!(l.check(5, 100.0), None, "nothing restarted, nothing due");
        l.restarted("controller", 1.5, 700);
        assert_eq!(l.check(700, 11.5), None, "not before the deadline");
        l.restarted("controller", 11.0, 700); // the watchdog's restart does not put it off
        let (role, why) = l.check(700, 11.6).expect("due");
        assert_eq!(role, "controller");
        assert!(why.contains("within 10.0 s of restarting controller"), "{why}");
        assert_eq!(l.check(700, 30.0), None, "once");
    }

    #[test]
    fn a_restart_whose_loop_comes_back_disarms_the_rule() {
        let mut l = LinkWatch::new(10.0);
        l.restarted("link-b", 2.0, 1000);
        assert_eq!(l.check(1001, 3.0), None);
        assert_eq!(l.check(1001, 60.0), None, "the loop came back: nothing is due");
        l.restarted("link-b", 61.0, 1001);
        assert!(l.check(1001, 71.1).is_some(), "a later restart is watched again");
    }
}
