//! What the controller decides, apart from the law and without IPC or a clock. The process
//! shell ([`crate::process`]) feeds it the samples that arrived and publishes its answers.
//!
//! - [`ReferencePairing`] pairs each state with the reference sample of the same tick,
//!   kept in a ring (the reference is published ahead). A rejected reference is counted
//!   and marks its tick; one for a tick beyond the newest state and the reference's lead
//!   (the tick rule, [`TickBound`]) is counted and leaves the ring alone: its entry is a
//!   true reference's, which it would displace (in lockstep the controller then waited
//!   for a reference that had come already). When tick `k`'s reference is missing
//!   (counted as a reference miss): in lockstep the shell waits for it (unless it was
//!   rejected); then, or at once in real time, the last good reference is held and
//!   propagated (`R_d ← R_d exp(Δt Ω_d)`, `Ω_d` and `Ω̇_d` held) for at most `hold_ticks`
//!   ticks; beyond that, or with no reference yet, there is nothing to track.
//! - [`TorqueAnswers`] decides what each state gets: the newest state taken is answered
//!   and older ones in the same batch are counted skipped; a state already answered (a
//!   restarted plant re-publishes its last one) gets the same answer again, never a second
//!   integration; a rejected state, or one with nothing to track, gets a
//!   [`TORQUE_SKIPPED`] answer (zero torque, `ξ_I` untouched), so every state taken is
//!   answered or counted skipped. A restart resumes the law's state (`ξ_I`) and the
//!   counters from its predecessor's resume slot ([`ControllerResume`]: the last answer
//!   and the law's state after it), bumpless; no law state rides on a wire sample.

use iceoryx2::prelude::ZeroCopySend;
use rotorloop_common::params::ReferenceState;
use rotorloop_common::role::count::SeqCounter;
use rotorloop_common::so3::exp;
use rotorloop_common::wire::{
    FLAG_LAST, NO_TICK, ReferenceSample, StateSample, TORQUE_SKIPPED, TickBound, TorqueSample,
    WireFault,
};

use crate::law::{AnyLaw, Law, LawState};

/// What the controller keeps in its resume slot: its last answer and the law's internal
/// state after it. A restart continues from both (bumpless), so a law's state never rides
/// on a wire sample and a new law never changes one.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("rotorloop::ControllerResume_v1")]
#[repr(C)]
pub struct ControllerResume {
    /// The last answer published (or about to be: the slot is written first).
    pub last: TorqueSample,
    /// The law's state after it ([`LawState`]).
    pub law: [f64; LawState::LEN],
}

/// Reference samples kept for pairing.
pub const RING: usize = 256;

/// A reference ring entry. Unboxed on purpose: the ring is allocated once, and boxing the
/// sample would allocate on every receive.
#[derive(Debug, Clone, Copy)]
#[allow(clippy::large_enum_variant)]
enum RefEntry {
    Empty,
    Valid(ReferenceSample),
    /// A sample of this tick arrived and was rejected.
    Rejected(u64),
}

/// The pairing rule (module docs).
#[derive(Debug, Clone)]
pub struct ReferencePairing {
    ring: Vec<RefEntry>,
    ticks: TickBound,
    /// The last reference paired, held over a miss: a copy made after the answer
    /// ([`ReferencePairing::settle`]), not at the pairing, which only notes its tick
    /// (`paired`); the ring still holds that tick's sample until the copy is made.
    last: Option<ReferenceSample>,
    paired: Option<u64>,
    held: u64,
    hold_ticks: u64,
    dt: f64,
    misses: u64,
    rejected: u64,
}

/// Reference `r` propagated to tick `k` (its `Ω_d` held over the gap): what the controller
/// tracks when tick `k`'s own reference is missing.
pub fn propagate(r: &ReferenceSample, k: u64, dt: f64) -> ReferenceState {
    let x = r.reference_state();
    let gap = (k - r.tick) as f64 * dt;
    ReferenceState { r_d: x.r_d * exp(gap * x.omega_d), ..x }
}

impl ReferencePairing {
    /// Holds a missing reference for at most `hold_ticks` ticks of `dt` seconds, in a run
    /// whose last tick is `last`.
    pub fn new(hold_ticks: u64, dt: f64, last: u64) -> Self {
        Self {
            ring: vec![RefEntry::Empty; RING],
            ticks: TickBound::new(last),
            last: None,
            paired: None,
            held: 0,
            hold_ticks,
            dt,
            misses: 0,
            rejected: 0,
        }
    }

    /// Continues the counts of a killed predecessor, from its last answer `t`.
    pub fn resume(&mut self, t: &TorqueSample) {
        (self.misses, self.rejected) = (t.reference_misses, t.references_rejected);
        self.ticks.saw_state(t.tick);
    }

    /// Asks for the cache lines pairing tick `k` reads and writes
    /// ([`rotorloop_common::prefetch`]).
    #[inline]
    pub fn prefetch(&self, k: u64) {
        rotorloop_common::prefetch::lines(self);
        rotorloop_common::prefetch::lines(&self.ring[k as usize % RING]);
    }

    /// The state of tick `k` was taken: the tick rule's newest state known.
    pub fn saw_state(&mut self, k: u64) {
        self.ticks.saw_state(k);
    }

    /// A reference sample arrived: its tick checked (the tick rule; `published` says the
    /// newest state the plant has published, asked only for a tick beyond the newest state
    /// taken and the lead), validated, stored by tick (or marked rejected).
    pub fn take(&mut self, r: ReferenceSample, published: impl FnOnce() -> Option<u64>) {
        if self.ticks.reference(&r, published).is_err() {
            self.rejected += 1;
            return;
        }
        self.ring[r.tick as usize % RING] = match r.validate() {
            Ok(()) => RefEntry::Valid(r),
            Err(_) => {
                self.rejected += 1;
                RefEntry::Rejected(r.tick)
            }
        };
    }

    /// After an answer (before any more references are taken): the reference just paired
    /// is copied out of the ring, where a later sample may take its entry, to be held
    /// over a miss. Off the path from a state to its answer, where a pairing copied the
    /// 240-byte sample before.
    #[inline]
    pub fn settle(&mut self) {
        if let Some(t) = self.paired.take()
            && let Some(r) = self.lookup(t)
        {
            self.last = Some(*r);
        }
    }

    /// Tick `k`'s reference sample, if it is here (in the ring: not copied).
    pub fn lookup(&self, k: u64) -> Option<&ReferenceSample> {
        match &self.ring[k as usize % RING] {
            RefEntry::Valid(r) if r.tick == k => Some(r),
            _ => None,
        }
    }

    /// Whether tick `k`'s reference arrived and was rejected (none will come).
    pub fn rejected_at(&self, k: u64) -> bool {
        matches!(self.ring[k as usize % RING], RefEntry::Rejected(t) if t == k)
    }

    /// Starts pairing tick `k` (whose state is `state_ok`): whether its reference is here.
    /// Missing for a valid state, it is counted as a reference miss; the caller may then
    /// wait for it (lockstep) before [`Self::finish`].
    pub fn begin(&mut self, k: u64, state_ok: bool) -> bool {
        self.saw_state(k);
        let here = self.lookup(k).is_some();
        if !here && state_ok {
            self.misses += 1;
        } else {
            self.held = 0;
        }
        here
    }

    /// Ends pairing tick `k`: its reference if it is here (after `begin`, or a wait), kept
    /// as the last good one; else the last good one propagated to `k` while the hold
    /// lasts (only after a miss counted by `begin`), else nothing to track.
    pub fn finish(&mut self, k: u64, missed: bool) -> Option<ReferenceState> {
        if let Some(r) = self.lookup(k) {
            let rd = r.reference_state();
            self.paired = Some(k);
            return Some(rd);
        }
        let unsettled = self.paired.and_then(|t| self.lookup(t)).copied();
        let r = unsettled.or(self.last).filter(|r| missed && r.tick < k)?;
        self.held += 1;
        (self.held <= self.hold_ticks).then(|| propagate(&r, k, self.dt))
    }

    /// Pairs tick `k` (whose state is `state_ok`) as [`Self::begin`] and [`Self::finish`]
    /// do; when the reference is missing and `wait` (lockstep), first polls `more` (which
    /// takes what arrived and says whether to keep waiting) until it is here or was
    /// rejected. Returns the reference to track, if any.
    pub fn pair(
        &mut self,
        k: u64,
        state_ok: bool,
        wait: bool,
        mut more: impl FnMut(&mut Self) -> anyhow::Result<bool>,
    ) -> anyhow::Result<Option<ReferenceState>> {
        let missed = !self.begin(k, state_ok) && state_ok;
        while missed && wait && self.lookup(k).is_none() && !self.rejected_at(k) && more(self)? {}
        Ok(self.finish(k, missed).filter(|_| state_ok))
    }

    /// States answered without their own reference sample at hand.
    pub fn misses(&self) -> u64 {
        self.misses
    }

    /// Reference samples rejected by validation.
    pub fn rejected(&self) -> u64 {
        self.rejected
    }
}

/// What to do with the newest state taken.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Decision {
    /// Already answered: send this same answer again.
    AnswerAgain(TorqueSample),
    /// Older than the last answer: nothing to send.
    Ignore,
    /// A new tick: pair it with a reference and answer it.
    Answer {
        /// Why the state cannot be used, if it was rejected.
        fault: Option<WireFault>,
        /// This is the first rejected state of this controller's life (worth a log line).
        first_rejection: bool,
    },
}

/// The answering rule (module docs), around the law.
#[derive(Debug, Clone)]
pub struct TorqueAnswers {
    law: AnyLaw,
    seq: SeqCounter,
    skipped: u64,
    published: u64,
    rejected: u64,
    rejection_seen: bool,
    last: Option<TorqueSample>,
    unanswered: Option<u64>,
}

impl TorqueAnswers {
    /// Answers with `law`.
    pub fn new(law: AnyLaw) -> Self {
        Self {
            law,
            seq: SeqCounter::default(),
            skipped: 0,
            published: 0,
            rejected: 0,
            rejection_seen: false,
            last: None,
            unanswered: None,
        }
    }

    /// Test hook: never answers the state of tick `tick` (unless it is the last), as when
    /// a newer state superseded it in the inbox under load; it is counted skipped.
    pub fn leaving_unanswered(mut self, tick: Option<u64>) -> Self {
        self.unanswered = tick;
        self
    }

    /// The law of `scenario` (gains, the controller's body model, actuator limits and
    /// anti-windup), answering from tick 0; an error if the scenario names no known law.
    pub fn for_scenario(
        scenario: &rotorloop_common::scenario::Scenario,
    ) -> Result<Self, crate::law::UnknownLaw> {
        Ok(Self::new(AnyLaw::for_scenario(scenario, scenario.actuation())?))
    }

    /// Continues bumplessly from what a killed predecessor kept in its resume slot: its
    /// law's state, its counters, its tick.
    pub fn resume(&mut self, r: &ControllerResume) {
        let t = &r.last;
        self.law.restore(&LawState(r.law));
        self.published = t.published;
        self.skipped = t.states_skipped;
        self.rejected = t.states_rejected;
        self.seq = SeqCounter::resume(t.states_received, t.states_lost, t.tick);
        self.last = Some(*t);
    }

    /// Asks for the cache lines the rule and the law read and write for the next state,
    /// and the numbers its validation compares with ([`rotorloop_common::prefetch`]).
    #[inline]
    pub fn prefetch(&self) {
        rotorloop_common::prefetch::lines(self);
        rotorloop_common::wire::prefetch_sweep();
    }

    /// What the resume slot keeps after answer `last` ([`Self::write_resume_record`], the
    /// one definition, which the slot's store uses in place), as a value.
    pub fn resume_record(&self, last: &TorqueSample) -> ControllerResume {
        let mut r = ControllerResume { last: *last, law: [0.0; LawState::LEN] };
        self.write_resume_record(&mut r, last);
        r
    }

    /// What the resume slot keeps after answer `last`: it and the law's state now, written
    /// into `r` in place (a resume slot's copy:
    /// [`rotorloop_common::resume::ResumeSlot::store_with`]).
    #[inline]
    pub fn write_resume_record(&self, r: &mut ControllerResume, last: &TorqueSample) {
        r.last = *last;
        self.write_law_state(r);
    }

    /// The law's state now, into the resume slot's copy `r` (after the `computed` stamp:
    /// the publish preparation's part of the slot's store).
    #[inline]
    pub fn write_law_state(&self, r: &mut ControllerResume) {
        r.law = self.law.state().0;
    }

    /// Whether this controller resumed from (or has sent) an answer.
    pub fn last(&self) -> Option<TorqueSample> {
        self.last
    }

    /// A state sample taken from the inbox. `newest_so_far` says whether another one was
    /// taken before it in this batch: that one is skipped (only the newest is answered).
    pub fn take(&mut self, s: &StateSample, newest_so_far: bool) {
        self.seq.see(s.tick);
        self.skipped += u64::from(newest_so_far);
    }

    /// What the newest state `s` gets.
    pub fn decide(&mut self, s: &StateSample) -> Decision {
        if self.unanswered == Some(s.tick) && s.flags & FLAG_LAST == 0 {
            self.skipped += 1;
            return Decision::Ignore;
        }
        // By reference: the last answer is copied only when it is sent again.
        match self.last.as_ref().filter(|t| t.tick >= s.tick) {
            Some(prev) if prev.tick == s.tick => Decision::AnswerAgain(*prev),
            Some(_) => Decision::Ignore,
            None => {
                let fault = s.validate().err();
                self.rejected += u64::from(fault.is_some());
                let first_rejection = fault.is_some() && !self.rejection_seen;
                self.rejection_seen |= fault.is_some();
                Decision::Answer { fault, first_rejection }
            }
        }
    }

    /// The answer to state `s` (received at `recv_ns`), tracking `rd`; with `None` (a
    /// rejected state or nothing to track) a skipped answer. The counts of `pairing` go
    /// into the sample; `publish_ns` is left for the send. The answer rule learns of it
    /// from [`TorqueAnswers::gave`], once it is sent: its copy is not the law's work, and
    /// was inside the law's stage (`computed_ns` is when the torques were computed).
    #[inline(always)]
    pub fn answer(
        &mut self,
        s: &StateSample,
        recv_ns: u64,
        rd: Option<&ReferenceState>,
        pairing: &ReferencePairing,
        dt: f64,
    ) -> TorqueSample {
        let out = match rd {
            Some(rd) => self.law.step(&s.body_state(), rd, dt),
            None => Default::default(),
        };
        self.published += 1;
        TorqueSample {
            tick: s.tick,
            rotor_torque_nm: out.rotor_torque.to_array(),
            body_torque_nm: out.body_torque.to_array(),
            state_recv_ns: recv_ns,
            publish_ns: 0,
            states_received: self.seq.received,
            states_lost: self.seq.lost,
            states_skipped: self.skipped,
            reference_misses: pairing.misses(),
            published: self.published,
            states_rejected: self.rejected,
            references_rejected: pairing.rejected(),
            flags: if rd.is_none() { TORQUE_SKIPPED } else { 0 },
            // The stage stamps and the previous publish's cost are the shell's to fill.
            validated_ns: 0,
            paired_ns: 0,
            computed_ns: 0,
            prev_tick: NO_TICK,
            prev_publish: Default::default(),
        }
    }

    /// [`Self::answer`] written in place into the resume slot's next copy `r` (the answer
    /// is sent from there: not built aside and copied), with its stage stamps (`validated`
    /// and `paired` given, `computed` read from `clock` once the law is done) and the
    /// law's state after it.
    #[inline]
    pub fn answer_into(
        &mut self,
        r: &mut ControllerResume,
        (s, recv_ns): (&StateSample, u64),
        (rd, pairing): (Option<&ReferenceState>, &ReferencePairing),
        dt: f64,
        (validated, paired, clock): (u64, u64, fn() -> u64),
    ) {
        r.last = self.answer(s, recv_ns, rd, pairing, dt);
        (r.last.validated_ns, r.last.paired_ns, r.last.computed_ns) = (validated, paired, clock());
        self.write_law_state(r);
    }

    /// Answer `t` was given (sent, or held back to be sent): a state of its tick again
    /// gets it again, without its stage stamps (theirs were this sending's), and an older
    /// one nothing. Called after the publish, off the hop.
    #[inline]
    pub fn gave(&mut self, t: &TorqueSample) {
        self.last = Some(TorqueSample { validated_ns: 0, paired_ns: 0, computed_ns: 0, ..*t });
    }
}

/// An injected delay (`--inject-delay FROM=SECONDS[:UNTIL]`, set by `rotorloop run --fault
/// controller:delay@…`): answers to states of times in `[from_s, until_s)` are sent
/// `delay_s` late.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InjectedDelay {
    /// From this state time (s).
    pub from_s: f64,
    /// Each answer this much late (s).
    pub delay_s: f64,
    /// Until this state time (s), if it ends.
    pub until_s: Option<f64>,
}

impl std::str::FromStr for InjectedDelay {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad =
            || format!("`{s}` is not allowed: FROM=SECONDS[:UNTIL], times in s ≥ 0, delay > 0");
        let (from, rest) = s.split_once('=').ok_or_else(bad)?;
        let (delay, until) = match rest.split_once(':') {
            Some((d, u)) => (d, Some(u)),
            None => (rest, None),
        };
        let num =
            |v: &str| v.parse::<f64>().ok().filter(|x| x.is_finite() && *x >= 0.0).ok_or_else(bad);
        let (from_s, delay_s) = (num(from)?, num(delay)?);
        let until_s = until.map(num).transpose()?;
        if delay_s == 0.0 || until_s.is_some_and(|u| u <= from_s) {
            return Err(bad());
        }
        Ok(Self { from_s, delay_s, until_s })
    }
}

/// Answers held back by an injected delay, sent when due (in order: a network that
/// delays, not one that reorders).
#[derive(Debug, Clone, Default)]
pub struct DelayedSends {
    delays: Vec<InjectedDelay>,
    queue: std::collections::VecDeque<(u64, TorqueSample)>,
}

impl DelayedSends {
    /// Sends delayed by `delays`; room for a second of answers at 10 kHz is reserved.
    pub fn new(delays: Vec<InjectedDelay>) -> Self {
        let room = if delays.is_empty() { 0 } else { 10_000 };
        Self { delays, queue: std::collections::VecDeque::with_capacity(room) }
    }

    /// The answer `t` to the state of time `t_s`, ready at `now_ns`: `Some(t)` to send now,
    /// or `None` when it is held back.
    pub fn hold(&mut self, t: TorqueSample, t_s: f64, now_ns: u64) -> Option<TorqueSample> {
        (!self.holds_back(&t, t_s, now_ns)).then_some(t)
    }

    /// [`Self::hold`] by reference: whether `t` was held back (then it was copied into
    /// the queue); false to send it now. Without injected delays (the queue is then
    /// empty) a test of one length, inline: no copy of the answer, no call.
    #[inline]
    pub fn holds_back(&mut self, t: &TorqueSample, t_s: f64, now_ns: u64) -> bool {
        !self.delays.is_empty() && self.queue_if_delayed(t, t_s, now_ns)
    }

    fn queue_if_delayed(&mut self, t: &TorqueSample, t_s: f64, now_ns: u64) -> bool {
        let active =
            self.delays.iter().find(|d| t_s >= d.from_s && d.until_s.is_none_or(|u| t_s < u));
        match active {
            Some(d) => {
                self.queue.push_back((now_ns + (d.delay_s * 1e9) as u64, *t));
                true
            }
            None if self.queue.is_empty() => false,
            None => {
                // Behind answers still held: keep the order.
                let due = self.queue.back().map_or(now_ns, |b| b.0);
                self.queue.push_back((due, *t));
                true
            }
        }
    }

    /// The next held answer if it is due at `now_ns`.
    pub fn due(&mut self, now_ns: u64) -> Option<TorqueSample> {
        self.queue
            .front()
            .is_some_and(|f| f.0 <= now_ns)
            .then(|| self.queue.pop_front().map(|f| f.1))
            .flatten()
    }

    /// When the next held answer is due.
    pub fn next_due_ns(&self) -> Option<u64> {
        self.queue.front().map(|f| f.0)
    }
}

impl rotorloop_common::resume::Resumable for ControllerResume {
    /// The last answer is of a tick within the run, and it and the law's state are finite
    /// and plausible (±1e6, the wire's bound on torques and rates).
    fn resume_fault(&self, ticks: u64) -> Option<String> {
        if self.last.tick >= ticks {
            let k = self.last.tick;
            return Some(format!("last.tick {k} is not before the run's last tick {ticks}"));
        }
        rotorloop_common::resume::unusable_field(
            &[
                ("last.rotor_torque_nm", &self.last.rotor_torque_nm),
                ("last.body_torque_nm", &self.last.body_torque_nm),
                ("law", &self.law),
            ],
            1e6,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::law::geometric_pid::GeometricPid;
    use glam::DMat3;
    use rotorloop_common::scenario::Scenario;
    use rotorloop_common::so3::to_row_major;
    use rotorloop_common::wire::REFERENCE_LEAD;

    const DT: f64 = 1e-3;
    /// The run's last tick.
    const LAST: u64 = 1000;

    /// What a host without the plant knows of the states it has published.
    fn no_plant() -> Option<u64> {
        None
    }

    fn reference(tick: u64, omega: f64) -> ReferenceSample {
        ReferenceSample {
            t_s: tick as f64 * DT,
            r_d_row_major: to_row_major(&DMat3::IDENTITY),
            omega_d_rad_s: [0.0, 0.0, omega],
            ..ReferenceSample::zeroed(tick)
        }
    }

    /// Pairs tick `k` as the real-time shell does (no wait).
    fn pair(p: &mut ReferencePairing, k: u64) -> Option<ReferenceState> {
        let missed = !p.begin(k, true);
        p.finish(k, missed)
    }

    #[test]
    fn a_state_pairs_with_the_reference_of_its_own_tick() {
        let mut p = ReferencePairing::new(10, DT, LAST);
        p.take(reference(3, 0.5), no_plant);
        p.take(reference(4, 0.7), no_plant);
        assert_eq!(pair(&mut p, 4).expect("paired").omega_d.z, 0.7);
        assert_eq!(p.misses(), 0);
    }

    #[test]
    fn the_reference_held_over_a_miss_survives_its_ring_entry_being_taken() {
        let last = 10 * RING as u64;
        let mut p = ReferencePairing::new(5, DT, last);
        p.take(reference(1, 2.0), no_plant);
        pair(&mut p, 1).expect("tick 1");
        p.settle(); // after the answer, as the shell does
        // Tick 1's entry is taken by a later tick (the tick rule asks the plant, which
        // has published that far), then by a rejected one.
        let far = 1 + RING as u64;
        p.take(reference(far, 9.0), || Some(far));
        let bad =
            ReferenceSample { omega_d_rad_s: [f64::NAN; 3], ..reference(far + RING as u64, 9.0) };
        p.take(bad, || Some(far + RING as u64));
        assert!(p.rejected_at(far + RING as u64), "the entry now marks a rejected tick");
        assert_eq!(p.lookup(1).map(|r| r.tick), None, "tick 1's entry holds another tick");
        let rd = pair(&mut p, 3).expect("tick 1's reference, held");
        let expected = exp(2.0 * DT * glam::DVec3::new(0.0, 0.0, 2.0));
        assert!(rd.r_d.abs_diff_eq(expected, 1e-15), "R_d ← R_d exp(2 Δt Ω_d), from tick 1's");
        assert_eq!(rd.omega_d.z, 2.0, "tick 1's Ω_d, not the later samples'");
    }

    #[test]
    fn a_missing_reference_is_held_and_propagated_for_at_most_hold_ticks() {
        let mut p = ReferencePairing::new(2, DT, LAST);
        p.take(reference(0, 2.0), no_plant);
        pair(&mut p, 0).expect("tick 0");
        let rd = pair(&mut p, 3).expect("propagated");
        let expected = exp(3.0 * DT * glam::DVec3::new(0.0, 0.0, 2.0));
        assert!(rd.r_d.abs_diff_eq(expected, 1e-15), "R_d ← R_d exp(3 Δt Ω_d)");
        assert_eq!(rd.omega_d.z, 2.0, "Ω_d held");
        assert!(pair(&mut p, 4).is_some(), "second held tick");
        assert!(pair(&mut p, 5).is_none(), "beyond the hold: nothing to track");
        assert_eq!(p.misses(), 3);
        // A fresh reference ends the hold and resets it.
        p.take(reference(6, 1.0), no_plant);
        assert_eq!(pair(&mut p, 6).expect("fresh").omega_d.z, 1.0);
        assert!(pair(&mut p, 7).is_some(), "the hold counts afresh");
    }

    #[test]
    fn with_no_reference_yet_there_is_nothing_to_track() {
        let mut p = ReferencePairing::new(1000, DT, LAST);
        assert!(pair(&mut p, 0).is_none());
        assert_eq!(p.misses(), 1);
    }

    #[test]
    fn a_rejected_reference_is_counted_and_marks_its_tick() {
        let mut p = ReferencePairing::new(1000, DT, LAST);
        p.take(reference(0, 1.0), no_plant);
        pair(&mut p, 0);
        let mut bad = reference(1, 1.0);
        bad.omega_d_rad_s[0] = f64::NAN;
        p.take(bad, no_plant);
        assert!(p.rejected_at(1) && !p.rejected_at(2));
        assert_eq!(p.rejected(), 1);
        assert!(pair(&mut p, 1).is_some(), "the last good reference is propagated instead");
    }

    /// Issue 42: a reference for a far tick took the ring entry of a true one already
    /// there (`tick mod RING`), and a lockstep controller waited for it for ever.
    #[test]
    fn a_reference_beyond_the_lead_is_rejected_counted_and_displaces_none() {
        let mut p = ReferencePairing::new(1000, DT, LAST);
        let plant_at = |k: u64| move || Some(k);
        for k in 0..=REFERENCE_LEAD {
            p.take(reference(k, 1.0), plant_at(0));
        }
        let far = reference(REFERENCE_LEAD + 256 * 3_906_250_000, 9.0);
        assert_eq!(far.tick as usize % RING, REFERENCE_LEAD as usize % RING, "the same entry");
        p.take(far, plant_at(0));
        p.take(reference(REFERENCE_LEAD + 1, 1.0), plant_at(0));
        assert_eq!(p.rejected(), 2, "beyond the newest state (0) and the lead");
        assert!(!p.rejected_at(REFERENCE_LEAD), "a true tick is not marked");
        assert_eq!(p.lookup(REFERENCE_LEAD).map(|r| r.omega_d_rad_s[2]), Some(1.0), "kept");
        // The reference saw a state the controller has not taken yet: the plant's slot
        // says it is out, and the reference is taken.
        p.take(reference(REFERENCE_LEAD + 1, 1.0), plant_at(1));
        assert!(p.lookup(REFERENCE_LEAD + 1).is_some());
        assert_eq!(p.rejected(), 2);
        // Pairing a tick moves the bound with it.
        assert!(pair(&mut p, 5).is_some());
        p.take(reference(5 + REFERENCE_LEAD, 1.0), || panic!("not asked within the lead"));
        // No plant on this host: only what the run never reaches is refused.
        p.take(reference(LAST, 1.0), no_plant);
        p.take(reference(LAST + REFERENCE_LEAD + 1, 1.0), no_plant);
        assert_eq!(p.rejected(), 3);
    }

    #[test]
    fn a_rejected_state_does_not_count_a_reference_miss() {
        let mut p = ReferencePairing::new(1000, DT, LAST);
        assert!(!p.begin(0, false));
        assert_eq!(p.misses(), 0);
    }

    fn answers() -> (TorqueAnswers, StateSample) {
        let scenario = Scenario::load("paper-constant").expect("built-in");
        let a = scenario.actuation();
        let pid = GeometricPid::new(scenario.gains, scenario.controller_params(a));
        (
            TorqueAnswers::new(AnyLaw::GeometricPid(pid)),
            StateSample::of(0, 0.0, &scenario.plant_init),
        )
    }

    /// The answer written in place into the resume slot's copy is the one `answer`
    /// gives, with the stage stamps (the computed one read after the law) and the law's
    /// state after it: every field of the record set, whatever the copy held.
    #[test]
    fn the_answer_written_into_the_slot_is_the_answer_with_its_stamps_and_the_laws_state() {
        let ((mut a, s0), (mut b, _)) = (answers(), answers());
        let p = ReferencePairing::new(10, DT, LAST);
        let rd = reference(0, 0.1).reference_state();
        let want = a.answer(&s0, 5, Some(&rd), &p, DT);
        let junk = TorqueSample { tick: 99, rotor_torque_nm: [f64::NAN; 3], ..want };
        let mut r = ControllerResume { last: junk, law: [f64::NAN; LawState::LEN] };
        b.answer_into(&mut r, (&s0, 5), (Some(&rd), &p), DT, (7, 8, || 9));
        let stamped = TorqueSample { validated_ns: 7, paired_ns: 8, computed_ns: 9, ..want };
        assert_eq!(r.last, stamped);
        assert_eq!(r.law, a.resume_record(&want).law, "the law's state after this answer");
    }

    #[test]
    fn a_state_already_answered_gets_the_same_answer_again() {
        let (mut a, s0) = answers();
        let p = ReferencePairing::new(10, DT, LAST);
        let rd = reference(0, 0.1).reference_state();
        assert_eq!(a.decide(&s0), Decision::Answer { fault: None, first_rejection: false });
        let first = a.answer(&s0, 5, Some(&rd), &p, DT);
        assert!(matches!(a.decide(&s0), Decision::Answer { .. }), "not given yet");
        a.gave(&TorqueSample { validated_ns: 7, paired_ns: 8, computed_ns: 9, ..first });
        assert_eq!(a.decide(&s0), Decision::AnswerAgain(first), "without this sending's stamps");
        let older = StateSample { tick: 0, ..s0 };
        let s1 = StateSample { tick: 1, ..s0 };
        let second = a.answer(&s1, 6, Some(&rd), &p, DT);
        a.gave(&second);
        assert_eq!(a.decide(&older), Decision::Ignore);
        assert_eq!(a.last().expect("answered").published, 2, "no second integration");
    }

    #[test]
    fn a_rejected_state_gets_a_skipped_answer_with_the_integral_untouched() {
        let (mut a, s0) = answers();
        let p = ReferencePairing::new(10, DT, LAST);
        let rd = reference(0, 0.1).reference_state();
        let t0 = a.answer(&s0, 0, Some(&rd), &p, DT);
        let law_before = a.resume_record(&t0).law;
        let mut bad = StateSample { tick: 1, ..s0 };
        bad.omega_body_rad_s[1] = f64::INFINITY;
        let Decision::Answer { fault: Some(f), first_rejection: true } = a.decide(&bad) else {
            panic!("not rejected")
        };
        assert_eq!(f.kind(), "non-finite");
        let t1 = a.answer(&bad, 0, None, &p, DT);
        assert_eq!(t1.flags, TORQUE_SKIPPED);
        assert_eq!(t1.rotor_torque_nm, [0.0; 3]);
        assert_eq!(a.resume_record(&t1).law, law_before, "ξ_I untouched by a skipped tick");
        assert_eq!(t1.states_rejected, 1);
    }

    #[test]
    fn only_the_newest_state_of_a_batch_is_answered_the_rest_counted_skipped() {
        let (mut a, s0) = answers();
        for (i, k) in [3u64, 4, 6].iter().enumerate() {
            a.take(&StateSample { tick: *k, ..s0 }, i > 0);
        }
        let t = a.answer(
            &StateSample { tick: 6, ..s0 },
            0,
            None,
            &ReferencePairing::new(1, DT, LAST),
            DT,
        );
        assert_eq!(
            (t.states_received, t.states_lost, t.states_skipped),
            (3, 4, 2),
            "0-2 and 5 lost"
        );
    }

    #[test]
    fn a_state_left_unanswered_by_the_test_hook_is_counted_skipped_unless_last() {
        let (a, s0) = answers();
        let mut a = a.leaving_unanswered(Some(2));
        assert_eq!(a.decide(&StateSample { tick: 2, ..s0 }), Decision::Ignore);
        let last = StateSample { tick: 2, flags: FLAG_LAST, ..s0 };
        assert!(matches!(a.decide(&last), Decision::Answer { .. }));
        let t = a.answer(&last, 0, None, &ReferencePairing::new(1, DT, LAST), DT);
        assert_eq!(t.states_skipped, 1);
    }

    #[test]
    fn an_injected_delay_sends_each_answer_that_much_later_in_order() {
        let d: InjectedDelay = "1=0.005:2".parse().expect("valid");
        assert_eq!(d, InjectedDelay { from_s: 1.0, delay_s: 0.005, until_s: Some(2.0) });
        for bad in ["1", "1=0", "2=0.1:1", "x=1", "-1=0.1"] {
            assert!(bad.parse::<InjectedDelay>().is_err(), "{bad}");
        }
        let mut s = DelayedSends::new(vec![d]);
        let t = |tick| TorqueSample { tick, ..Default::default() };
        assert_eq!(s.hold(t(1), 0.5, 0), Some(t(1)), "before the delay: at once");
        assert_eq!(s.hold(t(2), 1.0, 1_000), None);
        assert_eq!(s.hold(t(3), 1.001, 2_000_000), None);
        assert_eq!(s.next_due_ns(), Some(5_001_000));
        assert_eq!(s.due(5_000_999), None);
        assert_eq!(s.due(5_001_000), Some(t(2)));
        // After the delay ends, an answer still waits behind those held: in order.
        assert_eq!(s.hold(t(4), 2.0, 3_000_000), None);
        assert_eq!(s.due(7_000_000), Some(t(3)));
        assert_eq!(s.due(7_000_000), Some(t(4)));
        assert_eq!(s.hold(t(5), 2.1, 8_000_000), Some(t(5)));
    }

    #[test]
    fn a_restart_resumes_the_integral_state_bumplessly() {
        let (mut a, s0) = answers();
        let p = ReferencePairing::new(10, DT, LAST);
        let rd = reference(0, 0.1).reference_state();
        let mut last = a.answer(&s0, 0, Some(&rd), &p, DT);
        for k in 1..5 {
            last = a.answer(&StateSample { tick: k, ..s0 }, 0, Some(&rd), &p, DT);
        }
        let (mut b, _) = answers();
        b.resume(&a.resume_record(&last));
        let s5 = StateSample { tick: 5, ..s0 };
        assert_eq!(b.decide(&s5), Decision::Answer { fault: None, first_rejection: false });
        let (ta, tb) = (a.answer(&s5, 0, Some(&rd), &p, DT), b.answer(&s5, 0, Some(&rd), &p, DT));
        assert_eq!(format!("{ta:?}"), format!("{tb:?}"));
    }
}
