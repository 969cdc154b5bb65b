//! The run's report from the roles' flight records (`common::flight`), not from what the
//! monitor happened to see: every sample each role published is in its record, so the
//! trace, the timing rows, the histograms and the figures are complete whatever was
//! killed, the monitor included, and whether or not the monitor kept up.
//!
//! The records go through the same [`RowJoiner`] and [`Recording`] as the live view, in
//! tick order, so a row is the row the monitor would have written had it seen every
//! sample. A torque missing from the controller's record (a controller killed between
//! its publish and its record) is taken from the plant's record of what it received.
//!
//! The live view keeps what only it knows: what the monitor itself received and lost,
//! its gaps and restarts, and the rejected samples of no role's record (another
//! publisher's on a topic) (the live [`RowJoiner`] handed to [`report`]).

use std::path::Path;

use rotorloop_common::flight::{FlightError, FlightLog, SPARE_SLOTS, Stream};
use rotorloop_common::role::args::RoleArgs;
use rotorloop_common::scenario::Scenario;
use rotorloop_common::wire::{ReferenceSample, StateSample, TorqueSample};

use crate::hosts::Hosts;
use crate::policy::RowJoiner;
use crate::recording::{Recording, fallback_dir};
use crate::report::{FlightSummary, LostSummary, RunSummary, StreamSummary, summary};

/// Readers of a run's four records ([`FlightRecords::shared`]).
pub type SharedRecords = (
    FlightLog<StateSample>,
    Option<FlightLog<TorqueSample>>,
    FlightLog<TorqueSample>,
    FlightLog<ReferenceSample>,
);

/// The four records of a run.
#[derive(Debug)]
pub struct FlightRecords {
    states: FlightLog<StateSample>,
    received: FlightLog<TorqueSample>,
    torques: Option<FlightLog<TorqueSample>>,
    references: FlightLog<ReferenceSample>,
    /// The last tick the run could hold (its ticks and the reference's lead).
    limit: u64,
    /// Why a stream the report needs could not be read at all (its reader is empty, the
    /// problem named in it).
    incomplete: Option<FlightError>,
}

/// `r`'s reader, or an empty one naming its error (the first kept in `first`).
fn or_unreadable<T: rotorloop_common::flight::Record>(
    r: Result<FlightLog<T>, FlightError>,
    first: &mut Option<FlightError>,
) -> FlightLog<T> {
    r.unwrap_or_else(|e| {
        let log = FlightLog::unreadable(&e);
        first.get_or_insert(e);
        log
    })
}

impl StreamSummary {
    fn of<T: rotorloop_common::flight::Record>(
        stream: Stream,
        log: &FlightLog<T>,
        last: u64,
    ) -> Self {
        let count = log.count(last);
        let mut problems = log.problems.clone();
        if log.more_problems > 0 {
            problems.push(format!("and {} more", log.more_problems));
        }
        Self {
            stream: stream.name(),
            records: count.records,
            missing: count.missing,
            opens: log.opens,
            beyond: log.beyond,
            problems,
        }
    }
}

impl FlightRecords {
    /// Opens the records in `dir` of a run of `ticks` ticks (a block at a time: the
    /// stream is never held), reading whatever of them is sound: a stream whose files are
    /// all missing or damaged reads as empty, named ([`Self::incomplete`]; the controller's
    /// may be absent: the plant's record of what it received stands in). An error where
    /// nothing of the plant's states, or of any stream, can be read.
    pub fn read(dir: &Path, ticks: u64) -> Result<Self, FlightError> {
        let limit = ticks.saturating_add(SPARE_SLOTS);
        let mut first = None;
        let states = or_unreadable(FlightLog::read(dir, Stream::PlantState, limit), &mut first);
        let received = or_unreadable(FlightLog::read(dir, Stream::PlantTorque, limit), &mut first);
        let references = or_unreadable(FlightLog::read(dir, Stream::Reference, limit), &mut first);
        let torques = match FlightLog::read(dir, Stream::ControllerTorque, limit) {
            Ok(t) => Some(t),
            Err(FlightError::Missing { .. }) => None, // a controller of the user's own
            Err(e) => Some(FlightLog::unreadable(&e)),
        };
        let sound = states.is_sound()
            || received.is_sound()
            || references.is_sound()
            || torques.as_ref().is_some_and(FlightLog::is_sound);
        // The plant's states are the record's spine (its clock, every row of the trace):
        // without one sound, nothing of the run can be reported.
        match first {
            Some(e) if !sound || !states.is_sound() => Err(e),
            incomplete => Ok(Self { states, received, torques, references, limit, incomplete }),
        }
    }

    /// Why a stream the report needs has no readable record at all (the monitor's live
    /// view is then the better report of a run that is still its own).
    pub fn incomplete(&self) -> Option<&FlightError> {
        self.incomplete.as_ref()
    }

    /// Readers of the same four records sharing these readers' kept blocks
    /// ([`FlightLog::shared`]): the plant's states, the controller's torques (if
    /// recorded), the plant's record of the torques it received, the references.
    pub fn shared(&self) -> SharedRecords {
        (
            self.states.shared(),
            self.torques.as_ref().map(FlightLog::shared),
            self.received.shared(),
            self.references.shared(),
        )
    }

    /// The newest state recorded.
    pub fn last_state(&self) -> Option<StateSample> {
        self.states.last().and_then(|k| self.states.get(k))
    }

    /// Hands tick `k`'s samples to `joiner` in the order the live monitor takes them:
    /// the reference, the torque (the controller's record, else the plant's: then it
    /// returns true), the state.
    pub(crate) fn feed(&self, k: u64, joiner: &mut RowJoiner) -> bool {
        // The records hold each tick's sample in that tick's slot, so none is beyond the
        // run; no later state says more than the run's last tick (the tick rule's
        // stand-in).
        let published = || None;
        if let Some(r) = self.references.get(k) {
            joiner.take_reference(r, published);
        }
        let torque = self.torques.as_ref().and_then(|t| t.get(k));
        let from_plant = match (torque, self.received.get(k)) {
            (Some(t), _) => {
                joiner.take_torque(t, published);
                false
            }
            (None, Some(t)) => {
                joiner.take_torque(t, published);
                true
            }
            (None, None) => false,
        };
        if let Some(s) = self.states.get(k) {
            joiner.take_state(s);
        }
        from_plant
    }

    /// The first state's wake-up: where the report's clocks start.
    pub(crate) fn start_ns(&self) -> u64 {
        self.states.get(0).map_or(0, |s| s.wake_ns)
    }

    /// The newest tick any stream recorded (no later tick holds anything).
    pub(crate) fn last_tick(&self) -> u64 {
        let torques = self.torques.as_ref().and_then(FlightLog::last);
        [self.states.last(), self.received.last(), torques, self.references.last()]
            .into_iter()
            .flatten()
            .max()
            .unwrap_or(0)
            .min(self.limit)
    }

    fn summary(&self, dir: &Path, ticks: u64) -> FlightSummary {
        let last = self.last_state().map_or(ticks, |s| s.tick);
        let mut streams = vec![
            StreamSummary::of(Stream::PlantState, &self.states, last),
            StreamSummary::of(Stream::PlantTorque, &self.received, last),
            StreamSummary::of(Stream::Reference, &self.references, last),
        ];
        if let Some(t) = &self.torques {
            streams.insert(2, StreamSummary::of(Stream::ControllerTorque, t, last));
        }
        FlightSummary {
            dir: dir.display().to_string(),
            assembled: true,
            lost: self.lost(ticks),
            streams,
            ..Default::default()
        }
    }

    /// What of a run whose last tick is `ticks` the record lost to a
    /// machine crash (its rings on tmpfs gone) or to damage; `None` where it lost nothing.
    fn lost(&self, ticks: u64) -> Option<LostSummary> {
        // Every ring gone, the segments and journals on disk: what a machine crash leaves
        // (the rings were on tmpfs). One ring gone among others is damage.
        let logs = [self.states.no_ring, self.received.no_ring, self.references.no_ring];
        let crash = logs.iter().all(|n| *n);
        // So is the newest segment torn or empty: what the crash did to the one being
        // written (the journal holds its ticks), damage where the machine did not crash.
        let s = &self.states;
        let (r, f) = (&self.received, &self.references);
        let flags = [(s.damaged, s.no_ring, s.torn_last), (r.damaged, r.no_ring, r.torn_last)];
        let damaged = flags
            .into_iter()
            .chain([(f.damaged, f.no_ring, f.torn_last)])
            .chain(self.torques.iter().map(|t| (t.damaged, t.no_ring, t.torn_last)))
            .any(|(d, n, t)| d || ((n || t) && !crash));
        if !crash && !damaged {
            return None;
        }
        let reason = match (crash, damaged) {
            (true, true) => "machine crash, record damaged",
            (true, false) => "machine crash",
            _ => "record damaged",
        };
        let recorded = self.states.last();
        let count = self.states.count(recorded.unwrap_or(0));
        let count = if recorded.is_some() { count } else { Default::default() };
        let next = recorded.map_or(0, |k| k + 1);
        Some(LostSummary {
            reason,
            last_tick_recorded: recorded,
            ticks: count.missing,
            ranges: count.missing_ranges,
            after_last: (next <= ticks).then_some([next, ticks]),
        })
    }
}

/// Writes the run's files into `out` from `records` (module docs; `trace.csv` and
/// `timing.csv` only with `csv`) and returns the summary, with the live view's part
/// (receive counts, gaps, restarts) taken from the live monitor's joiner `live` when
/// there was a monitor.
pub fn report(
    out: &Path,
    dir: &Path,
    records: &FlightRecords,
    (scenario, role, csv): (&Scenario, &RoleArgs, bool),
    hosts: &Hosts,
    live: Option<&RowJoiner>,
) -> RunSummary {
    let ticks = scenario.ticks();
    let start = records.start_ns();
    let (mut rec, _) = Recording::open(out, scenario, None, (start, None), csv);
    rec.hosts = hosts.clone();
    let mut joiner = RowJoiner::for_scenario(scenario, start);
    let mut flight = records.summary(dir, ticks);
    // Ticks past the newest record hold nothing: a run whose files claim more ticks than
    // were recorded is read as far as it goes, not looped over to its claim.
    for k in 0..=records.last_tick() {
        flight.torques_from_plant += u64::from(records.feed(k, &mut joiner));
        while let Some(row) = joiner.next_row(false) {
            rec.write(&row);
        }
    }
    while let Some(row) = joiner.next_row(true) {
        rec.write(&row);
    }
    let ended = joiner.plant_ended();
    if ended {
        joiner.settle_rest();
    }
    let (files, written) = rec.finish(&scenario.file.name, &fallback_dir(role.domain()));
    let mut s = summary(scenario, role, &joiner, &rec, files);
    s.report_dir = (written != out).then(|| written.display().to_string());
    s.live_rows_lost = 0;
    if let Some(live) = live {
        let monitor = crate::report::monitor_counts(live);
        s.subscribers.extend(monitor);
        s.monitor_kept_up = crate::report::kept_up(live, ticks);
        s.monitor_gaps = live.gaps().to_vec();
        s.monitor_restarts = live.restarts();
        s.live_rows_lost = live.rows_lost();
        crate::report::add_live_rejections(&mut s, live);
    } else {
        s.monitor_kept_up = false;
        s.subscribers.retain(|k, _| !k.starts_with("monitor."));
    }
    s.flight = Some(flight);
    s
}

/// The flight summary of records that could not be used.
pub fn unusable(dir: &Path, e: &FlightError) -> FlightSummary {
    FlightSummary {
        dir: dir.display().to_string(),
        error: Some(e.to_string()),
        ..Default::default()
    }
}

/// The monitor's report at its end: from the flight records in `record` when they can be
/// read (waiting briefly for the records of what it saw), else its live view `rec`
/// (whose files it then finishes, into `fallback` where `out` cannot take them).
pub fn final_report(
    out: &Path,
    record: Option<&Path>,
    fallback: &Path,
    (scenario, role, csv): (&Scenario, &RoleArgs, bool),
    joiner: &RowJoiner,
    mut rec: Recording,
) -> RunSummary {
    if let Some(dir) = record {
        wait_for_records(dir, joiner, role.mode == rotorloop_common::role::args::Mode::Lockstep);
    }
    let records = record.map(|d| (d, FlightRecords::read(d, scenario.ticks())));
    // A stream with no record at all (a recorder that was off): the live view has more.
    if let Some((dir, Ok(records))) = &records
        && records.incomplete().is_none()
    {
        let hosts = rec.hosts.clone();
        drop(rec); // its buffered rows go to disk before the files are rewritten
        return report(out, dir, records, (scenario, role, csv), &hosts, Some(joiner));
    }
    let (files, dir) = rec.finish(&scenario.file.name, fallback);
    let mut s = summary(scenario, role, joiner, &rec, files);
    s.report_dir = (dir != out).then(|| dir.display().to_string());
    let error = match &records {
        Some((dir, Err(e))) => Some((dir, e)),
        Some((dir, Ok(r))) => r.incomplete().map(|e| (dir, e)),
        None => None,
    };
    if let Some((dir, e)) = error {
        eprintln!("monitor: the report is the live view only: {e}");
        s.flight = Some(unusable(dir, e));
    }
    s
}

/// Waits (at most 2 s) until the roles' records hold the newest state and torque the
/// monitor saw: a role records a sample just after publishing it, and a writer preempted
/// between the two would otherwise miss the report by microseconds (seen: a paper run's
/// last state). A writer killed in between never writes it; the bound covers that.
fn wait_for_records(dir: &Path, joiner: &RowJoiner, lockstep: bool) {
    use rotorloop_common::clock::now_ns;
    use rotorloop_common::flight::has_record;
    let until = now_ns() + 2_000_000_000;
    let state = joiner.last_state().map(|s| s.tick);
    let torque = joiner.last_torque().map(|t| t.tick);
    // The controller records a torque after its send, the plant after its wake-up and
    // drain: the monitor can see it before either. In lockstep the plant takes every
    // answer it waits for, so both records come (the controller's where it keeps one);
    // in real time a last torque after the plant's deadline is never in the plant's.
    let has_controller = Stream::ControllerTorque.path(dir).exists();
    let torque_recorded = |k| {
        let plant = has_record::<TorqueSample>(dir, Stream::PlantTorque, k);
        let controller = has_record::<TorqueSample>(dir, Stream::ControllerTorque, k);
        match lockstep {
            true => plant && (controller || !has_controller),
            false => plant || controller,
        }
    };
    let recorded = || {
        state.is_none_or(|k| has_record::<StateSample>(dir, Stream::PlantState, k))
            && torque.is_none_or(torque_recorded)
    };
    while !recorded() && now_ns() < until {
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
}
