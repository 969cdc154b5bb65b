//! Why an incident happened: from the launcher's faults and the fault schedule, from a
//! rejected sample (what was rejected, by whom, and whose it was), from the loop's own
//! stamps (which stage of the tick held it up, beyond its median, and whose process that
//! stage is), and from the kernel's view of that process (`sched.csv`: time runnable but
//! not running, stopped, on a CPU; the machine's steal time).

use std::sync::LazyLock;

use rotorloop_common::graph::{Role, Topic};
use rotorloop_common::wire::{NO_TICK, ReferenceSample, StateSample, TorqueSample};

use rotorloop_monitor::summary::FaultRow;

use super::load::{RunRecord, SchedRow};
use super::ticks::{self, DELAY, LATE, MISS, NOT_FRESH, REFERENCE_LATE, REJECTED, SAFE, TickFlags};

/// What an incident's cause is.
#[derive(Debug, Clone, PartialEq)]
pub struct Cause {
    /// `simulator stall`, `fault`, `injected delay`, `miss`, `late torque`, `safe mode`,
    /// `rejected samples`, `late reference`.
    pub kind: &'static str,
    /// The process ([`ANOTHER_PUBLISHER`] for a rejected sample the role of its topic did
    /// not publish).
    pub role: String,
    /// The stage of the tick that held it up, or what was done to the process.
    pub stage: String,
    /// The stamps and kernel figures behind it, in words.
    pub evidence: String,
}

/// Who sent a rejected sample that the role publishing its topic did not send (its own
/// record of that tick is valid): a same-user process, or a link gateway's peer.
pub const ANOTHER_PUBLISHER: &str = "another publisher";

/// The stages of one tick that belong to one process (ns): the plant's wake after its
/// grid time; its work from its wake to the state's publish; the state's delivery up to
/// the controller having it (its wake-up); the controller from then to its torque's
/// publish; the torque's delivery up to the plant having it (its wake-up).
/// Derived from the loop's graph: the state's publisher (the plant) and the torque's (the
/// controller), whose answer closes the loop.
static STAGES: LazyLock<[(String, &str); 5]> = LazyLock::new(|| {
    let (p, c) = (Topic::State.publisher(), Topic::Torque.publisher());
    let (state, torque) = (Topic::State.name(), Topic::Torque.name());
    [
        (format!("{p} wake"), p.name()),
        (format!("{p} publish"), p.name()),
        (format!("{state} delivery (the {c}'s wake-up)"), c.name()),
        (format!("{c} compute"), c.name()),
        (format!("{torque} delivery (the {p}'s wake-up)"), p.name()),
    ]
});

/// When the answer to state `k` took effect: (tick, offset), if it did within 10 000
/// ticks. The search ends where a newer answer is in force: the plant accepts only a
/// torque newer than every one it accepted before (`rotorloop_plant::policy`), so an
/// answer not in effect by then never is (without that end, each tick of a window whose
/// answers never took effect read the 10 000 states after it).
fn took_effect(run: &RunRecord, k: u64) -> Option<(u64, f64)> {
    for j in k..(k + 10_000).min(run.last) {
        let Some(n) = run.state(j + 1) else { continue };
        let m = (n.effects as usize).min(n.effect_ticks.len());
        if let Some(i) = (0..m).find(|i| n.effect_ticks[*i] == k) {
            return Some((j, n.effect_offsets_s[i]));
        }
        if n.applied_torque_tick != NO_TICK && n.applied_torque_tick > k {
            return None;
        }
    }
    None
}

/// The five stages of tick `k` (ns), each where its stamps allow (the wake in real time
/// only; the torque's delivery only where the plant took that answer as the one in
/// force).
pub(super) fn stages(run: &RunRecord, k: u64) -> [Option<u64>; 5] {
    let (s, t) = (run.state(k), run.torque(k));
    let n = took_effect(run, k)
        .and_then(|(j, _)| run.state(j + 1))
        .filter(|n| n.applied_torque_tick == k);
    [
        s.filter(|s| s.deadline_ns > 0)
            .and_then(|s| s.wake_ns.checked_sub(s.deadline_ns))
            .map(|w| w + ticks::paused_ns(run, k)),
        s.and_then(|s| s.publish_ns.checked_sub(s.wake_ns)),
        // A state never answered waited for the controller at least until it took the next.
        s.zip(t.or_else(|| run.next_answer(k)))
            .and_then(|(s, t)| t.state_recv_ns.checked_sub(s.publish_ns)),
        t.and_then(|t| t.publish_ns.checked_sub(t.state_recv_ns)),
        n.zip(t).and_then(|(n, t)| n.applied_torque_recv_ns.checked_sub(t.publish_ns)),
    ]
}

/// Each stage's median over the run's fresh ticks (ns), a tick at a time, for passes over
/// the ticks made for something else: every tick `0..last` is seen ([`StageMedians::see`])
/// in each of two passes, with [`StageMedians::second_pass`] between them. In bounded
/// memory (`ticks::Medians`); the stages are in ns, the medians' keys in s.
#[derive(Debug, Default)]
pub struct StageMedians(ticks::Medians<5>);

impl StageMedians {
    /// Sees tick `k`, whose flags are `flags` (only a fresh tick's stages count).
    pub fn see(&mut self, run: &RunRecord, k: u64, flags: u16) {
        if flags != 0 {
            return;
        }
        for (i, x) in stages(run, k).iter().enumerate() {
            if let Some(x) = x {
                self.0.add(i, *x as f64 / 1e9);
            }
        }
    }

    /// Ends the first pass.
    pub fn second_pass(&mut self) {
        self.0.second_pass();
    }

    /// The medians (ns), after the second pass.
    pub fn medians(&self) -> [f64; 5] {
        self.0.medians().map(|s| (s * 1e9).round())
    }
}

fn ms(ns: f64) -> String {
    format!("{:.3} ms", ns / 1e6)
}

/// Whether the fault schedule asked for `f`: as the launcher said, or, in a `summary.json`
/// that does not say, a fault of the schedule's role and kind within 50 ms of its time (a
/// guess that a loaded real-time run's drifting grid defeats).
fn scheduled(run: &RunRecord, f: &FaultRow) -> bool {
    f.scheduled.unwrap_or_else(|| {
        run.schedule
            .iter()
            .any(|s| s.role == f.role && s.kind == f.kind && (s.at_s - f.kill_s).abs() < 0.05)
    })
}

/// The first fault of a loop role whose ticks overlap `[start, end]` (its index in
/// `run.faults`).
pub fn fault_of(run: &RunRecord, [start, end]: [u64; 2]) -> Option<usize> {
    run.faults
        .iter()
        .zip(run.fault_spans())
        .position(|(f, [from, to])| ticks::in_loop(&f.role) && *from <= end && *to >= start)
}

/// The cause of a fault the launcher saw.
pub fn fault_cause(run: &RunRecord, f: &FaultRow) -> Cause {
    if f.kind == "delay" {
        return Cause {
            kind: "injected delay",
            role: f.role.clone(),
            stage: "injected delay".into(),
            evidence: format!(
                "{} from {:.3} s{} ({})",
                f.detail,
                f.kill_s,
                f.restart_s.map(|u| format!(" until {u:.3} s")).unwrap_or_default(),
                if scheduled(run, f) { "the fault schedule" } else { "not in the schedule" }
            ),
        };
    }
    let by = if scheduled(run, f) { "by the fault schedule" } else { "from outside the launcher" };
    let what = match f.kind.as_str() {
        "stop" => "stopped",
        "kill" | "killed" => "killed",
        "hang" => "hung (the watchdog found no progress)",
        "crash" => "crashed",
        "exited" => "exited",
        "rejected" => "answered only with torques the plant refused",
        "resume-refused" => "restarted from scratch (its resume slot was refused)",
        _ => "lost its link",
    };
    let end = match (f.kind.as_str(), f.ended_s.or(f.restart_s)) {
        ("stop", Some(e)) => {
            format!(", continued at {e:.3} s ({:.1} ms stopped)", (e - f.kill_s) * 1e3)
        }
        (_, Some(e)) => format!(", started again at {e:.3} s"),
        (_, None) => ", not started again".to_owned(),
    };
    let signal = f.signal.as_deref().map(|s| format!(" ({s})")).unwrap_or_default();
    Cause {
        kind: if f.role == Role::Plant.name() { "simulator stall" } else { "fault" },
        role: f.role.clone(),
        stage: format!("{what}{signal}"),
        evidence: format!("{} {what}{signal} {by} at {:.3} s{end}", f.role, f.kill_s),
    }
}

/// The cause of the incident `[start, end]` whose ticks' flags together are `all`.
pub fn cause(
    run: &RunRecord,
    flags: &TickFlags,
    medians: &[f64; 5],
    [start, end]: [u64; 2],
) -> Cause {
    let all = flags.all(run, [start, end]);
    let c = if let Some(f) = fault_of(run, [start, end]).map(|i| &run.faults[i]) {
        fault_cause(run, f)
    } else if let Some(d) =
        run.schedule.iter().find(|d| d.kind == "delay").filter(|_| all & DELAY != 0)
    {
        let v = d.value_s.unwrap_or(0.0);
        Cause {
            kind: "injected delay",
            role: Role::Controller.name().into(),
            stage: "injected delay".into(),
            evidence: format!(
                "--fault controller:delay@{}={v}: each answer sent {:.1} ms late from {:.3} s{}",
                d.at_s,
                v * 1e3,
                d.at_s,
                d.until_s.map(|u| format!(" until {u:.3} s")).unwrap_or_default()
            ),
        }
    } else if all & REJECTED != 0 {
        rejected(run, flags, [start, end], kind_of(all))
    } else {
        from_stamps(run, flags, medians, [start, end], all)
    };
    with_kernel(run, c, [start, end])
}

/// The kind of an incident from its ticks' flags, when no fault or injected delay explains
/// it.
fn kind_of(all: u16) -> &'static str {
    match all {
        a if a & SAFE != 0 => "safe mode",
        a if a & REJECTED != 0 => "rejected samples",
        a if a & REFERENCE_LATE != 0 => "late reference",
        a if a & (MISS | NOT_FRESH) != 0 => "miss",
        _ => "late torque",
    }
}

/// An incident in which a sample was rejected is named after the rejection, never after a
/// stage's timing: a stage slower than usual on one of its ticks did not make it an
/// incident (a torque for a tick the loop had not reached, from a same-user process, was
/// once reported as a "simulator stall"). It names the first such tick, the receiver and
/// the topic, and whose the sample was: the publishing role's own, if its record of that
/// tick fails the same validation, else [`ANOTHER_PUBLISHER`]'s.
fn rejected(
    run: &RunRecord,
    flags: &TickFlags,
    [start, end]: [u64; 2],
    kind: &'static str,
) -> Cause {
    let k = (start..=end).find(|k| flags.get(run, *k) & REJECTED != 0).unwrap_or(start);
    let more = |before: u64, after: u64| after.saturating_sub(before);
    let (s, n) = (run.state(k), run.state(k + 1));
    let torques = s.zip(n).map_or(0, |(s, n)| more(s.torques_rejected, n.torques_rejected));
    // The controller's counts, in its answer to state k against its previous one.
    let answers = run.torque(k).zip(ticks::previous_answer(run, k));
    let states = answers.map_or(0, |(t, p)| more(p.states_rejected, t.states_rejected));
    let limits = run.scenario.limits_for(run.scenario.actuation());
    let limit = TorqueSample::absurd_limit(limits.rotor_torque);
    // What was rejected, how many, by whom, whose topic it is, and that role's own sample
    // of the tick as validated again.
    let (topic, count, receiver, own) = if torques > 0 {
        (Topic::Torque, torques, Role::Plant, run.torque(k).map(|t| t.validate(limit)))
    } else if states > 0 {
        (Topic::State, states, Role::Controller, s.as_ref().map(StateSample::validate))
    } else {
        let references =
            answers.map_or(0, |(t, p)| more(p.references_rejected, t.references_rejected));
        let own = run.references.get(k).as_ref().map(ReferenceSample::validate);
        (Topic::Reference, references, Role::Controller, own)
    };
    let (what, role) = (topic.name(), topic.publisher().name());
    let (role, whose) = match own {
        Some(Err(f)) => (role, format!("its own {what} of tick {k} was invalid: {f}")),
        Some(Ok(())) => (
            ANOTHER_PUBLISHER,
            format!(
                "the {role}'s own {what} of tick {k} was valid: the rejected one came from \
                 another publisher on the topic (a same-user process or a link peer; \
                 summary.json's wire_faults has the monitor's view of it)"
            ),
        ),
        None => (role, format!("the {role}'s record has no {what} of tick {k}")),
    };
    Cause {
        kind,
        role: role.into(),
        stage: format!("{what} rejected by the {receiver}"),
        evidence: format!("tick {k}: the {receiver} rejected {count} {what} sample(s); {whose}"),
    }
}

/// `c` with the kernel's view of its process over `[start, end]` added.
pub fn with_kernel(run: &RunRecord, mut c: Cause, [start, end]: [u64; 2]) -> Cause {
    if let Some(k) = kernel(run, &c.role, [start, end]) {
        c.evidence = format!("{}; kernel: {k}", c.evidence);
    }
    c
}

/// A plant that woke late: the worst tick's lateness, and the states it then published at
/// once to catch up.
fn late_wake(run: &RunRecord, flags: &TickFlags, [start, end]: [u64; 2]) -> Cause {
    let woke = |k: u64| run.state(k).map_or(0, |s| s.wake_ns.saturating_sub(s.deadline_ns));
    let late = |k: u64| woke(k) + ticks::paused_ns(run, k);
    let worst = (start..=end).max_by_key(|k| late(*k)).unwrap_or(start);
    if ticks::paused_ns(run, worst) > 0 && woke(worst) < ticks::paused_ns(run, worst) {
        return Cause {
            kind: "simulator stall",
            role: Role::Plant.name().into(),
            stage: format!("{} (the world's clock paused)", STAGES[0].0),
            evidence: format!(
                "state {worst} published {} after its tick's time on the grid before it; the \
                 grid moved on from its wake (--plant-stall pause, or a restarted plant's new \
                 grid): the physics did not feel the stall",
                ms(late(worst) as f64)
            ),
        };
    }
    let burst = (worst..=end.min(run.last)).take_while(|k| flags.get(run, *k) & LATE != 0).count();
    Cause {
        kind: "simulator stall",
        role: Role::Plant.name().into(),
        stage: STAGES[0].0.clone(),
        evidence: format!(
            "state {worst} published {} after its grid time (the plant did not run); {burst} \
             late state(s) from it",
            ms(late(worst) as f64)
        ),
    }
}

/// The stage that exceeded its median most on any tick of the incident, and its process;
/// where no tick has the stamps to say (answers missing), what the missing answers say.
fn from_stamps(
    run: &RunRecord,
    flags: &TickFlags,
    medians: &[f64; 5],
    [start, end]: [u64; 2],
    all: u16,
) -> Cause {
    let kind = kind_of(all);
    let worst = (start..=end)
        .flat_map(|k| {
            let st = stages(run, k);
            (0..5).filter_map(move |i| st[i].map(|v| (k, i, v as f64 - medians[i])))
        })
        .max_by(|a, b| a.2.total_cmp(&b.2));
    let Some((k, i, excess)) = worst else { return unanswered(run, [start, end], kind) };
    if i == 0 {
        return late_wake(run, flags, [start, end]);
    }
    let parts: Vec<String> = STAGES
        .iter()
        .zip(stages(run, k))
        .filter_map(|((n, _), v)| v.map(|v| format!("{n} {}", ms(v as f64))))
        .collect();
    let effect = match took_effect(run, k) {
        Some((j, o)) => {
            format!("took effect {} after its grid time", ms(((j - k) as f64 * run.dt + o) * 1e9))
        }
        None => "never took effect".into(),
    };
    let role = if kind == "late reference" { Role::Reference.name() } else { STAGES[i].1 };
    let kind = if i == 1 { "simulator stall" } else { kind };
    Cause {
        kind,
        role: role.into(),
        stage: STAGES[i].0.to_owned(),
        evidence: format!(
            "tick {k}: {} {} over its median; its answer {effect}; {}",
            STAGES[i].0,
            ms(excess),
            parts.join(", ")
        ),
    }
}

/// An incident whose ticks have no stamps to weigh: what the missing answers say.
fn unanswered(run: &RunRecord, [start, end]: [u64; 2], kind: &'static str) -> Cause {
    let k = (start..=end).find(|k| run.torque(*k).is_none_or(|t| !t.computed())).unwrap_or(start);
    let (stage, detail) = match run.torque(k) {
        None if skipped(run, k) => (
            "controller late to wake",
            "the controller took it with a newer state already waiting, and answered that one",
        ),
        None => ("controller absent", "no answer to it was published"),
        Some(_) => (
            "controller had nothing to track",
            "its answer was not computed (the state or its reference rejected or missing)",
        ),
    };
    let late = kind == "late reference";
    let role = if late { Role::Reference.name() } else { Role::Controller.name() };
    Cause { kind, role: role.into(), stage: stage.into(), evidence: format!("state {k}: {detail}") }
}

/// Whether the controller took state `k` but answered a newer one (its next answer counts
/// a skipped state more than its previous one).
fn skipped(run: &RunRecord, k: u64) -> bool {
    let before = ticks::previous_answer(run, k);
    let after = (k + 1..(k + 64).min(run.last + 1)).find_map(|j| run.torque(j));
    matches!((before, after), (Some(b), Some(a)) if a.states_skipped > b.states_skipped)
}

/// How long the rows `seen` (one role's, in time order; a row is written at each change
/// of state) say it was stopped (`T`, or `t` traced): from each stopped row to the next
/// row that is not, give or take one sampling period.
fn stopped_ns(seen: &[&SchedRow]) -> u64 {
    let is_stopped = |r: &SchedRow| r.state == 'T' || r.state == 't';
    let (mut total, mut since) = (0, None::<u64>);
    for r in seen {
        match (is_stopped(r), since) {
            (true, None) => since = Some(r.t_ns),
            (false, Some(s)) => {
                total += r.t_ns - s;
                since = None;
            }
            _ => {}
        }
    }
    let last = seen.last().map_or(0, |r| r.t_ns);
    total + since.map_or(0, |s| last.saturating_sub(s) + crate::pipeline::sched_csv::PERIOD_NS)
}

/// The kernel's view of `role` over the incident, from `sched.csv`.
fn kernel(run: &RunRecord, role: &str, [start, end]: [u64; 2]) -> Option<String> {
    let from = run.grid_ns(start).saturating_sub((run.dt * 1e9) as u64);
    let to = run.grid_ns(end + 1) + (run.dt * 1e9) as u64;
    let seen = role_rows(&run.sched, role, [from, to]);
    let (a, b) = (seen.first()?, seen.last()?);
    if b.t_ns <= a.t_ns {
        return None;
    }
    let mut words = Vec::new();
    let stopped = stopped_ns(&seen);
    if stopped > 0 {
        words.push(format!("stopped (T) for about {}", ms(stopped as f64)));
    }
    let pids: Vec<u32> = seen.iter().map(|r| r.pid).collect();
    if a.pid == b.pid {
        let wait = b.wait_ns.saturating_sub(a.wait_ns) as f64;
        let on = b.on_cpu_ns.saturating_sub(a.on_cpu_ns) as f64;
        words.push(format!("runnable, not running for {}", ms(wait)));
        words.push(format!("on a CPU for {}", ms(on)));
    } else if pids.windows(2).any(|w| w[0] != w[1]) {
        words.push(format!("a new process (pid {} → {})", a.pid, b.pid));
    }
    let steal = b.steal_ns.saturating_sub(a.steal_ns);
    if steal > 0 {
        words.push(format!("the host took the vCPUs for {} (steal)", ms(steal as f64)));
    }
    let mut cpus: Vec<u32> = seen.iter().map(|r| r.cpu).collect();
    cpus.sort_unstable();
    cpus.dedup();
    for cpu in cpus.iter().filter(|_| run.traced) {
        words.push(ran_instead(run, *cpu, &pids, [from, to]));
    }
    Some(format!(
        "{role} (pid {}, CPU {}) over {}: {}",
        b.pid,
        b.cpu,
        ms((b.t_ns - a.t_ns) as f64),
        words.join(", ")
    ))
}

/// `role`'s rows of `sched` (in time order) from its last at or before `from` (its first,
/// if none) to its first at or after `to` (its last, if none). Found by bisection, so an
/// incident costs the rows near it, not all the rows kept: a soak with many incidents
/// spent minutes scanning every row once per incident.
fn role_rows<'a>(sched: &'a [SchedRow], role: &str, [from, to]: [u64; 2]) -> Vec<&'a SchedRow> {
    let is = |r: &&SchedRow| r.role == role;
    let lo = sched.partition_point(|r| r.t_ns <= from);
    let first = || sched.iter().position(|r| is(&r));
    let Some(start) = sched[..lo].iter().rposition(|r| is(&r)).or_else(first) else {
        return Vec::new();
    };
    let hi = sched.partition_point(|r| r.t_ns < to);
    let end = match sched[hi..].iter().position(|r| is(&r)) {
        Some(i) => hi + i,
        None => sched.iter().rposition(|r| is(&r)).unwrap_or(start),
    };
    sched[start..=end.max(start)].iter().filter(is).collect()
}

/// What the scheduler trace says ran on `cpu` over `[from, to]`, but the role's own `pids`.
fn ran_instead(run: &RunRecord, cpu: u32, pids: &[u32], window: [u64; 2]) -> String {
    let (ran, irq_ns) = super::trace::occupancy(&run.trace, cpu, window);
    let others: Vec<String> = ran
        .iter()
        .filter(|((_, pid), _)| *pid != 0 && !pids.contains(pid))
        .take(3)
        .map(|((comm, pid), ns)| format!("{comm} (pid {pid}) {}", ms(*ns as f64)))
        .collect();
    let idle: u64 = ran.iter().filter(|((_, pid), _)| *pid == 0).map(|(_, ns)| ns).sum();
    let others = if others.is_empty() { "no other task".to_owned() } else { others.join(", ") };
    format!(
        "ran instead on CPU {cpu} (sched trace): {others}; IRQ handlers {}; idle {}",
        ms(irq_ns as f64),
        ms(idle as f64)
    )
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use rotorloop_common::scenario::Scenario;

    /// Each stage's median over the run's fresh ticks (ns), in two passes of its own.
    pub(in crate::pipeline::incidents) fn stage_medians(
        run: &RunRecord,
        flags: &TickFlags,
    ) -> [f64; 5] {
        let mut m = StageMedians::default();
        for pass in 0..2 {
            (0..run.last).for_each(|k| m.see(run, k, flags.get(run, k)));
            if pass == 0 {
                m.second_pass();
            }
        }
        m.medians()
    }

    /// A lockstep run of 20 ticks in which the plant rejected one torque while it waited
    /// for tick 10, and whose plant took 0.5 ms to publish state 10 (its median: 1 µs).
    fn run_with_a_rejection(controllers_own: TorqueSample) -> RunRecord {
        let scenario = Scenario::load("paper-zero").expect("built-in");
        let dt = scenario.dt();
        let publish = |k: u64| 1_000_000 * (k + 1);
        let states = (0..20)
            .map(|k| {
                let mut s = StateSample::of(k, k as f64 * dt, &scenario.plant_init);
                s.publish_ns = publish(k);
                s.wake_ns = publish(k) - if k == 10 { 500_000 } else { 1_000 };
                s.torques_rejected = u64::from(k > 10);
                if k > 0 {
                    (s.effects, s.effect_ticks[0], s.effect_offsets_s[0]) = (1, k - 1, 1e-5);
                }
                s
            })
            .collect();
        let torques = (0..20)
            .map(|k| TorqueSample {
                tick: k,
                state_recv_ns: publish(k) + 2_000,
                publish_ns: publish(k) + 3_000,
                ..if k == 10 { controllers_own } else { TorqueSample::default() }
            })
            .collect();
        RunRecord::of(scenario, states, torques)
    }

    fn cause_at(run: &RunRecord, k: u64) -> Cause {
        let flags = ticks::flag(run, 0.25);
        let medians = stage_medians(run, &flags);
        let mut scan = ticks::WindowScan::default();
        let w = std::iter::from_fn(|| flags.next_window(run, &mut scan, super::super::GAP))
            .find(|w| w[0] <= k && k <= w[1])
            .expect("an incident at k");
        cause(run, &flags, &medians, w)
    }

    /// The searches that end early (an answer's effect ends where a newer one is in force;
    /// the next answer is remembered from the tick before) find what a scan of the next
    /// 10 000 ticks finds, on a plant history made by the plant's own rule: an answer is
    /// taken only if newer than every one taken before, late ones too, several per tick,
    /// stretches of safe mode (nothing in force) and of silence.
    #[test]
    fn the_searches_that_stop_early_find_what_a_scan_finds() {
        let scenario = Scenario::load("paper-zero").expect("built-in");
        let mut next = super::super::test_random(0x9e37_79b9_7f4a_7c15_u64);
        let n = 3000;
        let (mut newest, mut states, mut torques) = (NO_TICK, Vec::new(), Vec::new());
        let mut effects: Vec<(u64, f64)> = Vec::new();
        for k in 0..n {
            let mut s = StateSample::of(k, k as f64 * scenario.dt(), &scenario.plant_init);
            s.effects = effects.len() as u64;
            for (i, (tick, offset)) in effects.drain(..).enumerate() {
                (s.effect_ticks[i], s.effect_offsets_s[i]) = (tick, offset);
            }
            let safe = (k / 200) % 5 == 3;
            s.applied_torque_tick = if safe { NO_TICK } else { newest };
            states.push(s);
            let silent = (k / 300) % 4 == 2;
            if !silent && next(3) > 0 {
                torques.push(TorqueSample { tick: k, ..Default::default() });
            }
            // What takes effect in tick k: answers to ticks up to k, some of them late.
            for i in 0..next(4) {
                let source = k.saturating_sub(next(40));
                if newest == NO_TICK || source > newest {
                    newest = source;
                    effects.push((source, i as f64 * 1e-5));
                }
            }
        }
        let run = RunRecord::of(scenario, states, torques);
        let scan_effect = |k: u64| {
            (k..(k + 10_000).min(run.last)).find_map(|j| {
                let s = run.state(j + 1)?;
                let m = (s.effects as usize).min(s.effect_ticks.len());
                (0..m).find(|i| s.effect_ticks[*i] == k).map(|i| (j, s.effect_offsets_s[i]))
            })
        };
        let scan_answer =
            |k: u64| (k + 1..(k + 10_000).min(run.last + 1)).find_map(|j| run.torque(j));
        let (mut took, mut never) = (0, 0);
        for k in 0..n {
            let found = took_effect(&run, k);
            assert_eq!(found, scan_effect(k), "tick {k}");
            (took, never) = if found.is_some() { (took + 1, never) } else { (took, never + 1) };
            assert_eq!(run.next_answer(k).map(|t| t.tick), scan_answer(k).map(|t| t.tick), "{k}");
        }
        assert!(took > 100 && never > 100, "{took} answers took effect, {never} never did");
        for _ in 0..2000 {
            let k = next(n);
            assert_eq!(run.next_answer(k).map(|t| t.tick), scan_answer(k).map(|t| t.tick), "{k}");
        }
    }

    /// Issue 42: a torque for a tick the loop had not reached, from a same-user process,
    /// was reported as a "simulator stall" (the plant's slowest stage in the window).
    #[test]
    fn a_rejected_sample_is_named_after_the_rejection_never_a_stall() {
        let c = cause_at(&run_with_a_rejection(TorqueSample::default()), 10);
        assert_eq!((c.kind, c.role.as_str()), ("rejected samples", ANOTHER_PUBLISHER), "{c:?}");
        assert_eq!(c.stage, "torque rejected by the plant");
        assert!(c.evidence.contains("the controller's own torque of tick 10 was valid"), "{c:?}");
        // The controller's own answer was the bad one: it is named.
        let nan = TorqueSample { rotor_torque_nm: [f64::NAN, 0.0, 0.0], ..Default::default() };
        let c = cause_at(&run_with_a_rejection(nan), 10);
        assert_eq!((c.kind, c.role.as_str()), ("rejected samples", "controller"), "{c:?}");
        assert!(c.evidence.contains("torque.rotor_torque is not finite"), "{c:?}");
    }

    /// The bisection finds the same rows as a scan of every row (the form it replaced), on
    /// rows with repeated times, roles missing from stretches, and windows before, inside
    /// and after the rows.
    #[test]
    fn a_roles_rows_by_bisection_are_those_of_a_scan() {
        fn scan<'a>(sched: &'a [SchedRow], role: &str, [from, to]: [u64; 2]) -> Vec<&'a SchedRow> {
            let rows: Vec<&SchedRow> = sched.iter().filter(|r| r.role == role).collect();
            let Some(len) = rows.len().checked_sub(1) else { return Vec::new() };
            let first = rows.iter().rposition(|r| r.t_ns <= from).unwrap_or(0);
            let last = rows.iter().position(|r| r.t_ns >= to).unwrap_or(len);
            rows[first..=last.max(first)].to_vec()
        }
        let mut next = super::super::test_random(0x2545_f491_4f6c_dd1d_u64);
        let roles = ["plant", "controller", "monitor"];
        let mut t = 0;
        let sched: Vec<SchedRow> = (0..400)
            .map(|i| {
                t += next(3);
                let role = if (100..180).contains(&i) { "plant" } else { roles[next(3) as usize] };
                SchedRow {
                    t_ns: t,
                    role: role.into(),
                    pid: i,
                    state: 'R',
                    cpu: 0,
                    on_cpu_ns: 0,
                    wait_ns: 0,
                    steal_ns: 0,
                }
            })
            .collect();
        for _ in 0..2000 {
            let from = next(t + 40);
            let to = from + next(60);
            for role in roles.iter().chain(&["reference"]) {
                let (got, want) =
                    (role_rows(&sched, role, [from, to]), scan(&sched, role, [from, to]));
                let pids = |v: &[&SchedRow]| v.iter().map(|r| r.pid).collect::<Vec<_>>();
                assert_eq!(pids(&got), pids(&want), "{role} over [{from}, {to}]");
            }
        }
    }
}
