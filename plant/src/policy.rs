//! What the plant decides, apart from the dynamics and without IPC or a clock: which rotor
//! torque is in force over each part of each tick (delayed zero-order hold), when a tick
//! is a **miss**, when **safe mode** starts and ends, what a restart resumes, and what
//! goes into the state sample. The process shell ([`crate::process`]) feeds it the
//! samples that arrived and their receive times, and publishes what it returns; the
//! in-process simulator feeds the same [`DelayLine`] with its own torques.
//!
//! - [`TorqueHold`] is the acceptance and hold rule: a torque sample is **accepted** when
//!   it passes validation, is not a controller's skipped answer, and is newer than every
//!   torque accepted before (an older one would undo a newer command). Newer, but not
//!   beyond the tick the plant waits for (the newest state it has published): a torque
//!   for a tick the loop has not reached answers no state, and taken as the newest it
//!   would make every true torque after it "older" for the rest of the run. It is
//!   rejected (`future-tick`, [`rotorloop_common::wire::TickBound`]) and counted, never
//!   counted as received, and it changes nothing in force. A tick whose own
//!   torque did not arrive in time is a **miss** (a deadline miss of the loop), whatever
//!   else arrived. After `hold_ticks` consecutive ticks in which no torque was accepted,
//!   the plant enters **safe mode** (zero torque: the rotors coast, momentum is conserved)
//!   until one is. A late torque (one that arrives after its own tick) is applied when it
//!   arrives, not dropped: a real actuator takes the newest command it gets, and a loop
//!   whose every answer is late still controls, late. A rejected sample is counted; a
//!   skipped one is not a rejection.
//! - The actuator model ([`crate::actuator`]: the delayed zero-order hold and one tick's
//!   piecewise integration) is its own module: the in-process simulator uses it too.
//! - [`PlantTicker`] is one tick of the plant around them: the state sample of tick `k`
//!   (state, the torque in force at the end of the previous tick, the torques that took
//!   effect in it and when, its rotor work, the counters), then, once the wait for torque
//!   `k` has ended, the tick's pieces through the actuator limits (at the rotor rates at
//!   the start of each piece) with the scenario's disturbance.

use glam::DVec3;
use rotorloop_common::params::ActuatorLimits;
use rotorloop_common::role::count::SeqCounter;
use rotorloop_common::role::{UsageError, diverged};
use rotorloop_common::scenario::{Actuation, Scenario};
use rotorloop_common::wire::{
    FLAG_LAST, FLAG_REALTIME, FLAG_SAFE_MODE, FLAG_SATURATED, NO_TICK, Refusals, StateSample,
    TORQUE_SKIPPED, TorqueSample, WireFault,
};

use crate::actuator::{ActuationDelay, DelayLine, Effects, integrate_tick};
use crate::{Body, BodyInput};

/// How the wait for tick `k`'s torque ended, or what arrived during it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Answer {
    /// A valid computed torque for tick `k`, received at `recv_ns`.
    Fresh(TorqueSample, u64),
    /// A valid computed torque for an earlier tick, newer than the one in force, received
    /// at `recv_ns`: it takes effect, but it does not answer tick `k`.
    Late(TorqueSample, u64),
    /// The controller answered tick `k` with a skipped sample (no state or reference to
    /// control with): no torque comes for this tick.
    Skipped(TorqueSample),
    /// The sample answering tick `k` failed validation.
    Rejected(TorqueSample, WireFault),
    /// A sample for a tick beyond `k`, which the loop has not reached: rejected, and it
    /// does not answer tick `k` (nor has it a place in the flight record, which is by tick).
    Future(TorqueSample, WireFault),
}

impl Answer {
    /// Whether this answers tick `k` (ends the wait for it).
    pub fn answers_the_tick(&self) -> bool {
        !matches!(self, Answer::Late(..) | Answer::Future(..))
    }
}

/// What [`TorqueHold::settle`] decided for one tick (for the shell to log).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Settled {
    /// The tick's own torque arrived; `after_safe_mode` when it ended safe mode.
    Fresh {
        /// The plant was in safe mode until this torque.
        after_safe_mode: bool,
        /// A sample taken during the tick's wait was rejected (not the tick's answer: one
        /// for a tick not reached, say), for the first time in this plant's life.
        first_rejection: Option<(u64, WireFault)>,
    },
    /// The tick's own torque did not arrive in time.
    Miss {
        /// This miss started safe mode.
        entered_safe_mode: bool,
        /// A sample taken during the tick's wait (its answer, or another) was rejected,
        /// for the first time in this plant's life.
        first_rejection: Option<(u64, WireFault)>,
    },
}

impl Settled {
    /// What changed at tick `k`, for the log (state changes only; `None` on a plain tick).
    pub fn event(&self, k: u64, hold_ticks: u64) -> Option<String> {
        match *self {
            Settled::Fresh { after_safe_mode: true, .. } => {
                Some(format!("fresh torque at tick {k}; control resumed"))
            }
            Settled::Fresh { first_rejection: Some((tick, fault)), .. } => {
                Some(format!("rejected a torque for tick {tick}: {fault} (ignored; counted)"))
            }
            Settled::Miss { first_rejection: Some((tick, fault)), .. } => {
                Some(format!("rejected the torque of tick {tick}: {fault} (holding; counted)"))
            }
            Settled::Miss { entered_safe_mode: true, .. } => Some(format!(
                "no fresh torque for {hold_ticks} ticks at tick {k}: safe mode (zero torque, rotors coast)"
            )),
            _ => None,
        }
    }
}

/// The acceptance and hold rule (module docs): what is accepted, misses, safe mode, and
/// the counts the state sample carries.
#[derive(Debug, Clone, Copy)]
pub struct TorqueHold {
    hold_ticks: u64,
    actuation: Actuation,
    absurd_limit: f64,
    /// The newest torque tick accepted (never goes back, never beyond the plant's tick).
    newest: u64,
    /// A torque was accepted during the current tick's wait.
    accepted: bool,
    /// Consecutive ticks without an accepted torque.
    stale: u64,
    safe: bool,
    rejection_seen: bool,
    /// This plant's first rejection, taken during the current tick's wait (for the log).
    first_rejection: Option<(u64, WireFault)>,
    misses: u64,
    safe_ticks: u64,
    rejected: u64,
    /// The rejections by kind, continued across restarts from their own slot.
    refusals: Refusals,
    seq: SeqCounter,
}

impl TorqueHold {
    /// A hold with no torque yet, entering safe mode after `hold_ticks` consecutive ticks
    /// without one; torques beyond `absurd_limit` are rejected.
    pub fn new(hold_ticks: u64, actuation: Actuation, absurd_limit: f64) -> Self {
        Self {
            hold_ticks,
            actuation,
            absurd_limit,
            newest: NO_TICK,
            accepted: false,
            stale: 0,
            safe: false,
            rejection_seen: false,
            first_rejection: None,
            misses: 0,
            safe_ticks: 0,
            rejected: 0,
            refusals: Refusals::default(),
            seq: SeqCounter::default(),
        }
    }

    /// Continues from the last state sample a killed predecessor published: its
    /// counters, its safe mode, and the newest torque it had accepted. That is never beyond
    /// the state's own tick (the tick rule); a slot that says otherwise (not written by
    /// this rule) is taken as naming none, so it cannot silence the restart.
    pub fn resume(&mut self, s: &StateSample) {
        self.misses = s.misses;
        self.safe_ticks = s.safe_mode_ticks;
        self.rejected = s.torques_rejected;
        self.safe = s.flags & FLAG_SAFE_MODE != 0;
        // `NO_TICK` (none held: safe mode) is beyond every tick too.
        let held = Some(s.applied_torque_tick).filter(|t| *t <= s.tick);
        self.newest = held.unwrap_or(NO_TICK);
        self.seq = match held {
            None => SeqCounter::resume_unanchored(s.torques_received, s.torques_lost),
            Some(t) => SeqCounter::resume(s.torques_received, s.torques_lost, t),
        };
    }

    /// One torque sample taken while waiting for tick `k`, received at `recv_ns`: counted
    /// (and, if invalid, counted rejected). Returns what it means: the answer to tick `k`
    /// (fresh, skipped or rejected: each ends the wait, since the controller will not send
    /// another for this tick), a late torque that is accepted all the same, a rejected one
    /// for a tick beyond `k` (which ends nothing), or nothing (older than what is in
    /// force, or a skipped or rejected answer to an older tick).
    pub fn take(&mut self, t: &TorqueSample, k: u64, recv_ns: u64) -> Option<Answer> {
        // Tick `k`'s state is the newest the plant has published (the tick rule).
        if let Err(f) = t.check_tick(k) {
            // Not seen by the sequence counter: its tick would make every tick before it
            // a loss, and every true torque after it a repeat.
            self.reject(t.tick, f);
            return Some(Answer::Future(*t, f));
        }
        self.seq.see(t.tick);
        let fault = t.validate(self.absurd_limit).err();
        if let Some(f) = fault {
            self.reject(t.tick, f);
        }
        let newer = self.newest == NO_TICK || t.tick > self.newest;
        let usable = fault.is_none() && t.flags & TORQUE_SKIPPED == 0 && newer;
        if usable {
            self.newest = t.tick;
            self.accepted = true;
        }
        match fault {
            _ if t.tick != k => usable.then_some(Answer::Late(*t, recv_ns)),
            Some(f) => Some(Answer::Rejected(*t, f)),
            None if t.flags & TORQUE_SKIPPED != 0 => Some(Answer::Skipped(*t)),
            None if usable => Some(Answer::Fresh(*t, recv_ns)),
            None => None,
        }
    }

    /// Counts a rejected sample of tick `tick`, and keeps the first of this plant's life
    /// for the log.
    fn reject(&mut self, tick: u64, f: WireFault) {
        self.rejected += 1;
        self.refusals.count(tick, &f);
        // The kinds' slot outlives the state's count when the plant is killed between a
        // refusal and its next state: the total follows the newer of the two.
        self.refusals.total = self.refusals.total.max(self.rejected);
        if !std::mem::replace(&mut self.rejection_seen, true) {
            self.first_rejection = Some((tick, f));
        }
    }

    /// The wait for tick `k` ended with `answer` (`None`: nothing for `k` in time).
    pub fn settle(&mut self, answer: Option<Answer>) -> Settled {
        let accepted = std::mem::take(&mut self.accepted);
        let after_safe_mode = self.safe && accepted;
        if accepted {
            self.safe = false;
            self.stale = 0;
        }
        let first_rejection = self.first_rejection.take();
        if let Some(Answer::Fresh(..)) = answer {
            return Settled::Fresh { after_safe_mode, first_rejection };
        }
        self.misses += 1;
        self.stale += u64::from(!accepted);
        let entered_safe_mode = self.stale > self.hold_ticks && !self.safe;
        self.safe |= entered_safe_mode;
        self.safe_ticks += u64::from(self.safe);
        Settled::Miss { entered_safe_mode, first_rejection }
    }

    /// The input a torque sample commands.
    pub fn input_of(&self, t: &TorqueSample) -> BodyInput {
        let (u, tau) = (t.rotor_torque_nm, t.body_torque_nm);
        BodyInput::of(self.actuation, DVec3::from_array(u), DVec3::from_array(tau))
    }

    /// Whether the plant is in safe mode.
    pub fn safe_mode(&self) -> bool {
        self.safe
    }

    /// Ticks whose own torque did not arrive in time, over the run.
    pub fn misses(&self) -> u64 {
        self.misses
    }

    /// Ticks spent in safe mode, over the run.
    pub fn safe_mode_ticks(&self) -> u64 {
        self.safe_ticks
    }

    /// Torque samples rejected by validation, over the run.
    pub fn rejected(&self) -> u64 {
        self.rejected
    }

    /// The rejections by kind, over the run.
    pub fn refusals(&self) -> Refusals {
        self.refusals
    }

    /// Continues the count by kind a killed predecessor kept in its slot.
    pub fn resume_refusals(&mut self, r: Refusals) {
        self.refusals = r;
    }

    /// Torque samples received and lost.
    pub fn seq(&self) -> SeqCounter {
        self.seq
    }

    /// Writes the counters into `s`.
    fn fill(&self, s: &mut StateSample) {
        s.misses = self.misses;
        s.safe_mode_ticks = self.safe_ticks;
        s.torques_received = self.seq.received;
        s.torques_lost = self.seq.lost;
        s.torques_rejected = self.rejected;
    }
}

/// One tick of the plant around the hold and the delay line (module docs).
#[derive(Debug, Clone)]
pub struct PlantTicker {
    body: Body,
    /// The acceptance and hold rule.
    pub hold: TorqueHold,
    line: DelayLine,
    limits: ActuatorLimits,
    disturbance: DVec3,
    dt: f64,
    ticks: u64,
    realtime: bool,
    first: u64,
    /// What the motors delivered at the end of the previous tick (after their limits).
    applied: BodyInput,
    work: f64,
    effects: Effects,
    saturated: bool,
    saturated_ticks: u64,
}

impl PlantTicker {
    /// The plant of `scenario` at tick 0, with the hold rule's `hold_ticks` and the delay
    /// rule `delay`.
    pub fn new(
        scenario: &Scenario,
        hold_ticks: u64,
        realtime: bool,
        delay: ActuationDelay,
    ) -> Self {
        let actuation = scenario.actuation();
        let limits = scenario.limits_for(actuation);
        let absurd = TorqueSample::absurd_limit(limits.rotor_torque);
        Self {
            body: Body::new(scenario.plant_params(actuation), scenario.plant_init),
            hold: TorqueHold::new(hold_ticks, actuation, absurd),
            line: DelayLine::new(delay, scenario.dt()),
            limits,
            disturbance: scenario.disturbance,
            dt: scenario.dt(),
            ticks: scenario.ticks(),
            realtime,
            first: 0,
            applied: BodyInput::default(),
            work: 0.0,
            effects: Effects::default(),
            saturated: false,
            saturated_ticks: 0,
        }
    }

    /// Whether `s` (a resume slot's content) is of an unfinished run of this scenario, so
    /// a restart continues from it.
    pub fn can_resume(&self, s: &StateSample) -> bool {
        s.flags & FLAG_LAST == 0 && s.tick <= self.ticks
    }

    /// Continues, bit for bit, from the last state a killed predecessor published: the
    /// integrator's own state, the torque in force and every counter, at the same tick.
    /// (Torques it had queued but not yet applied are gone with it: with a delay longer
    /// than a tick, the controller's answers to the ticks before the restart are lost.)
    pub fn resume(&mut self, s: &StateSample) {
        let x = s.body_state();
        self.body = Body::from_internal(
            *self.body.params(),
            x.r,
            DVec3::from_array(s.internal_h),
            DVec3::from_array(s.internal_p),
            x.theta,
        );
        self.first = s.tick;
        self.hold.resume(s);
        self.applied = BodyInput {
            rotor_torque: DVec3::from_array(s.applied_rotor_torque_nm),
            body_torque: DVec3::from_array(s.applied_body_torque_nm),
        };
        self.line.resume(self.applied, s.applied_torque_tick, s.applied_torque_recv_ns);
        self.work = s.rotor_work_j;
        self.effects =
            Effects { count: s.effects, ticks: s.effect_ticks, offsets_s: s.effect_offsets_s };
        self.saturated_ticks = s.saturated_ticks;
        self.saturated = s.flags & FLAG_SATURATED != 0;
    }

    /// The first tick to publish (0, or the tick a restart resumes at).
    pub fn first(&self) -> u64 {
        self.first
    }

    /// The run's last tick.
    pub fn last(&self) -> u64 {
        self.ticks
    }

    /// The state sample of tick `k` (the plant has done `k` steps): woken at `wake_ns` for
    /// the grid time `deadline_ns` (0 in lockstep). `publish_ns` is left for the send.
    pub fn state_sample(&self, k: u64, deadline_ns: u64, wake_ns: u64) -> StateSample {
        let mut s = StateSample::of(k, k as f64 * self.dt, &self.body.state());
        let (_, h, p, _) = self.body.internal();
        s.internal_h = h.to_array();
        s.internal_p = p.to_array();
        s.applied_rotor_torque_nm = self.applied.rotor_torque.to_array();
        s.applied_body_torque_nm = self.applied.body_torque.to_array();
        (_, s.applied_torque_tick, s.applied_torque_recv_ns) = self.line.in_force();
        s.deadline_ns = deadline_ns;
        s.wake_ns = wake_ns;
        s.saturated_ticks = self.saturated_ticks;
        s.rotor_work_j = self.work;
        (s.effects, s.effect_ticks, s.effect_offsets_s) =
            (self.effects.count, self.effects.ticks, self.effects.offsets_s);
        self.hold.fill(&mut s);
        let flag = |on: bool, f: u64| if on { f } else { 0 };
        s.flags = flag(k == self.ticks, FLAG_LAST)
            | flag(self.realtime, FLAG_REALTIME)
            | flag(self.hold.safe_mode(), FLAG_SAFE_MODE)
            | flag(self.saturated, FLAG_SATURATED);
        s
    }

    /// One torque sample taken while waiting for tick `k` (which started at `tick_start_ns`
    /// of the monotonic clock in real time; 0 in lockstep), received at `recv_ns`: the
    /// hold rule's verdict, and an accepted torque goes into the delay line.
    pub fn take(
        &mut self,
        t: &TorqueSample,
        k: u64,
        tick_start_ns: u64,
        recv_ns: u64,
    ) -> Option<Answer> {
        let answer = self.hold.take(t, k, recv_ns);
        if let Some(Answer::Fresh(t, recv) | Answer::Late(t, recv)) = answer {
            let arrived_s = if tick_start_ns == 0 {
                0.0
            } else {
                recv.saturating_sub(tick_start_ns) as f64 / 1e9
            };
            let input = self.hold.input_of(&t);
            self.line.arrive(t.tick, input, k, arrived_s, recv, None);
        }
        answer
    }

    /// The wait for tick `k` ended with `answer`: the hold rule settles it; entering safe
    /// mode clears the delay line (zero torque from the start of the tick).
    pub fn settle(&mut self, answer: Option<Answer>) -> Settled {
        let settled = self.hold.settle(answer);
        if self.hold.safe_mode() {
            self.line.clear();
        }
        settled
    }

    /// Steps from tick `k` to `k + 1`, piecewise (module docs), each piece through the
    /// actuator limits at the rotor rates at its start. The last tick does not step. A
    /// state that stops being finite is an error: nothing non-finite is ever published.
    pub fn step(&mut self, k: u64) -> Result<(), UsageError> {
        if k >= self.ticks {
            return Ok(());
        }
        let t = integrate_tick(&mut self.body, &mut self.line, k, &self.limits, self.disturbance);
        (self.work, self.saturated, self.applied, self.effects) =
            (t.work, t.saturated, t.applied, t.effects);
        self.saturated_ticks += u64::from(t.saturated);
        if self.body.is_finite() { Ok(()) } else { Err(diverged(k + 1, (k + 1) as f64 * self.dt)) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMIT: f64 = 1e3;

    fn torque(tick: u64, u: f64) -> TorqueSample {
        TorqueSample { tick, rotor_torque_nm: [u, 0.0, 0.0], ..Default::default() }
    }

    fn hold(hold_ticks: u64) -> TorqueHold {
        TorqueHold::new(hold_ticks, Actuation::Internal, LIMIT)
    }

    /// Feeds `samples` while waiting for tick `k`, then settles.
    fn tick(h: &mut TorqueHold, k: u64, samples: &[TorqueSample]) -> Settled {
        let mut answer = None;
        for (i, t) in samples.iter().enumerate() {
            if let Some(a) = h.take(t, k, 1000 * k + i as u64).filter(Answer::answers_the_tick) {
                answer = Some(a);
            }
        }
        h.settle(answer)
    }

    fn paper() -> Scenario {
        Scenario::load("paper-sinusoid").expect("built-in")
    }

    #[test]
    fn a_torque_for_this_tick_answers_it() {
        let mut h = hold(50);
        let fresh = Settled::Fresh { after_safe_mode: false, first_rejection: None };
        assert_eq!(tick(&mut h, 0, &[torque(0, 2.0)]), fresh);
        assert_eq!(h.misses(), 0);
        assert!(matches!(tick(&mut h, 1, &[]), Settled::Miss { entered_safe_mode: false, .. }));
        assert_eq!(h.misses(), 1);
    }

    #[test]
    fn a_late_torque_is_accepted_and_applied_when_it_arrives_but_its_tick_was_a_miss() {
        let mut h = hold(2);
        tick(&mut h, 0, &[torque(0, 2.0)]);
        // Torque 1 arrives during tick 2's wait: a miss for ticks 1 and 2, but it is newer
        // than torque 0, so it is taken (and keeps the plant out of safe mode).
        assert!(matches!(tick(&mut h, 1, &[]), Settled::Miss { .. }));
        assert_eq!(h.take(&torque(1, 3.0), 2, 7), Some(Answer::Late(torque(1, 3.0), 7)));
        assert!(matches!(h.settle(None), Settled::Miss { entered_safe_mode: false, .. }));
        for k in 3..6 {
            assert_eq!(
                h.take(&torque(k - 1, 3.0), k, 7).map(|a| a.answers_the_tick()),
                Some(false)
            );
            h.settle(None);
        }
        assert!(!h.safe_mode(), "a controller whose every answer is late still controls");
        assert_eq!(h.misses(), 5);
    }

    #[test]
    fn a_torque_for_an_older_tick_never_replaces_a_newer_one() {
        let mut h = hold(50);
        tick(&mut h, 5, &[torque(5, 1.0)]);
        assert_eq!(h.take(&torque(4, 9.0), 6, 0), None, "older than torque 5");
        assert_eq!(h.seq().repeated, 1, "the older tick counts as a repeat, not a reception");
    }

    #[test]
    fn safe_mode_starts_after_hold_ticks_without_a_torque_and_ends_with_the_next() {
        let scenario = paper();
        let mut p = PlantTicker::new(&scenario, 3, true, ActuationDelay::Instant);
        let feed = |p: &mut PlantTicker, k: u64, t: Option<TorqueSample>| {
            let a = t.and_then(|t| p.take(&t, k, 0, 0));
            let s = p.settle(a);
            p.step(k).expect("finite");
            s
        };
        feed(&mut p, 0, Some(torque(0, 2.0)));
        for k in 1..=3 {
            assert!(matches!(
                feed(&mut p, k, None),
                Settled::Miss { entered_safe_mode: false, .. }
            ));
            assert_eq!(p.line.in_force().0.rotor_torque.x, 2.0, "held during miss {k}");
        }
        assert!(matches!(feed(&mut p, 4, None), Settled::Miss { entered_safe_mode: true, .. }));
        assert_eq!(p.line.in_force(), (BodyInput::default(), NO_TICK, 0), "zero torque");
        assert_eq!(p.state_sample(5, 0, 0).flags & FLAG_SAFE_MODE, FLAG_SAFE_MODE);
        feed(&mut p, 5, None);
        assert_eq!(p.hold.safe_mode_ticks(), 2);
        let back = Settled::Fresh { after_safe_mode: true, first_rejection: None };
        assert_eq!(feed(&mut p, 6, Some(torque(6, 4.0))), back);
        assert!(!p.hold.safe_mode());
        assert_eq!(p.line.in_force().0.rotor_torque.x, 4.0);
    }

    #[test]
    fn a_rejected_torque_is_counted_and_held_like_a_missing_one() {
        let mut h = hold(50);
        tick(&mut h, 0, &[torque(0, 2.0)]);
        match tick(&mut h, 1, &[torque(1, f64::NAN)]) {
            Settled::Miss { first_rejection: Some((1, f)), entered_safe_mode: false } => {
                assert_eq!(f.kind(), "non-finite");
            }
            other => panic!("{other:?}"),
        }
        assert_eq!((h.rejected(), h.misses()), (1, 1));
        // Absurd magnitude: rejected too, and only the first rejection is reported.
        let huge = torque(2, 10.0 * LIMIT);
        assert!(matches!(tick(&mut h, 2, &[huge]), Settled::Miss { first_rejection: None, .. }));
        assert_eq!((h.rejected(), h.misses()), (2, 2));
    }

    /// Issue 42: one valid zero torque for tick 10¹² was taken as the newest, and every
    /// true torque after it was "older": safe mode for the rest of the run, uncounted.
    #[test]
    fn a_torque_for_a_tick_not_reached_is_rejected_counted_and_never_silences_control() {
        let mut h = hold(3);
        tick(&mut h, 0, &[torque(0, 2.0)]);
        let far = torque(1_000_000_000_000, 0.0);
        assert!(
            matches!(h.take(&far, 1, 0), Some(a @ Answer::Future(..)) if !a.answers_the_tick())
        );
        match h.settle(None) {
            Settled::Miss { first_rejection: Some((1_000_000_000_000, f)), .. } => {
                assert_eq!(f.kind(), "future-tick");
            }
            other => panic!("{other:?}"),
        }
        // Before or after the tick's own torque, and one tick ahead as much as 10¹².
        let ahead = |k: u64| torque(k + 1, 5.0);
        for k in 2..100 {
            let samples =
                if k % 2 == 0 { [far, torque(k, 1.0)] } else { [torque(k, 1.0), ahead(k)] };
            let settled = tick(&mut h, k, &samples);
            assert!(matches!(settled, Settled::Fresh { after_safe_mode: false, .. }), "{k}");
        }
        assert!(!h.safe_mode());
        assert_eq!((h.rejected(), h.misses(), h.safe_mode_ticks()), (99, 1, 0));
        let seq = h.seq();
        assert_eq!((seq.received, seq.lost), (99, 1), "ticks 0 and 2..=99; tick 1 lost");
        let t = torque(7, 0.0);
        let f = t.check_tick(6).expect_err("future");
        let event = Settled::Fresh { after_safe_mode: false, first_rejection: Some((7, f)) };
        let line = event.event(6, 3).expect("logged");
        assert!(line.contains("torque.tick is 7") && line.contains("ignored"), "{line}");
    }

    #[test]
    fn a_torque_for_a_tick_not_reached_never_displaces_the_torque_in_force() {
        let scenario = paper();
        let mut p = PlantTicker::new(&scenario, 3, true, ActuationDelay::Instant);
        let mut feed = |k: u64, samples: &[TorqueSample]| {
            let mut answer = None;
            for t in samples {
                let a = p.take(t, k, 0, 0);
                answer = a.filter(Answer::answers_the_tick).or(answer);
            }
            p.settle(answer);
            p.step(k).expect("finite");
            let (input, tick, _) = p.line.in_force();
            (input.rotor_torque.x, tick)
        };
        assert_eq!(feed(0, &[torque(0, 2.0)]), (2.0, 0));
        assert_eq!(feed(1, &[torque(5, 9.0), torque(1, 3.0)]), (3.0, 1), "taken after it");
        assert_eq!(feed(2, &[torque(1_000_000_000_000, 0.0)]), (3.0, 1), "held, not replaced");
        assert_eq!(feed(3, &[torque(3, 4.0)]), (4.0, 3), "control goes on");
    }

    #[test]
    fn a_restart_never_resumes_a_newest_torque_beyond_its_own_tick() {
        let scenario = paper();
        let p = PlantTicker::new(&scenario, 3, true, ActuationDelay::Instant);
        let mut slot = p.state_sample(10, 0, 0);
        slot.applied_torque_tick = 1_000_000_000_000;
        let mut h = hold(3);
        h.resume(&slot);
        assert!(matches!(tick(&mut h, 10, &[torque(10, 1.0)]), Settled::Fresh { .. }));
    }

    #[test]
    fn a_skipped_answer_is_a_miss_but_not_a_rejection() {
        let mut h = hold(50);
        tick(&mut h, 0, &[torque(0, 2.0)]);
        let skipped = TorqueSample { flags: TORQUE_SKIPPED, ..torque(1, 0.0) };
        assert_eq!(h.take(&skipped, 1, 7), Some(Answer::Skipped(skipped)));
        let settled = h.settle(Some(Answer::Skipped(skipped)));
        assert!(matches!(settled, Settled::Miss { first_rejection: None, .. }));
        assert_eq!((h.rejected(), h.misses()), (0, 1));
    }

    #[test]
    fn external_actuation_commands_the_body_torque() {
        let h = TorqueHold::new(50, Actuation::External, LIMIT);
        let t = TorqueSample { body_torque_nm: [0.0, 5.0, 0.0], ..torque(0, 3.0) };
        assert_eq!(
            h.input_of(&t),
            BodyInput { rotor_torque: DVec3::ZERO, body_torque: DVec3::new(0.0, 5.0, 0.0) }
        );
    }

    #[test]
    fn zero_delay_steps_exactly_as_the_plain_zero_order_hold() {
        let scenario = paper();
        let mut p = PlantTicker::new(&scenario, 50, false, ActuationDelay::Instant);
        let mut body = Body::new(scenario.plant_params(scenario.actuation()), scenario.plant_init);
        for k in 0..50 {
            let t = torque(k, (k as f64 * 0.37).sin());
            let a = p.take(&t, k, 0, 0);
            p.settle(a);
            p.step(k).expect("finite");
            let x = body.state();
            let u = DVec3::from_array(t.rotor_torque_nm);
            body.step(BodyInput { rotor_torque: u, body_torque: DVec3::ZERO }, scenario.dt());
            let s = p.state_sample(k + 1, 0, 0);
            assert_eq!(s.body_state(), body.state(), "tick {k}: bit for bit");
            assert_eq!(s.rotor_work_j, 0.0 + u.dot(body.state().theta - x.theta));
        }
    }

    #[test]
    fn a_restart_resumes_the_hold_its_predecessor_published() {
        let scenario = paper();
        let mut a = PlantTicker::new(&scenario, 2, true, ActuationDelay::Instant);
        let run = |p: &mut PlantTicker, k: u64, t: Option<TorqueSample>| {
            let ans = t.and_then(|t| p.take(&t, k, 0, 0));
            p.settle(ans);
            p.step(k).expect("finite");
        };
        for k in 0..10 {
            run(&mut a, k, (k < 4).then(|| torque(k, 0.5 + k as f64)));
        }
        // The predecessor dies after publishing tick 10 (in safe mode since tick 6).
        let last = a.state_sample(10, 0, 0);
        assert_ne!(last.flags & FLAG_SAFE_MODE, 0);
        let mut b = PlantTicker::new(&scenario, 2, true, ActuationDelay::Instant);
        assert!(b.can_resume(&last));
        b.resume(&last);
        assert_eq!(b.first(), 10);
        assert_eq!(
            format!("{:?}", b.state_sample(10, 0, 0)),
            format!("{last:?}"),
            "the same state again"
        );
        for k in 10..15 {
            run(&mut a, k, Some(torque(k, 0.1)));
            run(&mut b, k, Some(torque(k, 0.1)));
        }
        let (sa, sb) = (a.state_sample(15, 0, 0), b.state_sample(15, 0, 0));
        // One counter cannot continue exactly: resumed in safe mode, the sample names no
        // held torque tick, so the restart does not know the last torque tick seen and
        // cannot count the gap before the next one as lost (the report's per-subscriber
        // losses come from the controller's published count instead).
        assert_eq!((sa.torques_lost, sb.torques_lost), (6, 0));
        let sb = StateSample { torques_lost: sa.torques_lost, ..sb };
        assert_eq!(format!("{sa:?}"), format!("{sb:?}"), "the physics and the hold continue");
        let finished = StateSample { flags: FLAG_LAST, ..last };
        assert!(!b.can_resume(&finished), "a finished run is not resumed");
    }
}
