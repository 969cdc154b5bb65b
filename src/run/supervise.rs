//! The supervision loop while the roles run (`supervise`): the `--fault` schedule
//! applied by its table, the restart policy, the watchdog on the resume slots' marks,
//! every stop and continue of a child, the link rule of a split run, the flight records
//! moved out as the run goes, and the clean end.

use std::collections::BTreeMap;
use std::os::unix::process::ExitStatusExt;
use std::process::Child;
use std::time::Duration;

use anyhow::Context;
use rotorloop_common::clock::now_ns;
use rotorloop_common::role::end::LINGER_S;
use rotorloop_common::signals::shutdown_requested;
use rotorloop_common::wire::REFERENCE_LEAD;

use rotorloop_common::graph::Role;

use crate::observe::slots::Slots;
use crate::run::fault::{Action, Apply, FaultEvent, FaultKind, FaultSchedule};
use crate::run::mover::MoverThread;
use crate::run::policy::{
    Children, Ending, LinkWatch, Marks, RejectWatch, START_TIMEOUT_S, Streak, Supervisor, Verdict,
    Watchdog, signal,
};
use crate::run::resources::RssLog;
use crate::run::spawn::Launch;
use rotorloop_common::role::args::Mode;
use rotorloop_common::wire::{NO_TICK, Refusals, StateSample};

/// Where each role stands, from the resume slots (what the watchdog reads), and whether
/// the controller is the user's (`--controller-cmd`: it keeps no slot of rotorloop's).
struct Progress(Slots, bool);

impl Progress {
    /// Each role's slot on its own host.
    fn open(launch: &Launch) -> anyhow::Result<Self> {
        let slots = Slots::open(|role| launch.domain_of(role.name()), true);
        Ok(Self(slots.context("the resume slots")?, launch.external.is_some()))
    }

    fn marks(&self) -> Marks {
        // A user's controller: its newest torque the plant has taken.
        let external = || self.0.plant().map(|s| s.applied_torque_tick).filter(|k| *k != NO_TICK);
        Marks {
            plant: self.0.plant().map(|s| s.tick),
            controller: if self.1 { external() } else { self.0.controller_tick() },
            reference_next: self.0.reference_next(),
            monitor_next: self.0.monitor_next(),
        }
    }

    /// What the watchdog reads as `role`'s sign of life: its mark, but for a user's
    /// controller any answer the plant took, accepted or not (one whose every torque is
    /// refused answers all the same: it is not hung, [`RejectWatch`] judges it). In
    /// lockstep that is the plant's tick (the plant moves on once its tick is answered,
    /// even by a torque it refused); in real time, the torques it received or rejected.
    fn alive(&self, role: Role, marks: &Marks, lockstep: bool) -> Option<u64> {
        match (role, self.1, self.0.plant()) {
            (Role::Controller, true, Some(s)) if lockstep => Some(s.tick),
            (Role::Controller, true, Some(s)) => Some(s.torques_received + s.torques_rejected),
            _ => marks.of(role),
        }
    }
}

/// What the supervision loop keeps between polls.
struct Watch {
    events: Vec<FaultEvent>,
    failures: Vec<String>,
    /// Roles waiting to be started again, and when (s after tick 0).
    restarts: BTreeMap<String, f64>,
    /// Pids whose end has been dealt with.
    handled: std::collections::BTreeSet<u32>,
    /// Pids killed by the schedule or the watchdog (their SIGKILL is not a new fault).
    planned: std::collections::BTreeSet<u32>,
    /// The pid stopped by each `stop` fault.
    stopped: BTreeMap<String, u32>,
    /// The stops not yet ended, whoever sent them: pid → index of its event.
    open_stops: BTreeMap<u32, usize>,
    /// The restart policy's state.
    supervisor: Supervisor,
    /// The hang watchdog's state.
    watchdog: Watchdog,
    /// Whether the controller's answers are all refused.
    rejects: RejectWatch,
    /// The marks at the last poll (a mark that moved is progress, for the restart limit).
    last_marks: Marks,
    /// Split: whether the link carries the loop again after a restart.
    link: LinkWatch,
    /// Torque samples the plant has received so far.
    torques_received: u64,
    /// Copies the finished halves of the flight records' rings into `OUT/flight` (a run
    /// longer than the rings).
    mover: Option<MoverThread>,
    /// The plant has published its last tick.
    loop_complete: bool,
    /// What the run needs on `/dev/shm` (bytes), named where a role died of it full.
    shm_need: u64,
    /// Lockstep: the plant (this pid) stands stopped at its gate after publishing this
    /// tick (`--gate-ticks`), for the faults due there.
    gated: Option<(u32, u64)>,
    /// Lockstep: the newest gate the plant stopped at, the run's clock for the schedule.
    gate_clock: Option<u64>,
    /// The plant pid this launcher continued from its gate (its SIGCONT is no fault).
    gate_released: Option<u32>,
}

impl Watch {
    fn new(launch: &Launch) -> Self {
        let watchdog_s = launch.args.watchdog_ms as f64 / 1e3;
        Self {
            events: Vec::new(),
            failures: Vec::new(),
            restarts: BTreeMap::new(),
            handled: Default::default(),
            planned: Default::default(),
            stopped: BTreeMap::new(),
            open_stops: BTreeMap::new(),
            supervisor: launch.supervisor.clone(),
            watchdog: Watchdog::new(watchdog_s),
            rejects: RejectWatch::new(launch.args.hold_ticks),
            last_marks: Marks::default(),
            link: LinkWatch::new(START_TIMEOUT_S.max(watchdog_s)),
            torques_received: 0,
            mover: launch.mover().and_then(|m| {
                let stall = launch.role_args.hooks.test_mover_stall_ms;
                let realtime = launch.role_args.mode == Mode::Realtime;
                MoverThread::spawn(m, stall.map(std::time::Duration::from_millis), realtime)
                    .map_err(|e| eprintln!("warning: flight records: no mover thread ({e})"))
                    .ok()
            }),
            loop_complete: false,
            shm_need: launch.shm_need,
            gated: None,
            gate_clock: None,
            gate_released: None,
        }
    }

    /// After the supervision loop: the last records moved, the stops still open ended.
    /// Returns the longest the newest ticks were from the disk (`Mover::durable_lag_max`).
    fn finish(&mut self, progress: &Progress) -> Option<std::time::Duration> {
        // What became due in the last pass, then the thread's end.
        let tick = progress.0.plant().map(|p| p.tick);
        let mover = self.mover.take().and_then(|m| m.finish(tick));
        let lag = mover.as_ref().and_then(|m| m.durable_lag_max);
        if let Some(l) = lag.filter(|l| *l > rotorloop_common::flight::DURABLE_BOUND) {
            // Not `eprintln!`: a terminal gone (SIGHUP) must not make this a panic.
            use std::io::Write;
            let _ = writeln!(
                std::io::stderr(),
                "warning: flight records: the newest ticks were up to {:.2} s from the disk \
                 (a machine crash then would have lost that much; the bound is {} s): the \
                 disk's syncs or the launcher's thread were slow",
                l.as_secs_f64(),
                rotorloop_common::flight::DURABLE_BOUND.as_secs_f64()
            );
        }
        if let Some(m) = mover.filter(|m| m.lost > 0) {
            eprintln!(
                "warning: flight records: {} record(s) lost from the rings: they came round \
                 before the launcher moved them (it was not running for that long); the \
                 journal kept those it had made durable (*.kept.journal beside their segment); \
                 a longer --flight-ring-ticks keeps them all",
                m.lost
            );
        }
        for pid in self.open_stops.keys().copied().collect::<Vec<_>>() {
            end_stop(self, pid, "still stopped when the launcher ended");
        }
        lag
    }
}

/// How the supervision loop ended.
pub(crate) struct Supervised {
    /// The faults, as they happened.
    pub events: Vec<FaultEvent>,
    /// The failure that stopped the run, if one did.
    pub failure: Option<anyhow::Error>,
    /// The longest the newest ticks of the record were from the disk (`None`: no journal).
    pub durable_lag_max: Option<std::time::Duration>,
}

/// Runs the fault schedule, the restart policy and the watchdog, samples memory, and
/// waits for every child; on a signal or a failure, forwards SIGTERM, then SIGKILL after
/// 10 s. Returns the faults as they happened, the failure that stopped the run, if one
/// did, and how far the record's newest ticks were from the disk.
pub(crate) fn supervise(
    launch: &Launch,
    children: &mut Children,
    rss: &mut RssLog,
    mut schedule: FaultSchedule,
) -> anyhow::Result<Supervised> {
    // The fault schedule runs on the plant's ticks: in real time its newest published
    // tick (its resume slot is written just before each publish), in lockstep the gate it
    // stands stopped at (`FaultSchedule::gate_ticks`). The launcher's own clock (`now_s`,
    // from the first tick) times the supervisor, the watchdog and a fault's down time.
    let progress = Progress::open(launch)?;
    let lockstep = launch.role_args.mode == Mode::Lockstep;
    let (mut run_t0, mut term_sent_at): (Option<u64>, Option<u64>) = (None, None);
    let mut plant_ended_at: Option<u64> = None;
    let mut w = Watch::new(launch);
    let launched_ns = now_ns();
    let mut dead_after_end = 0;
    loop {
        let plant_tick = progress.0.plant().map(|s| s.tick);
        if run_t0.is_none() && plant_tick.is_some() {
            run_t0 = Some(now_ns());
        }
        // Seconds since tick 0 (before it: negative, since the launch).
        let now_s = (now_ns() as f64 - run_t0.unwrap_or(launched_ns) as f64) / 1e9;
        w.loop_complete = progress.0.loop_complete();
        if w.loop_complete {
            continue_stopped_after_the_end(children, &mut w, now_s);
        }
        let stopping = term_sent_at.is_some();
        // In lockstep a slot at tick k also says k − 1 was published and passed: a gate the
        // plant went by without stopping (a plant killed between its slot and its stop
        // resumes past it) still has its faults carried out, late, never dropped.
        let passed = plant_tick.and_then(|k| k.checked_sub(1));
        let clock = match lockstep {
            true => w.gate_clock.max(passed),
            false => published_tick(&progress),
        };
        let clock = clock.filter(|_| !stopping);
        for action in schedule.due(clock, now_ns()) {
            injected(launch, children, rss, &mut w, action, (now_s, clock))?;
        }
        if !stopping && run_t0.is_some() && !w.loop_complete {
            w.torques_received = progress.0.plant().map_or(0, |s| s.torques_received);
            watch_the_link(&mut w, now_s);
        }
        if !stopping && run_t0.is_some() && !w.loop_complete && w.failures.is_empty() {
            watch_for_hangs(launch, children, &mut w, &progress, now_s);
            watch_for_rejections(children, &mut w, &progress, now_s);
        }
        let due: Vec<String> = w
            .restarts
            .iter()
            .filter(|(_, at)| **at <= now_s && !stopping)
            .map(|(r, _)| r.clone())
            .collect();
        for role in due {
            w.restarts.remove(&role);
            restart(launch, children, rss, &mut w, &role, now_s)?;
        }
        release_the_gate(children, &mut w, &schedule);
        rss.sample_if_due();
        move_due_records(&mut w, &progress);
        watch_for_stops(launch, children, &mut w, &progress, now_s);
        let running = reap(children, &mut w, &progress, stopping, now_s);
        remove_dead_ports_after_the_end(launch, &w, &mut dead_after_end);
        if launch.split.is_some() && w.loop_complete && !stopping {
            term_sent_at = stop_far_roles_after_the_end(children, &mut plant_ended_at);
        } else if launch.external.is_some() && w.loop_complete && !stopping {
            stop_a_lingering_controller(children, &mut w, &mut plant_ended_at);
        }
        // Restarts still to come keep the launcher waiting, but only until the last tick:
        // after it nobody is started again (see `restart`).
        let awaiting = (schedule.awaiting_restart() || !w.restarts.is_empty()) && !w.loop_complete;
        if running == 0 && (!awaiting || stopping) {
            break;
        }
        if (shutdown_requested() || !w.failures.is_empty()) && !stopping {
            term_sent_at = Some(now_ns());
            children.signal_all(libc::SIGCONT); // a stopped child must see the SIGTERM
            children.signal_all(libc::SIGTERM);
        }
        if term_sent_at.is_some_and(|t| now_ns() - t > 10_000_000_000) {
            children.signal_all(libc::SIGKILL);
        }
        std::thread::sleep(poll_interval(launch, &schedule, plant_tick));
    }
    for f in schedule.not_done() {
        eprintln!("launcher: --fault {f}: not carried out, the run was stopped first");
    }
    let durable_lag_max = w.finish(&progress);
    let failure = (!w.failures.is_empty())
        .then(|| anyhow::anyhow!("the run was stopped: {}", w.failures.join("; ")));
    Ok(Supervised { events: w.events, failure, durable_lag_max })
}

/// Real time: the plant's newest tick surely published. Its resume slot is written just
/// before the publish, so the slot's own tick may still be on its way (a plant preempted
/// between the two on a loaded machine: seen, a kill "at" tick 950 landed before its
/// publication); the tick before it has been published for certain. So a fault lands
/// within one tick (and a poll) of its tick's publication, never before it.
fn published_tick(progress: &Progress) -> Option<u64> {
    progress.0.plant()?.tick.checked_sub(1)
}

/// How long the supervision loop sleeps: 2 ms, but in real time, as the plant nears the
/// next tick a fault is due at, no longer than until the tick after it begins, and then
/// 100 µs, so that the fault lands within about a tick of that tick's publication.
fn poll_interval(launch: &Launch, schedule: &FaultSchedule, tick: Option<u64>) -> Duration {
    const POLL: Duration = Duration::from_millis(2);
    let (Some(due), Some(tick)) = (schedule.next_tick(), tick) else { return POLL };
    if launch.role_args.mode == Mode::Lockstep {
        return POLL;
    }
    let dt_s = 1.0 / launch.rate_hz;
    // Due once the slot says `due + 1` (`published_tick`): sleep until about then.
    let ahead_s = due.saturating_sub(tick) as f64 * dt_s;
    Duration::from_secs_f64(ahead_s).clamp(Duration::from_micros(100), POLL)
}

/// Lockstep: continues the plant from its gate once the faults due there are carried out
/// and none that stops the run's clock is still open (the plant stays at the tick of such
/// a fault's start until its end: a restart lands at the same tick every time), and no
/// role the plant waits for is still to be started again. A plant killed at its gate (its
/// pid gone) or stopped there by a `stop` fault is not continued here.
fn release_the_gate(children: &mut Children, w: &mut Watch, schedule: &FaultSchedule) {
    let Some((pid, _)) = w.gated else { return };
    let plant = Role::Plant.name();
    let Some(c) = children.get_mut(plant).filter(|c| c.id() == pid && !w.planned.contains(&pid))
    else {
        w.gated = None;
        return;
    };
    let waited_on = w.restarts.keys().any(|r| r != Role::Monitor.name());
    if schedule.holding() || waited_on || w.stopped.contains_key(plant) {
        return;
    }
    w.gate_released = Some(pid);
    w.gated = None;
    signal(c, libc::SIGCONT);
}

/// Split: a role on another host than the plant cannot read the plant's resume slot (it
/// learns the end from the last state). If that state was lost with a gateway, it would
/// wait for ever: once the plant has ended, the rest get their linger time, then SIGTERM
/// (a clean end, not a fault). Returns when the SIGTERM was sent, if it was.
fn stop_far_roles_after_the_end(children: &mut Children, since: &mut Option<u64>) -> Option<u64> {
    let plant_gone =
        children.get_mut(Role::Plant.name()).is_none_or(|c| !matches!(c.try_wait(), Ok(None)));
    let since = *since.get_or_insert_with(now_ns);
    if !plant_gone || now_ns() - since <= (LINGER_S + 5) * 1_000_000_000 {
        return None;
    }
    eprintln!("launcher: the plant ended {} s ago; stopping the roles still waiting", LINGER_S + 5);
    children.signal_all(libc::SIGTERM);
    Some(now_ns())
}

/// A user's controller that does not stop after the plant's last tick (it missed the last
/// state, or never looks at its flag) would keep the launcher waiting for ever: once the
/// plant has ended, it gets the linger time of a role, then SIGTERM, and 10 s later
/// SIGKILL. Neither is a fault: the run was over.
fn stop_a_lingering_controller(children: &mut Children, w: &mut Watch, since: &mut Option<u64>) {
    let plant_gone =
        children.get_mut(Role::Plant.name()).is_none_or(|c| !matches!(c.try_wait(), Ok(None)));
    if !plant_gone {
        return;
    }
    let since = *since.get_or_insert_with(now_ns);
    let Some(c) = children.get_mut(Role::Controller.name()) else { return };
    let (pid, waited_s) = (c.id(), (now_ns() - since) / 1_000_000_000);
    if !matches!(c.try_wait(), Ok(None)) || waited_s < LINGER_S + 5 {
        return;
    }
    let sig = if waited_s < LINGER_S + 15 { libc::SIGTERM } else { libc::SIGKILL };
    if w.planned.insert(pid) || (sig == libc::SIGKILL && !dying(pid)) {
        let name = signal_name(sig);
        eprintln!(
            "launcher: the controller is still running {waited_s} s after the plant ended; {name}"
        );
        signal(c, sig);
    }
}

/// After the last tick the schedule is moot: a role it stopped and has not continued
/// would never see the end, and the launcher would wait for it for ever (seen: a
/// controller killed by hand at 4.9 s, restarted, stopped at 5 s before its first
/// progress, so under the start timeout, and the 8 s loop ended before the watchdog
/// judged it). It is continued, sees the end and exits as the others do.
fn continue_stopped_after_the_end(children: &mut Children, w: &mut Watch, now_s: f64) {
    for (role, pid) in std::mem::take(&mut w.stopped) {
        let Some(c) = children.get_mut(&role).filter(|c| c.id() == pid) else { continue };
        if w.planned.contains(&pid) || !matches!(c.try_wait(), Ok(None)) {
            continue;
        }
        continue_stopped(c, stop_event(&mut w.events, &role), "; SIGCONT at the end of the loop");
        eprintln!("launcher: continued {role} (SIGCONT) at {now_s:.3} s: the loop has ended");
    }
}

/// Continues (SIGCONT) a role the schedule stopped, and marks its `stop` fault continued
/// now, `how` added to its detail.
fn continue_stopped(c: &mut Child, stop: Option<&mut FaultEvent>, how: &str) {
    signal(c, libc::SIGCONT);
    if let Some(e) = stop {
        e.restart_ns = Some(now_ns());
        e.detail.push_str(how);
    }
}

/// The newest `stop` fault of `role`.
fn stop_event<'a>(events: &'a mut [FaultEvent], role: &str) -> Option<&'a mut FaultEvent> {
    events.iter_mut().rev().find(|e| e.role == role && e.kind == "stop")
}

/// Tells the mover thread the plant's newest tick: the halves of the flight records'
/// rings it finished are copied into `OUT/flight` off this loop.
fn move_due_records(w: &mut Watch, progress: &Progress) {
    if let (Some(m), Some(p)) = (&w.mover, progress.0.plant()) {
        m.saw(p.tick);
    }
}

/// Split: a restart after which the link does not carry the loop again within the start
/// timeout ends the run (see [`LinkWatch`]), with a fault of its own in the report.
fn watch_the_link(w: &mut Watch, now_s: f64) {
    let Some((role, why)) = w.link.check(w.torques_received, now_s) else { return };
    eprintln!("launcher: {why} ({now_s:.3} s)");
    w.events.push(FaultEvent::now(role, "link-lost", why.clone()));
    w.failures.push(why);
}

/// Every stop and continue of a child, whoever sent the signal (the fault schedule, the
/// user's `kill -STOP`, a debugger's SIGTSTP): a stop the schedule did not make is a fault
/// of its own, listed with its signal, and every stop is ended in the report as continued,
/// killed, judged hung, or with the run. A stop and its continue both between two looks
/// (2 ms apart) show only as the continue, and are listed as a stop of under 2 ms.
fn watch_for_stops(
    launch: &Launch,
    children: &mut Children,
    w: &mut Watch,
    progress: &Progress,
    now_s: f64,
) {
    for (role, c) in &children.0 {
        let pid = c.id();
        match job_control_event(pid) {
            None => {}
            Some(JobControl::Stopped(libc::SIGSTOP))
                if role == Role::Plant.name() && at_a_gate(launch, w, progress) =>
            {
                let tick = progress.0.plant().map_or(0, |s| s.tick);
                w.gated = Some((pid, tick));
                w.gate_clock = Some(tick);
            }
            // The launcher's release of its gate, or the SIGCONT of a stop at the end.
            Some(JobControl::Continued)
                if (w.gate_released == Some(pid) || w.gated.is_some_and(|g| g.0 == pid))
                    && !w.open_stops.contains_key(&pid) =>
            {
                w.gate_released = None;
                w.gated = None;
            }
            Some(JobControl::Stopped(sig)) => {
                if let Some(&i) = w.open_stops.get(&pid) {
                    w.events[i].signal.get_or_insert(signal_name(sig));
                    continue;
                }
                let name = signal_name(sig);
                eprintln!("launcher: {role} was stopped ({name}) at {now_s:.3} s, not by --fault");
                let detail = format!("{name} from outside the launcher");
                w.open_stops.insert(pid, w.events.len());
                let e = FaultEvent {
                    signal: Some(name),
                    ..FaultEvent::now(role.as_str(), "stop", detail)
                };
                w.events.push(e);
            }
            Some(JobControl::Continued) => {
                if !w.open_stops.contains_key(&pid) {
                    let detail = "stopped and continued within 2 ms, not by --fault".to_owned();
                    w.open_stops.insert(pid, w.events.len());
                    w.events.push(FaultEvent::now(role.as_str(), "stop", detail));
                }
                eprintln!("launcher: {role} continued at {now_s:.3} s");
                end_stop(w, pid, "continued");
            }
        }
    }
}

/// Whether the plant, just seen stopped, stopped itself at a gate: lockstep, its newest
/// tick is a gate it has not stopped at before, and no `stop` fault of it is open.
fn at_a_gate(launch: &Launch, w: &Watch, progress: &Progress) -> bool {
    let Some(tick) = progress.0.plant().map(|s| s.tick) else { return false };
    launch.role_args.mode == Mode::Lockstep
        && launch.gates.binary_search(&tick).is_ok()
        && w.gate_clock.is_none_or(|g| tick > g)
        && !w.stopped.contains_key(Role::Plant.name())
}

/// Ends the open stop of `pid`, if any, `how` and now (a continue is also its restart).
fn end_stop(w: &mut Watch, pid: u32, how: &'static str) {
    let Some(i) = w.open_stops.remove(&pid) else { return };
    let e = &mut w.events[i];
    let now = now_ns();
    e.ended.get_or_insert((how, now));
    if how == "continued" {
        e.restart_ns.get_or_insert(now);
    }
}

/// A change of a child's job-control state.
enum JobControl {
    /// Stopped by this signal.
    Stopped(libc::c_int),
    /// Continued (SIGCONT).
    Continued,
}

/// The child's newest stop or continue not yet seen, if any. `waitid` without `WEXITED`
/// consumes only job-control events and leaves an exit for `Child::try_wait`.
fn job_control_event(pid: u32) -> Option<JobControl> {
    // SAFETY: an all-zero siginfo_t is valid; waitid fills it for our own child's pid.
    let mut info: libc::siginfo_t = unsafe { std::mem::zeroed() };
    let opts = libc::WSTOPPED | libc::WCONTINUED | libc::WNOHANG;
    // SAFETY: as above; a pid that is not (or no longer) our child gives ECHILD.
    let rc = unsafe { libc::waitid(libc::P_PID, pid as libc::id_t, &mut info, opts) };
    // SAFETY: si_pid and si_status are set by a successful waitid.
    if rc != 0 || unsafe { info.si_pid() } == 0 {
        return None;
    }
    match info.si_code {
        libc::CLD_STOPPED => Some(JobControl::Stopped(unsafe { info.si_status() })),
        libc::CLD_CONTINUED => Some(JobControl::Continued),
        _ => None,
    }
}

/// Whether process `pid` is dying: a SIGKILL is pending for it (`/proc/PID/status`,
/// `ShdPnd` or `SigPnd`) or it is exiting (`PF_EXITING` in the flags of `/proc/PID/stat`).
/// A process killed while in an uninterruptible wait shows both until the wait ends.
pub(crate) fn dying(pid: u32) -> bool {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    dying_from(&status, &stat)
}

/// [`dying`] from the texts of `/proc/PID/status` and `/proc/PID/stat`.
fn dying_from(status: &str, stat: &str) -> bool {
    const SIGKILL_BIT: u64 = 1 << (libc::SIGKILL - 1);
    const PF_EXITING: u64 = 0x4;
    let pending = status.lines().any(|l| {
        let mask = l.strip_prefix("ShdPnd:").or_else(|| l.strip_prefix("SigPnd:"));
        mask.and_then(|m| u64::from_str_radix(m.trim(), 16).ok())
            .is_some_and(|m| m & SIGKILL_BIT != 0)
    });
    // The flags are the 7th field after the parenthesised command name.
    let flags = stat.rsplit(')').next().and_then(|r| r.split_whitespace().nth(6));
    pending || flags.and_then(|f| f.parse::<u64>().ok()).is_some_and(|f| f & PF_EXITING != 0)
}

/// The name of signal `sig` (`SIGSTOP`), or `signal N`.
fn signal_name(sig: libc::c_int) -> &'static str {
    // Each name is the constant's, written once.
    macro_rules! names {
        ($($name:ident),*) => {
            match sig { $(libc::$name => stringify!($name),)* _ => "another signal" }
        };
    }
    names![
        SIGSTOP, SIGTSTP, SIGTTIN, SIGTTOU, SIGKILL, SIGTERM, SIGINT, SIGSEGV, SIGABRT, SIGBUS,
        SIGHUP, SIGPIPE, SIGQUIT, SIGFPE, SIGILL
    ]
}

/// After the last tick nobody is started again: the ports of a dead role would keep the
/// finished publishers lingering for subscribers that never leave (up to `LINGER_S`), so
/// they are removed as soon as a role is seen dead (`dead` counts the ends dealt with).
/// Not in a split run: there the launcher stops the far host's roles itself after the
/// plant's end (their gateways hold ports of their own), and this was not tested there.
fn remove_dead_ports_after_the_end(launch: &Launch, w: &Watch, dead: &mut usize) {
    if launch.split.is_none() && w.loop_complete && w.handled.len() != *dead {
        *dead = w.handled.len();
        for d in &launch.domains {
            let _ = d.cleanup();
        }
    }
}

/// The watchdog's pass: a role with work waiting and no progress for `--watchdog-ms` is
/// hung: killed (SIGKILL), recorded as a fault, and handed to the restart policy. A
/// controller whose answers since its last accepted one were all refused is not hung but
/// `rejected` (in lockstep an answer for a tick not reached does not end the plant's wait,
/// so such a controller stops the loop as a silent one does). Each role's progress (its mark
/// moved) is told to the restart policy, whose limit ages restarts by it.
fn watch_for_hangs(
    launch: &Launch,
    children: &mut Children,
    w: &mut Watch,
    progress: &Progress,
    now_s: f64,
) {
    let lockstep = launch.role_args.mode == Mode::Lockstep;
    let marks = progress.marks();
    let run_s = marks.plant.map(|k| k as f64 / launch.rate_hz);
    let stopped = holding_the_loop(launch, children, w, lockstep, run_s);
    for r in Role::ALL {
        let role = r.name();
        if marks.of(r) != w.last_marks.of(r) {
            w.supervisor.progressed(role, now_s);
        }
        let pid = children.get_mut(role).map(|c| c.id());
        // A pid already killed (by the schedule or by this watchdog) is not judged again:
        // a stopped process that got its SIGKILL may take a while to die and be reaped on
        // a loaded machine, and each pass over it counted as another hang (seen: one
        // SIGSTOP counted six times 2 ms apart, over the restart limit, the run stopped).
        let alive = pid.is_some_and(|p| !w.handled.contains(&p) && !w.planned.contains(&p));
        // In lockstep the plant waits for this launcher's record mover before a ring comes
        // round (`common::flight::free_through`): the launcher's own work, not a hang.
        let held = r == Role::Plant
            && lockstep
            && (w.gated.is_some()
                || w.mover.as_ref().zip(marks.plant).is_some_and(|(m, k)| m.holds(k)));
        let pending =
            alive && !held && marks.work_waiting_with_stops(r, lockstep, REFERENCE_LEAD, &stopped);
        if !w.watchdog.check(role, progress.alive(r, &marks, lockstep), pending, now_s) {
            continue;
        }
        let c = children.get_mut(role).expect("alive");
        if !matches!(c.try_wait(), Ok(None)) || dying(c.id()) {
            // It has ended already (the launcher itself was descheduled past the limit on a
            // loaded machine, seen: 1.5 s), or it is dying: a SIGKILL from anyone is pending
            // or it is exiting, which takes seconds when the kill finds it in an
            // uninterruptible disk wait (seen under the repeat harness: `folio_wait_bit`).
            // Not a hang; `reap` gives its end its own name.
            continue;
        }
        let refused = (r == Role::Controller).then(|| rejected_since_accepted(w, progress));
        match refused.flatten() {
            Some(streak) => kill_rejected(children, w, streak, now_s),
            None => kill_hung(launch, children, w, role, now_s),
        }
    }
    for (role, c) in &children.0 {
        // A gateway has no mark: alive is its progress.
        if role.starts_with("link-") && !w.handled.contains(&c.id()) {
            w.supervisor.progressed(role, now_s);
        }
    }
    w.last_marks = marks;
}

/// The roles of the loop that hold it up whatever their marks say: those stopped now (any
/// stop, whoever sent it), and in lockstep a controller whose answers an injected delay
/// holds back (`--fault controller:delay`). Such a controller has stored its answer (its
/// mark says answered) but not sent it, and the plant waiting for it by design was judged
/// hung and killed every 3 s (a 60 s delay); it is the controller's answer that is late.
fn holding_the_loop(
    launch: &Launch,
    children: &mut Children,
    w: &Watch,
    lockstep: bool,
    progress_s: Option<f64>,
) -> Vec<Role> {
    let mut stopped: Vec<Role> = Role::ALL
        .into_iter()
        .filter(|r| children.get_mut(r.name()).is_some_and(|c| w.open_stops.contains_key(&c.id())))
        .collect();
    // The delay runs on the states' times, the run's clock.
    let run_s = progress_s.unwrap_or(f64::NEG_INFINITY);
    let delaying = launch.faults.iter().any(|f| match f.kind {
        FaultKind::Delay(d) => {
            run_s >= f.kill_s && f.restart_s.is_none_or(|until| run_s < until + d)
        }
        _ => false,
    });
    if lockstep && delaying && !stopped.contains(&Role::Controller) {
        stopped.push(Role::Controller);
    }
    stopped
}

/// Kills `role`, found hung, and hands it to the restart policy.
fn kill_hung(launch: &Launch, children: &mut Children, w: &mut Watch, role: &str, now_s: f64) {
    let Some(c) = children.get_mut(role) else { return };
    let pid = c.id();
    w.planned.insert(pid);
    signal(c, libc::SIGKILL);
    end_stop(w, pid, "hung");
    let ms = launch.args.watchdog_ms;
    eprintln!(
        "launcher: {role} made no progress for {ms} ms with work waiting: hung; killed (SIGKILL) at {now_s:.3} s"
    );
    let detail = format!("no progress for {ms} ms; killed by the watchdog");
    let hang = FaultEvent { signal: Some("SIGKILL"), ..FaultEvent::now(role, "hang", detail) };
    w.events.push(hang);
    let verdict = w.supervisor.on_end(role, Ending::Hang, "hung", None, now_s, false);
    decide(role, verdict, w, now_s);
}

/// The controller's answers since the plant last accepted one, if any were refused.
fn rejected_since_accepted(w: &mut Watch, progress: &Progress) -> Option<Streak> {
    let s = progress.0.plant()?;
    w.rejects.streak(s.tick, s.applied_torque_tick, refused(progress, &s))
}

/// The plant's refusals by kind (its slot of them), counted up to its state `s`'s own
/// count where that is newer. The slot is written at each refusal, the state once a
/// tick: in lockstep a refusal that ends no tick (an answer for a tick not reached) is
/// in the slot only.
fn refused(progress: &Progress, s: &StateSample) -> Refusals {
    let mut r = progress.0.refusals().unwrap_or_default();
    r.total = r.total.max(s.torques_rejected);
    r
}

/// The rule for a controller that answers but is always refused ([`RejectWatch`]): once
/// `--hold-ticks` of its answers in a row were rejected, it is killed (SIGKILL), listed as
/// a `rejected` fault of the controller, and handed to the restart policy.
fn watch_for_rejections(children: &mut Children, w: &mut Watch, progress: &Progress, now_s: f64) {
    let role = Role::Controller.name();
    let Some(pid) = children.get_mut(role).map(|c| c.id()) else { return };
    if w.handled.contains(&pid) || w.planned.contains(&pid) || w.open_stops.contains_key(&pid) {
        return;
    }
    let Some(s) = progress.0.plant() else { return };
    let streak = w.rejects.check(s.tick, s.applied_torque_tick, refused(progress, &s));
    if let Some(streak) = streak.filter(|_| !dying(pid)) {
        kill_rejected(children, w, streak, now_s);
    }
}

/// Kills the controller whose answers the plant refused (`streak`), lists the fault and
/// hands it to the restart policy.
fn kill_rejected(children: &mut Children, w: &mut Watch, streak: Streak, now_s: f64) {
    let role = Role::Controller.name();
    let Some(c) = children.get_mut(role) else { return };
    let pid = c.id();
    w.planned.insert(pid);
    signal(c, libc::SIGKILL);
    end_stop(w, pid, "rejected");
    let Streak { rejected, from_tick, to_tick, kinds, .. } = streak;
    let last = kinds.last_tick;
    let detail = format!(
        "the plant refused its answers: {rejected} in a row and none accepted, over ticks \
         {from_tick} to {to_tick} ({}; the last one for tick {last}); killed (SIGKILL)",
        kinds.describe()
    );
    eprintln!("launcher: {role} answers but every answer is refused: {detail}, at {now_s:.3} s");
    let e = FaultEvent { signal: Some("SIGKILL"), ..FaultEvent::now(role, "rejected", detail) };
    w.events.push(e);
    let what = "answered only with torques the plant refused";
    let verdict = w.supervisor.on_end(role, Ending::Rejected, what, None, now_s, false);
    decide(role, verdict, w, now_s);
}

/// Reaps the children that ended: an end nobody planned is a fault (unless it is a clean
/// exit), and goes to the restart policy. Returns how many children still run.
fn reap(
    children: &mut Children,
    w: &mut Watch,
    progress: &Progress,
    stopping: bool,
    now_s: f64,
) -> usize {
    let mut running = 0;
    for (role, c) in &mut children.0 {
        let pid = c.id();
        match c.try_wait() {
            // The gateways run until the roles are done (then they are stopped).
            Ok(None) => running += usize::from(!role.starts_with("link-")),
            Ok(Some(st)) if w.open_stops.contains_key(&pid) || !w.handled.contains(&pid) => {
                let how = Ending::of(st);
                end_stop(w, pid, how.name());
                if !w.handled.insert(pid) || w.planned.contains(&pid) || stopping {
                    continue;
                }
                // A clean exit before the last tick left work undone: a fault like any
                // other end (a controller that exits 0 at once left the plant waiting for
                // a subscriber for ever).
                let complete = progress.0.loop_complete();
                if how != Ending::Exited || !complete {
                    let early = match how {
                        Ending::Exited => ", before the run's last tick",
                        _ => "",
                    };
                    eprintln!("launcher: {role} {} ({st}) at {now_s:.3} s{early}", how.name());
                    let mut detail = st.to_string();
                    // A role that died of a full /dev/shm (SIGBUS on a mapped page, or a
                    // node refused) is told so, with the space the run needs there.
                    if let Some(full) = rotorloop_common::private::shm_full(Some(w.shm_need)) {
                        eprintln!("launcher: {full}");
                        detail = format!("{detail}; {full}");
                    }
                    let signal = st.signal().map(signal_name);
                    let e =
                        FaultEvent { signal, ..FaultEvent::now(role.as_str(), how.name(), detail) };
                    w.events.push(e);
                }
                let what = format!("exited with {st}");
                let verdict = w.supervisor.on_end(role, how, &what, st.code(), now_s, complete);
                decide(role, verdict, w, now_s);
            }
            _ => {}
        }
    }
    running
}

/// Carries out the supervisor's verdict on `role`. The monitor is an observer: when it may
/// not be restarted again, the loop goes on without it.
fn decide(role: &str, verdict: Verdict, w: &mut Watch, now_s: f64) {
    match verdict {
        Verdict::Done => {}
        Verdict::Restart { at_s } => {
            if at_s > now_s {
                eprintln!("launcher: restarting {role} in {:.1} s (backoff)", at_s - now_s);
            }
            w.restarts.insert(role.to_owned(), at_s);
        }
        Verdict::Fail(msg) if role == Role::Monitor.name() => {
            eprintln!("launcher: {msg}; the loop goes on without a monitor");
            if let Some(e) = w.events.last_mut().filter(|e| e.role == role) {
                e.detail = format!("{}; given up: {msg}", e.detail);
            }
        }
        Verdict::Fail(msg) => w.failures.push(msg),
    }
}

/// Starts `role` again (reaping the dead one first), at `at` s: the watchdog's clock starts
/// again, and the newest fault event of the role gets its restart time.
fn restart(
    launch: &Launch,
    children: &mut Children,
    rss: &mut RssLog,
    w: &mut Watch,
    role: &str,
    at: f64,
) -> anyhow::Result<()> {
    // The predecessor must be gone (reaped) before its successor starts: a zombie looks
    // alive to the successor's clean-up of dead nodes. One that is still dying (a SIGKILL
    // waits for an uninterruptible disk wait to end) postpones the restart to a later poll
    // instead of blocking the loop.
    if let Some(c) = children.get_mut(role)
        && matches!(c.try_wait(), Ok(None))
    {
        w.restarts.insert(role.to_owned(), at);
        return Ok(());
    }
    // After the last tick a role has nothing left to do: started again it would only
    // wait for states that never come (a plant would even start a new run). A monitor
    // that is down then has its report assembled by the launcher from the flight records.
    if w.loop_complete {
        eprintln!("launcher: {role} not restarted at {at:.3} s: the run has ended");
        if let Some(e) = w.events.iter_mut().rev().find(|e| e.role == role) {
            e.detail = format!("{}; not restarted: the run had ended", e.detail);
        }
        return Ok(());
    }
    let refused = refused_resume(launch, role);
    let child = launch.spawn(role, rss).with_context(|| format!("cannot restart {role}"))?;
    if let Some(c) = children.get_mut(role) {
        *c = child;
    }
    w.watchdog.reset(role, at);
    if role == Role::Controller.name() {
        w.rejects.reset();
    }
    if let Some(split) = &launch.split {
        let plant_host = split.host_of(Role::Plant.name());
        let far = role != Role::Monitor.name() && split.host_of(role) != plant_host;
        if far || role.starts_with("link-") {
            w.link.restarted(role, at, w.torques_received);
        }
    }
    if let Some(e) = w.events.iter_mut().rev().find(|e| e.role == role) {
        e.restart_ns = Some(now_ns());
    }
    eprintln!("launcher: restarted {role} at {at:.3} s");
    if let Some(why) = refused {
        eprintln!(
            "launcher: {role}'s resume slot was refused ({why}); it starts as a fresh {role}"
        );
        let e = FaultEvent::now(role, "resume-refused", why);
        w.events.push(FaultEvent { restart_ns: Some(e.kill_ns), ..e });
    }
    Ok(())
}

/// A role about to be restarted: its resume slot checked as the role itself will check it
/// ([`Resumable`]). One it would refuse is forgotten here (the role starts as a fresh one
/// would) and the reason returned, for the launcher to list as a fault of its own.
fn refused_resume(launch: &Launch, role: &str) -> Option<String> {
    use iceoryx2::prelude::ZeroCopySend;
    use rotorloop_common::resume::{Resumable, ResumeSlot};
    fn check<T: Copy + ZeroCopySend + Resumable>(launch: &Launch, role: &str) -> Option<String> {
        // None, or not this user's own (then the role refuses to start: exit 2).
        let slot = ResumeSlot::<T>::open_existing(launch.domain_of(role), role).ok()??;
        slot.load_checked(launch.ticks).err()
    }
    match role.parse::<Role>().ok()? {
        Role::Plant => check::<rotorloop_common::wire::StateSample>(launch, role),
        Role::Controller => check::<rotorloop_controller::policy::ControllerResume>(launch, role),
        Role::Reference => check::<rotorloop_reference::policy::ReferenceResume>(launch, role),
        Role::Monitor => check::<rotorloop_monitor::policy::MonitorResume>(launch, role),
    }
}

/// `role` was killed by a `--fault` without `restart@`: it stays down to the end. Under
/// `--restart never` that is a role lost beyond its policy, and in lockstep a loop without
/// its plant, controller, reference or gateway cannot go on (the plant waited for a torque
/// for ever): either way the run stops, exit 1, with its report. A monitor is an observer.
fn down_for_good(launch: &Launch, w: &mut Watch, role: &str) {
    if role == Role::Monitor.name() {
        return;
    }
    let never = w.supervisor.policy(role) == crate::run::policy::RestartPolicy::Never;
    let lockstep = launch.role_args.mode == Mode::Lockstep;
    let why = match (never, lockstep) {
        (true, _) => "its restart policy is never",
        (false, true) => "a lockstep loop cannot go on without it",
        (false, false) => return,
    };
    w.failures.push(format!("{role} was killed by --fault with no restart@, and {why}"));
}

/// Carries out one action of the `--fault` schedule, as its row of `fault::KINDS` says.
fn injected(
    launch: &Launch,
    children: &mut Children,
    rss: &mut RssLog,
    w: &mut Watch,
    action: Action,
    (at, tick): (f64, Option<u64>),
) -> anyhow::Result<()> {
    let name = action.role.to_string();
    let (kind, role) = (action.kind.spec().start, name.as_str());
    // The run's clock (the plant's tick) and the launcher's own (s since tick 0).
    let at_tick = tick.map_or_else(String::new, |k| format!(" (tick {k})"));
    match action.apply() {
        Apply::Signal(sig, name) if sig == libc::SIGCONT => {
            let stopped = w.stopped.remove(role);
            let event = stop_event(&mut w.events, role);
            match children.get_mut(role) {
                Some(c) if Some(c.id()) == stopped && !w.planned.contains(&c.id()) => {
                    continue_stopped(c, event, &format!("; {name} (--fault)"));
                    // A plant stopped at its gate: this continue is also the gate's release.
                    if w.gated.is_some_and(|g| g.0 == c.id()) {
                        w.gated = None;
                    }
                    eprintln!("launcher: continued {role} ({name}) at {at:.3} s{at_tick}");
                }
                _ => {
                    eprintln!(
                        "launcher: {role} was restarted by the watchdog before its {name} at {at:.3} s"
                    );
                    if let Some(e) = event {
                        e.detail
                            .push_str(&format!("; the watchdog restarted it before the {name}"));
                    }
                }
            }
        }
        Apply::Signal(sig, name) => {
            let Some(c) = children.get_mut(role) else { return Ok(()) };
            let pid = c.id();
            if sig == libc::SIGKILL {
                w.planned.insert(pid);
            }
            signal(c, sig);
            // Its moment is when the signal is sent, not when the launcher decided to send
            // it: preempted in between (a busy loop per core), the launcher once stamped a
            // kill several ticks before the controller died, whose last answers then showed
            // as answers from after the kill (faults::realtime_controller_loss…, 1 of 20).
            let e = FaultEvent {
                signal: Some(name),
                scheduled: true,
                ..FaultEvent::now(role, kind, format!("{name} (--fault)"))
            };
            // A SIGKILLed process is reaped by `reap` once it has exited, not waited for
            // here: one in an uninterruptible disk wait takes seconds to die under load, and
            // a blocking wait stalled this whole loop (fault schedule, watchdog, record
            // mover: records were overwritten before they were moved).
            if sig == libc::SIGSTOP {
                w.stopped.insert(role.to_owned(), pid);
                w.watchdog.stopped(role);
                w.open_stops.insert(pid, w.events.len());
            }
            let verb = match sig {
                libc::SIGKILL => "killed",
                libc::SIGSTOP => "stopped",
                _ => "signalled",
            };
            eprintln!("launcher: {verb} {role} ({name}) at {at:.3} s{at_tick}");
            w.events.push(e);
            if sig == libc::SIGKILL && !action.ends {
                down_for_good(launch, w, role);
            }
        }
        Apply::Restart => {
            w.restarts.remove(role); // the schedule's restart replaces a supervisor's
            restart(launch, children, rss, w, role, at)?;
        }
        Apply::ByTheRole(flag) if action.starts => {
            let FaultKind::Delay(d) = action.kind else { return Ok(()) };
            let ms = d * 1e3;
            eprintln!("launcher: {role} answers {ms} ms late from {at:.3} s ({flag})");
            let detail = format!("each answer sent {ms} ms late (--fault {kind})");
            w.events.push(FaultEvent { scheduled: true, ..FaultEvent::now(role, kind, detail) });
        }
        Apply::ByTheRole(_) => {
            eprintln!("launcher: {role}'s {kind} ends at {at:.3} s");
            if let Some(e) = w.events.iter_mut().rev().find(|e| e.role == role && e.kind == kind) {
                e.restart_ns = Some(now_ns());
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pending_sigkill_or_an_exit_is_dying_and_a_running_process_is_not() {
        let stat = |flags: u64| format!("42 (a (b) c) S 1 42 42 0 -1 {flags} 0 0");
        let status = |shd: &str, sig: &str| format!("Name:\tx\nSigPnd:\t{sig}\nShdPnd:\t{shd}\n");
        let none = "0000000000000000";
        assert!(!dying_from(&status(none, none), &stat(0x400000)));
        assert!(dying_from(&status("0000000000000100", none), &stat(0)), "SIGKILL shared");
        assert!(dying_from(&status(none, "0000000000000100"), &stat(0)), "SIGKILL own");
        assert!(!dying_from(&status("0000000000004000", none), &stat(0)), "SIGTERM is not");
        assert!(dying_from(&status(none, none), &stat(0x400004)), "PF_EXITING");
        // A real process: running, then killed and not yet reaped (a zombie has exited).
        let mut child = std::process::Command::new("sleep").arg("100").spawn().expect("sleep");
        let pid = child.id();
        assert!(!dying(pid));
        // SAFETY: signals our own child.
        unsafe { libc::kill(pid as libc::pid_t, libc::SIGKILL) };
        let zombie = || {
            std::fs::read_to_string(format!("/proc/{pid}/stat")).is_ok_and(|s| {
                s.rsplit(')').next().is_some_and(|r| r.trim_start().starts_with('Z'))
            })
        };
        while !zombie() {
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        assert!(dying(pid), "a killed process not yet reaped");
        child.wait().expect("reap");
    }
}
