//! What the plant decides, apart from the dynamics and without IPC or a clock: which rotor
//! torque is in force over each tick (zero-order hold), when a tick is a **miss**, when
//! **safe mode** starts and ends, what a restart resumes, and what goes into the state
//! sample. The process shell ([`crate::process`]) feeds it the samples that arrived and
//! their receive times, and publishes what it returns.
//!
//! - [`TorqueHold`] is the hold rule: a torque sample answering tick `k` that passes
//!   validation and is not a controller's skipped answer becomes the torque in force from
//!   this tick on. Anything else (late, missing, rejected, skipped) is a miss: the last
//!   good torque stays in force; after `hold_ticks` consecutive misses the plant enters
//!   safe mode (zero torque: the rotors coast, momentum is conserved) until a fresh
//!   torque arrives. A rejected sample is counted; a skipped one is not a rejection.
//! - [`PlantTicker`] is one tick of the plant around the hold: it writes the state
//!   sample of tick `k` (state, the torque applied over the previous tick and the counters),
//!   then, once the wait for torque `k` has ended, applies the actuator limits at the
//!   published rotor rates and steps the body (with the scenario's disturbance).

use glam::DVec3;
use rotorloop_common::role::{SeqCounter, UsageError, diverged};
use rotorloop_common::wire::{
    FLAG_LAST, FLAG_REALTIME, FLAG_SAFE_MODE, FLAG_SATURATED, NO_TICK, StateSample, TORQUE_SKIPPED,
    TorqueSample, WireFault,
};
use rotorloop_common::{Actuation, ActuatorLimits, Scenario};

use crate::{Body, BodyInput};

/// How the wait for tick `k`'s torque ended, as far as the hold rule is concerned.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Answer {
    /// A valid computed torque for tick `k`, received at `recv_ns`.
    Fresh(TorqueSample, u64),
    /// The controller answered tick `k` with a skipped sample (no state or reference to
    /// control with): no torque comes for this tick.
    Skipped(TorqueSample),
    /// The sample answering tick `k` failed validation.
    Rejected(TorqueSample, WireFault),
}

/// What [`TorqueHold::settle`] decided for one tick (for the shell to log).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Settled {
    /// A fresh torque is in force; `after_safe_mode` when it ended safe mode.
    Fresh {
        /// The plant was in safe mode until this torque.
        after_safe_mode: bool,
    },
    /// No fresh torque: the previous one (or zero, in safe mode) stays in force.
    Miss {
        /// This miss started safe mode.
        entered_safe_mode: bool,
        /// The tick's answer was rejected, for the first time in this plant's life.
        first_rejection: Option<(u64, WireFault)>,
    },
}

impl Settled {
    /// What changed at tick `k`, for the log (state changes only; `None` on a plain tick).
    pub fn event(&self, k: u64, hold_ticks: u64) -> Option<String> {
        match *self {
            Settled::Fresh { after_safe_mode: true } => {
                Some(format!("fresh torque at tick {k}; control resumed"))
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

/// The hold rule (module docs): the torque in force, misses, safe mode, and the counts the
/// state sample carries.
#[derive(Debug, Clone, Copy)]
pub struct TorqueHold {
    hold_ticks: u64,
    actuation: Actuation,
    absurd_limit: f64,
    held: BodyInput,
    held_tick: u64,
    held_recv_ns: u64,
    /// Consecutive ticks without a fresh torque.
    stale: u64,
    safe: bool,
    rejection_seen: bool,
    misses: u64,
    safe_ticks: u64,
    rejected: u64,
    seq: SeqCounter,
}

impl TorqueHold {
    /// A hold with no torque yet (zero in force), entering safe mode after `hold_ticks`
    /// consecutive misses; torques beyond `absurd_limit` are rejected.
    pub fn new(hold_ticks: u64, actuation: Actuation, absurd_limit: f64) -> Self {
        Self {
            hold_ticks,
            actuation,
            absurd_limit,
            held: BodyInput::default(),
            held_tick: NO_TICK,
            held_recv_ns: 0,
            stale: 0,
            safe: false,
            rejection_seen: false,
            misses: 0,
            safe_ticks: 0,
            rejected: 0,
            seq: SeqCounter::default(),
        }
    }

    /// Continues from the last state sample a killed predecessor published: the torque it
    /// held, its counters and its safe mode.
    pub fn resume(&mut self, s: &StateSample) {
        self.held = BodyInput {
            rotor_torque: DVec3::from_array(s.applied_rotor_torque_nm),
            body_torque: DVec3::from_array(s.applied_body_torque_nm),
        };
        self.held_tick = s.applied_torque_tick;
        self.held_recv_ns = s.applied_torque_recv_ns;
        self.misses = s.misses;
        self.safe_ticks = s.safe_mode_ticks;
        self.rejected = s.torques_rejected;
        self.safe = s.flags & FLAG_SAFE_MODE != 0;
        self.seq = match s.applied_torque_tick {
            NO_TICK => SeqCounter::resume_unanchored(s.torques_received, s.torques_lost),
            t => SeqCounter::resume(s.torques_received, s.torques_lost, t),
        };
    }

    /// One torque sample taken while waiting for tick `k`, received at `recv_ns`: counted
    /// (and, if invalid, counted rejected). Returns the answer it gives tick `k`, if it is
    /// for tick `k`; a rejected or skipped answer ends the wait too, since the controller
    /// will not send another for this tick.
    pub fn take(&mut self, t: &TorqueSample, k: u64, recv_ns: u64) -> Option<Answer> {
        self.seq.see(t.tick);
        let fault = t.validate(self.absurd_limit).err();
        if fault.is_some() {
            self.rejected += 1;
        }
        (t.tick == k).then_some(match fault {
            Some(f) => Answer::Rejected(*t, f),
            None if t.flags & TORQUE_SKIPPED != 0 => Answer::Skipped(*t),
            None => Answer::Fresh(*t, recv_ns),
        })
    }

    /// The wait for tick `k` ended with `answer` (`None`: nothing for `k` in time).
    pub fn settle(&mut self, answer: Option<Answer>) -> Settled {
        if let Some(Answer::Fresh(t, recv_ns)) = answer {
            let after_safe_mode = self.safe;
            self.safe = false;
            self.stale = 0;
            self.held = self.input_of(&t);
            self.held_tick = t.tick;
            self.held_recv_ns = recv_ns;
            return Settled::Fresh { after_safe_mode };
        }
        let first_rejection = match answer {
            Some(Answer::Rejected(t, f)) if !self.rejection_seen => {
                self.rejection_seen = true;
                Some((t.tick, f))
            }
            _ => None,
        };
        self.misses += 1;
        self.stale += 1;
        let entered_safe_mode = self.stale > self.hold_ticks && !self.safe;
        self.safe |= entered_safe_mode;
        if self.safe {
            self.safe_ticks += 1;
            self.held = BodyInput::default();
            self.held_tick = NO_TICK;
        }
        Settled::Miss { entered_safe_mode, first_rejection }
    }

    /// The torque in force (what the motors are commanded, before their limits).
    pub fn in_force(&self) -> BodyInput {
        self.held
    }

    /// Whether the plant is in safe mode.
    pub fn safe_mode(&self) -> bool {
        self.safe
    }

    /// Ticks without a fresh torque in time, over the run.
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

    /// Torque samples received and lost.
    pub fn seq(&self) -> SeqCounter {
        self.seq
    }

    fn input_of(&self, t: &TorqueSample) -> BodyInput {
        match self.actuation {
            Actuation::Internal => BodyInput {
                rotor_torque: DVec3::from_array(t.rotor_torque_nm),
                body_torque: DVec3::ZERO,
            },
            Actuation::External => BodyInput {
                rotor_torque: DVec3::ZERO,
                body_torque: DVec3::from_array(t.body_torque_nm),
            },
        }
    }

    /// Writes the held torque's tick and receive time and the counters into `s`.
    fn fill(&self, s: &mut StateSample) {
        s.applied_torque_tick = self.held_tick;
        s.applied_torque_recv_ns = self.held_recv_ns;
        s.misses = self.misses;
        s.safe_mode_ticks = self.safe_ticks;
        s.torques_received = self.seq.received;
        s.torques_lost = self.seq.lost;
        s.torques_rejected = self.rejected;
    }
}

/// One tick of the plant around the hold rule (module docs).
#[derive(Debug, Clone, Copy)]
pub struct PlantTicker {
    body: Body,
    /// The hold rule.
    pub hold: TorqueHold,
    limits: ActuatorLimits,
    disturbance: DVec3,
    dt: f64,
    ticks: u64,
    realtime: bool,
    first: u64,
    /// What the motors delivered over the previous tick (after their limits).
    applied: BodyInput,
    saturated: bool,
    saturated_ticks: u64,
}

impl PlantTicker {
    /// The plant of `scenario` at tick 0, with the hold rule's `hold_ticks`.
    pub fn new(scenario: &Scenario, hold_ticks: u64, realtime: bool) -> Self {
        let actuation = scenario.actuation();
        let limits = scenario.limits_for(actuation);
        Self {
            body: Body::new(scenario.plant_params(actuation), scenario.plant_init),
            hold: TorqueHold::new(
                hold_ticks,
                actuation,
                TorqueSample::absurd_limit(limits.rotor_torque),
            ),
            limits,
            disturbance: scenario.disturbance,
            dt: scenario.dt(),
            ticks: scenario.ticks(),
            realtime,
            first: 0,
            applied: BodyInput::default(),
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
        self.applied = self.hold.in_force();
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
        s.deadline_ns = deadline_ns;
        s.wake_ns = wake_ns;
        s.saturated_ticks = self.saturated_ticks;
        self.hold.fill(&mut s);
        let flag = |on: bool, f: u64| if on { f } else { 0 };
        s.flags = flag(k == self.ticks, FLAG_LAST)
            | flag(self.realtime, FLAG_REALTIME)
            | flag(self.hold.safe_mode(), FLAG_SAFE_MODE)
            | flag(self.saturated, FLAG_SATURATED);
        s
    }

    /// Steps from tick `k` to `k + 1` with the torque in force, through the actuator
    /// limits at the rotor rates of tick `k`'s state (the body has not moved since it was
    /// published). The last tick does not step. A state that stops being finite is an
    /// error: nothing non-finite is ever published.
    pub fn step(&mut self, k: u64) -> Result<(), UsageError> {
        if k >= self.ticks {
            return Ok(());
        }
        let held = self.hold.in_force();
        let (u, sat) = self.limits.apply(held.rotor_torque, self.body.state().omega_r);
        self.saturated = sat;
        self.saturated_ticks += u64::from(sat);
        self.applied = BodyInput { rotor_torque: u, body_torque: held.body_torque };
        self.body.step(
            BodyInput { rotor_torque: u, body_torque: held.body_torque + self.disturbance },
            self.dt,
        );
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
            if let Some(a) = h.take(t, k, 1000 * k + i as u64) {
                answer = Some(a);
            }
        }
        h.settle(answer)
    }

    #[test]
    fn no_torque_is_in_force_before_the_first_arrives() {
        let h = hold(50);
        assert_eq!(h.in_force(), BodyInput::default());
        assert_eq!(h.held_tick, NO_TICK);
    }

    #[test]
    fn a_torque_for_this_tick_is_in_force_from_this_tick() {
        let mut h = hold(50);
        assert_eq!(tick(&mut h, 0, &[torque(0, 2.0)]), Settled::Fresh { after_safe_mode: false });
        assert_eq!(h.in_force().rotor_torque.x, 2.0);
        assert_eq!((h.held_tick, h.held_recv_ns, h.misses()), (0, 0, 0));
    }

    #[test]
    fn a_late_torque_is_a_miss_and_the_previous_one_stays_in_force() {
        let mut h = hold(50);
        tick(&mut h, 0, &[torque(0, 2.0)]);
        // Nothing for tick 1 in time: miss, torque 0 held.
        assert!(matches!(tick(&mut h, 1, &[]), Settled::Miss { entered_safe_mode: false, .. }));
        assert_eq!((h.in_force().rotor_torque.x, h.held_tick, h.misses()), (2.0, 0, 1));
        // Torque 1 arrives during tick 2's wait: counted, but it answers tick 1, not 2.
        assert!(matches!(tick(&mut h, 2, &[torque(1, 3.0)]), Settled::Miss { .. }));
        assert_eq!((h.in_force().rotor_torque.x, h.misses(), h.seq().received), (2.0, 2, 2));
    }

    #[test]
    fn a_torque_for_an_older_tick_never_replaces_the_one_in_force() {
        let mut h = hold(50);
        tick(&mut h, 5, &[torque(5, 1.0)]);
        assert!(matches!(
            tick(&mut h, 6, &[torque(4, 9.0), torque(6, 2.0)]),
            Settled::Fresh { .. }
        ));
        assert_eq!((h.in_force().rotor_torque.x, h.held_tick), (2.0, 6));
        assert_eq!(h.seq().repeated, 1, "the older tick counts as a repeat, not a reception");
    }

    #[test]
    fn safe_mode_starts_after_hold_ticks_misses_and_ends_with_a_fresh_torque() {
        let mut h = hold(3);
        tick(&mut h, 0, &[torque(0, 2.0)]);
        for k in 1..=3 {
            assert!(matches!(tick(&mut h, k, &[]), Settled::Miss { entered_safe_mode: false, .. }));
            assert_eq!(h.in_force().rotor_torque.x, 2.0, "held during the first {k} misses");
        }
        assert!(matches!(tick(&mut h, 4, &[]), Settled::Miss { entered_safe_mode: true, .. }));
        assert!(h.safe_mode());
        assert_eq!(
            (h.in_force(), h.held_tick, h.safe_mode_ticks()),
            (BodyInput::default(), NO_TICK, 1)
        );
        assert!(matches!(tick(&mut h, 5, &[]), Settled::Miss { entered_safe_mode: false, .. }));
        assert_eq!(h.safe_mode_ticks(), 2);
        assert_eq!(tick(&mut h, 6, &[torque(6, 4.0)]), Settled::Fresh { after_safe_mode: true });
        assert!(!h.safe_mode());
        assert_eq!((h.in_force().rotor_torque.x, h.misses(), h.safe_mode_ticks()), (4.0, 5, 2));
    }

    #[test]
    fn a_rejected_torque_is_counted_and_held_like_a_missing_one() {
        let mut h = hold(50);
        tick(&mut h, 0, &[torque(0, 2.0)]);
        let bad = torque(1, f64::NAN);
        match tick(&mut h, 1, &[bad]) {
            Settled::Miss { first_rejection: Some((1, f)), entered_safe_mode: false } => {
                assert_eq!(f.kind(), "non-finite");
            }
            other => panic!("{other:?}"),
        }
        assert_eq!((h.in_force().rotor_torque.x, h.rejected(), h.misses()), (2.0, 1, 1));
        // Absurd magnitude: rejected too, and only the first rejection is reported.
        let huge = torque(2, 10.0 * LIMIT);
        assert!(matches!(tick(&mut h, 2, &[huge]), Settled::Miss { first_rejection: None, .. }));
        assert_eq!((h.rejected(), h.misses()), (2, 2));
    }

    #[test]
    fn a_skipped_answer_is_a_miss_but_not_a_rejection() {
        let mut h = hold(50);
        tick(&mut h, 0, &[torque(0, 2.0)]);
        let skipped = TorqueSample { flags: TORQUE_SKIPPED, ..torque(1, 0.0) };
        assert_eq!(h.take(&skipped, 1, 7), Some(Answer::Skipped(skipped)));
        assert!(matches!(
            h.settle(Some(Answer::Skipped(skipped))),
            Settled::Miss { first_rejection: None, .. }
        ));
        assert_eq!((h.in_force().rotor_torque.x, h.rejected(), h.misses()), (2.0, 0, 1));
    }

    #[test]
    fn external_actuation_holds_the_body_torque() {
        let mut h = TorqueHold::new(50, Actuation::External, LIMIT);
        let t = TorqueSample { tick: 0, body_torque_nm: [0.0, 5.0, 0.0], ..torque(0, 3.0) };
        tick(&mut h, 0, &[t]);
        assert_eq!(h.in_force().rotor_torque, DVec3::ZERO);
        assert_eq!(h.in_force().body_torque.y, 5.0);
    }

    #[test]
    fn a_restart_resumes_the_hold_its_predecessor_published() {
        let scenario = Scenario::load("paper-sinusoid").expect("built-in");
        let mut a = PlantTicker::new(&scenario, 2, true);
        let mut published = Vec::new();
        for k in 0..10 {
            let s = a.state_sample(k, 0, 0);
            published.push(s);
            let answer = if k < 4 { vec![torque(k, 0.5 + k as f64)] } else { vec![] };
            tick(&mut a.hold, k, &answer);
            a.step(k).expect("finite");
        }
        // The predecessor dies after publishing tick 9 (in safe mode since tick 7).
        let last = a.state_sample(10, 0, 0);
        assert_ne!(last.flags & FLAG_SAFE_MODE, 0);
        let mut b = PlantTicker::new(&scenario, 2, true);
        assert!(b.can_resume(&last));
        b.resume(&last);
        assert_eq!(b.first(), 10);
        let again = b.state_sample(10, 0, 0);
        assert_eq!(
            format!("{again:?}"),
            format!("{last:?}"),
            "the restart publishes the same state"
        );
        for k in 10..15 {
            for p in [&mut a, &mut b] {
                tick(&mut p.hold, k, &[torque(k, 0.1)]);
                p.step(k).expect("finite");
            }
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
