//! What the monitor decides, without IPC or a clock: [`RowJoiner`] joins the state,
//! reference and torque samples of each tick into one trace row, in tick order, and
//! decides when a row is settled, when it is lost, and what a restarted monitor missed.
//! The process shell ([`crate::process`]) feeds it every sample it takes (and the time,
//! for the end-of-run quiet rule) and writes the rows it returns.
//!
//! The rules:
//! - Every sample is validated first; a rejected one is counted per topic and recorded
//!   as a fault event (topic, tick, kind, reason; the first [`MAX_FAULT_EVENTS`]), and a
//!   row whose state or reference was rejected is never written. A torque or reference
//!   for a tick the loop has not reached (the tick rule, [`TickBound`]: beyond the newest
//!   state, or beyond it and the reference's lead) is rejected so (`future-tick`), before
//!   it is counted as received or takes a place in a row: its tick would make every tick
//!   before it a loss and settle every row as if its torque had come.
//! - A row needs tick `k`'s state and reference. Its torque is settled when it came, was
//!   rejected, or will not come: a torque of a later tick (the controller answers the
//!   newest state and skips older ones under load), [`TORQUE_PATIENCE`] ticks of states
//!   without one, or the end. A late torque still takes effect in the plant, so the row
//!   waits for it rather than giving up when the next states arrive. Its sense-to-actuate needs the next state (which says which torque the plant
//!   held), so the row also waits for tick `k + 1` unless it is the last.
//! - A row whose state or reference never comes is **lost**: newer states exist and the
//!   ring (half of [`RING`]) moved on, or the run ended with newer states seen.
//! - After the plant's last state (seen, or in its resume slot), [`END_QUIET_NS`] without
//!   any new sample ([`END_QUIET_AFTER_END_NS`] for a monitor started after that state)
//!   settles everything still open: what is missing now never comes.
//! - A restarted monitor continues the counts of its predecessor; the first state it
//!   sees tells how many ticks it missed: that is a **gap**, its rows are lost.

use iceoryx2::prelude::ZeroCopySend;
use rotorloop_common::role::count::SeqCounter;
use rotorloop_common::wire::{
    FLAG_LAST, ReferenceSample, StateSample, TickBound, TorqueSample, WireFault,
};
use serde::Serialize;

use crate::metrics::METRICS_STATE_LEN;

/// Ticks of samples kept for joining.
pub const RING: usize = 16_384;
/// Gaps a restarted monitor's report keeps.
pub const MAX_GAPS: usize = 8;
/// Most wire fault events kept in the report.
pub const MAX_FAULT_EVENTS: usize = 64;
/// How many ticks a row waits for its torque after its state while no newer torque comes.
/// A late torque still takes effect in the plant (delayed zero-order hold), so the trace
/// must carry it for a replay: a row is not given up on just because the states moved on
/// (a dead controller's rows settle when its restart answers a newer state, or after this).
pub const TORQUE_PATIENCE: u64 = 1024;

/// After the plant's last state, this long without any new sample settles the rows still
/// open: their missing samples are not coming.
pub const END_QUIET_NS: u64 = 5_000_000_000;
/// The same for a monitor that started after the plant's last state (a restart after the
/// end, or one started by hand after the others): what was published is in its buffers at
/// once, but the plant marks its end before it publishes its last state, so the
/// controller's last answer may still be coming.
pub const END_QUIET_AFTER_END_NS: u64 = 1_000_000_000;

/// What a restarted monitor needs to continue the same report.
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("rotorloop::MonitorResume_v7")]
#[repr(C)]
pub struct MonitorResume {
    /// The next row to write: the rows before it are in the files.
    pub next_row: u64,
    /// The next row to take: the monitor's progress, which the launcher's watchdog reads.
    /// Rows from `next_row` up to it are taken and on their way to the files
    /// (`crate::filer`).
    pub taken_row: u64,
    /// `trace.csv`'s length with the rows before `next_row` (bytes): a restarted monitor
    /// cuts the file back to it, so a row written after the slot's last word is not
    /// written twice.
    pub trace_bytes: u64,
    /// `timing.csv`'s length, the same way.
    pub timing_bytes: u64,
    /// Rows written.
    pub rows: u64,
    /// Rows lost.
    pub rows_lost: u64,
    /// Restarts so far.
    pub restarts: u64,
    /// Attitude error of the first row (deg).
    pub first_err: f64,
    /// Largest relative momentum drift so far.
    pub drift_max: f64,
    /// Sum of the squared attitude errors of the rows so far (deg²), and their number.
    pub err_sq_sum: f64,
    /// See `err_sq_sum`.
    pub err_rows: u64,
    /// The metrics' running state.
    pub metrics: [f64; METRICS_STATE_LEN],
    /// Received and lost of state, reference and torque.
    pub counts: [u64; 6],
    /// Rejected state, reference and torque samples.
    pub rejected: [u64; 3],
    /// Gaps `[first, last]`.
    pub gaps: [[u64; 2]; MAX_GAPS],
    /// Gaps used.
    pub n_gaps: u64,
}

/// A sample the monitor rejected.
#[derive(Debug, Clone, Serialize)]
pub struct WireFaultEvent {
    /// `state`, `reference` or `torque`.
    pub topic: &'static str,
    /// The sample's tick.
    pub tick: u64,
    /// `non-finite`, `absurd`, `non-orthonormal` or `future-tick`.
    pub kind: &'static str,
    /// The reason, naming the field.
    pub detail: String,
}

#[derive(Debug, Clone, Copy, Default)]
struct Slot {
    state: Option<StateSample>,
    reference: Option<ReferenceSample>,
    torque: Option<TorqueSample>,
    /// The tick of a torque sample that arrived here and was rejected.
    torque_rejected: Option<u64>,
}

/// One settled row: the samples of tick `tick`.
#[derive(Debug, Clone, Copy)]
pub struct JoinedRow {
    /// The tick.
    pub tick: u64,
    /// The plant's state.
    pub state: StateSample,
    /// The reference.
    pub reference: ReferenceSample,
    /// The controller's answer, if it came, valid.
    pub torque: Option<TorqueSample>,
    /// The state of the next tick, if here (it says which torque the plant held).
    pub following: Option<StateSample>,
    /// The torque of the next tick, if here (it carries what publishing this row's cost).
    pub next_torque: Option<TorqueSample>,
    /// The first row of the run (none was written before, by this monitor or a
    /// predecessor).
    pub first: bool,
}

/// The joining rule (module docs).
#[derive(Debug, Clone)]
pub struct RowJoiner {
    ticks: u64,
    absurd_limit: f64,
    /// The tick rule's newest state known (valid states taken).
    bound: TickBound,
    slots: Vec<Slot>,
    /// Received and lost per topic: state, reference, torque.
    pub seq: [SeqCounter; 3],
    /// Rejected per topic: state, reference, torque.
    pub rejected: [u64; 3],
    /// The first rejected samples (this monitor life).
    pub wire_faults: Vec<WireFaultEvent>,
    next: u64,
    rows: u64,
    rows_lost: u64,
    gaps: Vec<[u64; 2]>,
    restarts: u64,
    gap_pending: bool,
    first_wake: Option<u64>,
    last_state: Option<StateSample>,
    last_torque: Option<TorqueSample>,
    inputs_seen: u64,
    last_input_ns: u64,
}

impl RowJoiner {
    /// Joins the rows of ticks `0..=ticks`; torques beyond `absurd_limit` are rejected.
    /// `now_ns` starts the quiet clock.
    pub fn new(ticks: u64, absurd_limit: f64, now_ns: u64) -> Self {
        Self {
            ticks,
            absurd_limit,
            bound: TickBound::new(ticks),
            slots: vec![Slot::default(); RING],
            seq: [SeqCounter::default(); 3],
            rejected: [0; 3],
            wire_faults: Vec::new(),
            next: 0,
            rows: 0,
            rows_lost: 0,
            gaps: Vec::new(),
            restarts: 0,
            gap_pending: false,
            first_wake: None,
            last_state: None,
            last_torque: None,
            inputs_seen: 0,
            last_input_ns: now_ns,
        }
    }

    /// Joins the rows of `scenario`'s run, rejecting torques beyond its actuators' absurd
    /// limit ([`TorqueSample::absurd_limit`]).
    pub fn for_scenario(scenario: &rotorloop_common::scenario::Scenario, now_ns: u64) -> Self {
        let limits = scenario.limits_for(scenario.actuation());
        Self::new(scenario.ticks(), TorqueSample::absurd_limit(limits.rotor_torque), now_ns)
    }

    /// Continues the report of a killed predecessor; the ticks between its last row and
    /// the first state this monitor sees become a gap.
    pub fn resume(&mut self, r: &MonitorResume) {
        self.next = r.next_row;
        self.rows = r.rows;
        self.rows_lost = r.rows_lost;
        self.restarts = r.restarts + 1;
        self.rejected = r.rejected;
        self.gaps = r.gaps[..(r.n_gaps as usize).min(MAX_GAPS)].to_vec();
        let (c, last) = (r.counts, r.next_row.saturating_sub(1));
        self.seq = [0, 2, 4].map(|i| SeqCounter::resume(c[i], c[i + 1], last));
        self.gap_pending = true;
    }

    /// What a restart needs, with the recording's own part.
    pub fn save(
        &self,
        first_err: f64,
        (err_sq_sum, err_rows): (f64, u64),
        drift_max: f64,
        metrics: [f64; METRICS_STATE_LEN],
    ) -> MonitorResume {
        let mut gaps = [[0u64; 2]; MAX_GAPS];
        for (d, src) in gaps.iter_mut().zip(&self.gaps) {
            *d = *src;
        }
        let s = self.seq;
        MonitorResume {
            next_row: self.next,
            taken_row: self.next,
            trace_bytes: 0,
            timing_bytes: 0,
            rows: self.rows,
            rows_lost: self.rows_lost,
            restarts: self.restarts,
            first_err,
            drift_max,
            err_sq_sum,
            err_rows,
            metrics,
            counts: [s[0].received, s[0].lost, s[1].received, s[1].lost, s[2].received, s[2].lost],
            rejected: self.rejected,
            gaps,
            n_gaps: self.gaps.len().min(MAX_GAPS) as u64,
        }
    }

    fn fault(&mut self, topic: usize, tick: u64, f: WireFault) {
        self.rejected[topic] += 1;
        if self.wire_faults.len() < MAX_FAULT_EVENTS {
            let detail = f.to_string();
            self.wire_faults.push(WireFaultEvent {
                topic: rotorloop_common::graph::Topic::ALL[topic].name(),
                tick,
                kind: f.kind(),
                detail,
            });
        }
    }

    /// A state sample arrived.
    pub fn take_state(&mut self, s: StateSample) {
        self.seq[0].see(s.tick);
        // Counters and flags are integers: usable even from a rejected sample.
        if self.last_state.is_none_or(|l| s.tick >= l.tick) {
            self.last_state = Some(s);
        }
        if let Err(f) = s.validate() {
            return self.fault(0, s.tick, f);
        }
        self.bound.saw_state(s.tick);
        self.first_wake.get_or_insert(s.wake_ns);
        self.slots[s.tick as usize % RING].state = Some(s);
    }

    /// A reference sample arrived; `published` says the newest state the plant has
    /// published, asked only for a tick beyond the newest state taken and the lead.
    pub fn take_reference(&mut self, r: ReferenceSample, published: impl FnOnce() -> Option<u64>) {
        if let Err(f) = self.bound.reference(&r, published) {
            return self.fault(1, r.tick, f);
        }
        self.seq[1].see(r.tick);
        if let Err(f) = r.validate() {
            return self.fault(1, r.tick, f);
        }
        self.slots[r.tick as usize % RING].reference = Some(r);
    }

    /// A torque sample arrived; `published` says the newest state the plant has
    /// published, asked only for a tick beyond the newest state taken.
    pub fn take_torque(&mut self, t: TorqueSample, published: impl FnOnce() -> Option<u64>) {
        if let Err(f) = self.bound.torque(&t, published) {
            return self.fault(2, t.tick, f);
        }
        self.seq[2].see(t.tick);
        if let Err(f) = t.validate(self.absurd_limit) {
            self.slots[t.tick as usize % RING].torque_rejected = Some(t.tick);
            return self.fault(2, t.tick, f);
        }
        self.slots[t.tick as usize % RING].torque = Some(t);
        self.last_torque = Some(t);
    }

    /// Whether the plant's last state has been seen.
    pub fn plant_ended(&self) -> bool {
        self.last_state.is_some_and(|s| s.flags & FLAG_LAST != 0)
    }

    /// Nanoseconds since any new sample arrived, at `now_ns`.
    pub fn quiet_ns(&mut self, now_ns: u64) -> u64 {
        let counts = self.seq.iter().map(|s| s.received).sum();
        if counts != self.inputs_seen {
            (self.inputs_seen, self.last_input_ns) = (counts, now_ns);
        }
        now_ns.saturating_sub(self.last_input_ns)
    }

    /// A restarted monitor's first state tells what it missed: a gap, its rows lost.
    fn account_gap(&mut self) {
        if !self.gap_pending {
            return;
        }
        let first = self
            .slots
            .iter()
            .filter_map(|sl| sl.state)
            .map(|st| st.tick)
            .filter(|t| *t >= self.next)
            .min();
        if let Some(first) = first {
            if first > self.next {
                self.gaps.push([self.next, first - 1]);
                self.rows_lost += first - self.next;
                self.next = first;
            }
            self.gap_pending = false;
        }
    }

    /// The next settled row, in tick order, or `None` while it is not settled. `stopping`
    /// (a termination signal, or the end's quiet period) settles whatever can be. Rows
    /// found lost on the way are counted and skipped.
    pub fn next_row(&mut self, stopping: bool) -> Option<JoinedRow> {
        self.account_gap();
        let newest = self.seq[0].last().unwrap_or(0);
        let newest_torque = self.seq[2].last();
        let ended = self.plant_ended();
        while self.next <= self.ticks {
            let next = self.next;
            let slot = self.slots[next as usize % RING];
            let s = slot.state.filter(|s| s.tick == next);
            let r = slot.reference.filter(|r| r.tick == next);
            let t = slot.torque.filter(|t| t.tick == next);
            let following = (next < self.ticks)
                .then(|| {
                    self.slots[(next + 1) as usize % RING].state.filter(|s| s.tick == next + 1)
                })
                .flatten();
            // A rejected torque settles its row too: no other sample of that tick comes.
            let t_rejected = slot.torque_rejected == Some(next);
            let torque_settled = t.is_some()
                || t_rejected
                || newest >= next + TORQUE_PATIENCE
                || newest_torque.is_some_and(|l| l > next)
                || stopping;
            let next_settled =
                following.is_some() || next == self.ticks || newest > next + 1 || stopping;
            let (Some(state), Some(reference)) = (s, r) else {
                // Lost for good: newer states exist and the ring moved on, or the run ended.
                if newest >= next + (RING as u64) / 2 || ((ended || stopping) && newest > next) {
                    self.rows_lost += 1;
                    self.next += 1;
                    continue;
                }
                return None;
            };
            // The last row waits for its torque even after the plant's last state: the
            // report's counts come from that last answer (the end's quiet period settles
            // it if none comes).
            let last_open = next == self.ticks && t.is_none() && !t_rejected && !stopping;
            if !(torque_settled && next_settled) || last_open {
                return None;
            }
            let first = self.rows == 0;
            self.rows += 1;
            self.next += 1;
            let next_torque = following
                .and_then(|_| self.slots[(next + 1) as usize % RING].torque)
                .filter(|t| t.tick == next + 1);
            let (tick, torque) = (next, t);
            return Some(JoinedRow {
                tick,
                state,
                reference,
                torque,
                following,
                next_torque,
                first,
            });
        }
        None
    }

    /// The run is over and the rows still open never came together: lost. A monitor
    /// restarted after the end saw none of them: that is its gap.
    pub fn settle_rest(&mut self) {
        if self.next > self.ticks {
            return;
        }
        if std::mem::take(&mut self.gap_pending) {
            self.gaps.push([self.next, self.ticks]);
        }
        self.rows_lost += self.ticks + 1 - self.next;
        self.next = self.ticks + 1;
    }

    /// Every row of the run is written or lost.
    pub fn done(&self) -> bool {
        self.next > self.ticks
    }

    /// Rows written.
    pub fn rows(&self) -> u64 {
        self.rows
    }

    /// Rows lost.
    pub fn rows_lost(&self) -> u64 {
        self.rows_lost
    }

    /// The ticks missed while down, `[first, last]`.
    pub fn gaps(&self) -> &[[u64; 2]] {
        &self.gaps
    }

    /// How often the monitor was restarted in this run.
    pub fn restarts(&self) -> u64 {
        self.restarts
    }

    /// The first plant wake-up seen (for the achieved rate).
    pub fn first_wake(&self) -> Option<u64> {
        self.first_wake
    }

    /// The newest state seen (its counters are the plant's).
    pub fn last_state(&self) -> Option<StateSample> {
        self.last_state
    }

    /// The newest valid torque seen (its counters are the controller's).
    pub fn last_torque(&self) -> Option<TorqueSample> {
        self.last_torque
    }
}

impl rotorloop_common::resume::Resumable for MonitorResume {
    /// Its rows lie within the run and in order (written ≤ taken ≤ ticks + 1). (Its
    /// running figures may be NaN by design: `first_err` before the first row.)
    fn resume_fault(&self, ticks: u64) -> Option<String> {
        let (next, taken) = (self.next_row, self.taken_row);
        (next > taken || taken > ticks + 1 || self.rows > ticks + 1).then(|| {
            format!(
                "rows out of order or beyond the run: next_row {next}, taken_row {taken}, rows {} \
                 (allowed: next_row ≤ taken_row ≤ {})",
                self.rows,
                ticks + 1
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DMat3;
    use rotorloop_common::so3::to_row_major;

    fn state(tick: u64, last: bool) -> StateSample {
        let x = rotorloop_common::params::RotorBodyState {
            r: DMat3::IDENTITY,
            omega: glam::DVec3::ZERO,
            omega_r: glam::DVec3::ZERO,
            theta: glam::DVec3::ZERO,
        };
        let mut s = StateSample::of(tick, tick as f64 * 1e-3, &x);
        s.flags = if last { FLAG_LAST } else { 0 };
        s
    }

    fn reference(tick: u64) -> ReferenceSample {
        ReferenceSample {
            r_d_row_major: to_row_major(&DMat3::IDENTITY),
            ..ReferenceSample::zeroed(tick)
        }
    }

    fn torque(tick: u64) -> TorqueSample {
        TorqueSample { tick, ..Default::default() }
    }

    /// What a host without the plant knows of the states it has published.
    fn no_plant() -> Option<u64> {
        None
    }

    fn rows(j: &mut RowJoiner, stopping: bool) -> Vec<(u64, bool)> {
        std::iter::from_fn(|| j.next_row(stopping)).map(|r| (r.tick, r.torque.is_some())).collect()
    }

    /// Feeds the three samples of each tick in `ticks`.
    fn feed(j: &mut RowJoiner, ticks: std::ops::Range<u64>, last: u64) {
        for k in ticks {
            j.take_reference(reference(k), no_plant);
            j.take_state(state(k, k == last));
            j.take_torque(torque(k), no_plant);
        }
    }

    #[test]
    fn a_row_is_written_once_its_torque_and_the_next_state_are_here() {
        let mut j = RowJoiner::new(3, 1e6, 0);
        feed(&mut j, 0..1, 3);
        assert!(rows(&mut j, false).is_empty(), "row 0 waits for state 1");
        feed(&mut j, 1..4, 3);
        assert_eq!(rows(&mut j, false), [(0, true), (1, true), (2, true), (3, true)]);
        assert!(j.done());
        assert_eq!((j.rows(), j.rows_lost()), (4, 0));
    }

    #[test]
    fn a_torque_the_controller_skipped_settles_from_a_later_torque() {
        let mut j = RowJoiner::new(10, 1e6, 0);
        for k in 0..3 {
            j.take_reference(reference(k), no_plant);
            j.take_state(state(k, false));
        }
        j.take_torque(torque(1), no_plant); // no torque for tick 0: the controller answered 1
        assert_eq!(rows(&mut j, false), [(0, false), (1, true)]);
    }

    #[test]
    fn a_late_torque_still_lands_in_its_row() {
        let mut j = RowJoiner::new(10, 1e6, 0);
        for k in 0..5 {
            j.take_reference(reference(k), no_plant);
            j.take_state(state(k, false));
        }
        assert!(rows(&mut j, false).is_empty(), "row 0 waits for its torque");
        // Four ticks late: the plant applies it, the trace shows it.
        j.take_torque(torque(0), no_plant);
        assert_eq!(rows(&mut j, false), [(0, true)]);
    }

    #[test]
    fn a_rejected_sample_is_counted_recorded_and_its_row_never_written() {
        let mut j = RowJoiner::new(2, 1e6, 0);
        let mut bad = state(1, false);
        bad.omega_body_rad_s[2] = f64::NAN;
        j.take_reference(reference(0), no_plant);
        j.take_state(state(0, false));
        j.take_torque(torque(0), no_plant);
        j.take_reference(reference(1), no_plant);
        j.take_state(bad);
        let mut huge = torque(1);
        huge.rotor_torque_nm[0] = 1e9;
        j.take_torque(huge, no_plant);
        j.take_reference(reference(2), no_plant);
        j.take_state(state(2, true));
        j.take_torque(torque(2), no_plant);
        assert_eq!(rows(&mut j, false), [(0, true), (2, true)]);
        assert_eq!((j.rejected, j.rows_lost()), ([1, 0, 1], 1));
        let kinds: Vec<_> = j.wire_faults.iter().map(|f| (f.topic, f.tick, f.kind)).collect();
        assert_eq!(kinds, [("state", 1, "non-finite"), ("torque", 1, "absurd")]);
    }

    /// Issue 42: a valid zero torque for tick 10¹² from a foreign publisher was not
    /// counted, and its tick made every row's torque look settled.
    #[test]
    fn a_sample_for_a_tick_not_reached_is_a_fault_event_and_takes_no_place_in_a_row() {
        let mut j = RowJoiner::new(3, 1e6, 0);
        let plant_at = |k: u64| move || Some(k);
        j.take_reference(reference(0), plant_at(0));
        j.take_state(state(0, false));
        j.take_torque(torque(1_000_000_000_000), plant_at(0));
        j.take_torque(torque(1), plant_at(0)); // the plant has not published state 1
        j.take_reference(reference(1_000_000_000_000), plant_at(0));
        // A torque taken before its state, which the plant has published: no fault.
        j.take_torque(torque(0), plant_at(0));
        j.take_reference(reference(1), plant_at(1));
        j.take_torque(torque(1), plant_at(1));
        assert_eq!(j.rejected, [0, 1, 2]);
        let seen: Vec<_> = j.wire_faults.iter().map(|f| (f.topic, f.tick, f.kind)).collect();
        assert_eq!(
            seen,
            [
                ("torque", 1_000_000_000_000, "future-tick"),
                ("torque", 1, "future-tick"),
                ("reference", 1_000_000_000_000, "future-tick"),
            ]
        );
        assert!(j.wire_faults[0].detail.contains("torque.tick"), "{}", j.wire_faults[0].detail);
        assert_eq!((j.seq[2].received, j.seq[2].lost), (2, 0), "torques 0 and 1 only");
        assert_eq!(j.last_torque().map(|t| t.tick), Some(1));
        j.take_state(state(1, false));
        feed(&mut j, 2..4, 3);
        assert_eq!(rows(&mut j, false), [(0, true), (1, true), (2, true), (3, true)]);
    }

    #[test]
    fn rows_whose_samples_never_come_are_lost_once_the_run_has_ended() {
        let mut j = RowJoiner::new(5, 1e6, 0);
        feed(&mut j, 0..2, 5);
        feed(&mut j, 4..6, 5); // ticks 2 and 3 never arrive
        assert_eq!(rows(&mut j, false), [(0, true), (1, true), (4, true), (5, true)]);
        assert_eq!((j.rows(), j.rows_lost()), (4, 2));
        assert!(j.done());
    }

    #[test]
    fn the_end_quiet_period_settles_a_last_row_whose_torque_never_comes() {
        let mut j = RowJoiner::new(1, 1e6, 0);
        feed(&mut j, 0..1, 1);
        j.take_reference(reference(1), no_plant);
        j.take_state(state(1, true));
        assert_eq!(rows(&mut j, false), [(0, true)], "the last row waits for its torque");
        assert_eq!(j.quiet_ns(1_000), 0);
        assert!(j.quiet_ns(1_000 + END_QUIET_NS + 1) > END_QUIET_NS);
        // The shell then stops: the row is written with no torque.
        assert_eq!(rows(&mut j, true), [(1, false)]);
        assert!(j.done());
    }

    #[test]
    fn a_restarted_monitor_counts_what_it_missed_as_a_gap() {
        let mut a = RowJoiner::new(100, 1e6, 0);
        feed(&mut a, 0..10, 100);
        assert_eq!(rows(&mut a, false).len(), 9);
        let saved = a.save(1.0, (0.0, 0), 0.0, [0.0; METRICS_STATE_LEN]);
        let mut b = RowJoiner::new(100, 1e6, 0);
        b.resume(&saved);
        feed(&mut b, 20..30, 100); // down from tick 9 to 19
        assert_eq!(rows(&mut b, false).first(), Some(&(20, true)));
        assert_eq!(b.gaps(), [[9, 19]]);
        assert_eq!((b.rows_lost(), b.restarts()), (11, 1));
        // Restarted after the end: everything left is its gap.
        let mut c = RowJoiner::new(100, 1e6, 0);
        c.resume(&b.save(1.0, (0.0, 0), 0.0, [0.0; METRICS_STATE_LEN]));
        c.settle_rest();
        assert_eq!(c.gaps().last(), Some(&[29, 100]));
        assert!(c.done());
        assert_eq!(c.rows() + c.rows_lost(), 101, "every tick written or lost");
    }
}
