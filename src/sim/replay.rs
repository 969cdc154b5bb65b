//! `rotorloop sim --replay DIR`: a finished real-time run again, in process. The plant is
//! integrated with each torque taking effect in the tick and at the offset the real plant
//! recorded (`timing.csv`: the torques that took effect in each tick and when; safe mode
//! from the state flags), the torques being the controller's own answers as the trace
//! recorded them (shortest round-trip decimals: bit for bit), through the same
//! [`integrate_tick`] and actuator limits. The reference and the metrics are recomputed.
//! If the physics of the run is what rotorloop says it is, the replayed `trace.csv` is
//! the run's, byte for byte; the replay says whether it is, and where it first is not.
//!
//! The run's `trace.csv` and `timing.csv` are assembled from the roles' flight records
//! (`common::flight`), so they have every tick whatever was killed, the monitor included.
//! What a replay cannot know: the actuator limits applied again after a plant restart
//! (the restart resumes the limited torque), which matters only where a saturated torque
//! was held across the kill. Such a run replays up to it, and says at which tick it first
//! differs; a run without a row the replay needs is refused naming the tick.

use std::cell::RefCell;
use std::collections::{BTreeMap, VecDeque};
use std::io::Write;
use std::path::Path;
use std::rc::Rc;

use anyhow::Context;
use glam::DVec3;
use rotorloop_common::scenario::Actuation;
use rotorloop_common::wire::FLAG_SAFE_MODE;
use rotorloop_monitor::derive::{Csv, DerivedRows};
use rotorloop_monitor::metrics::{Metrics, TraceRow};
use rotorloop_monitor::rows::TickRows;
use rotorloop_monitor::summary::Summary;
use rotorloop_monitor::timing::{TimingRow, TimingRows};
use rotorloop_monitor::trace::TraceWriter;
use rotorloop_plant::actuator::{ActuationDelay, DelayLine, integrate_tick};
use rotorloop_plant::{Body, BodyInput};
use rotorloop_reference::Reference;
use serde::Serialize;

use rotorloop_common::role::UsageError;

/// What a replay found.
#[derive(Debug, Clone, Serialize)]
pub struct ReplaySummary {
    /// The run replayed.
    pub run: String,
    /// Rows replayed.
    pub rows: u64,
    /// Whether the replayed trace equals the run's, byte for byte (where the replay
    /// [`stopped`](Self::stopped) at a hole of the record: its rows up to there).
    pub identical: bool,
    /// The first row (tick) that differs, if any.
    pub first_difference: Option<u64>,
    /// Ticks in which more torques took effect than `timing.csv` records (not replayable).
    pub unrecorded_effects: Vec<u64>,
    /// The tick after which the replay stopped because the run has no record of what
    /// happened next (a file of its record missing or damaged: its rows are missing),
    /// and why; the rows before it are compared. Absent where it replayed every row.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stopped: Option<Stopped>,
}

/// Where and why a replay stopped before the run's last row ([`ReplaySummary::stopped`]).
#[derive(Debug, Clone, Serialize)]
pub struct Stopped {
    /// The last tick replayed.
    pub after_tick: u64,
    /// What was missing, in words.
    pub why: String,
}

impl ReplaySummary {
    /// One line for the console.
    pub fn describe(&self) -> String {
        match (self.identical, self.first_difference) {
            (true, _) => {
                format!("replay of {}: {} rows, identical byte for byte", self.run, self.rows)
            }
            (false, Some(k)) => {
                format!("replay of {}: {} rows, first difference at tick {k}", self.run, self.rows)
            }
            (false, None) => {
                format!("replay of {}: {} rows, not the same length", self.run, self.rows)
            }
        }
    }
}

fn bad(dir: &Path, what: &str) -> UsageError {
    UsageError(format!("--replay {}: {what}", dir.display()))
}

/// A trace row's torques `u`, `τ`.
type Torques = (DVec3, DVec3);

/// The columns of `u1` and `tau1` in a trace header.
fn torque_columns(dir: &Path, header: &str) -> anyhow::Result<(usize, usize)> {
    let cols: Vec<&str> = header.split(',').collect();
    let at = |name: &str| cols.iter().position(|c| *c == name);
    match (at("u1"), at("tau1")) {
        (Some(u1), Some(tau1)) => Ok((u1, tau1)),
        _ => Err(bad(dir, "trace.csv has no u1, tau1 and tick columns").into()),
    }
}

/// The torques of a trace line.
fn torques_of(line: &str, (u1, tau1): (usize, usize)) -> Torques {
    let f: Vec<&str> = line.split(',').collect();
    let v = |j: usize| f.get(j).and_then(|x| x.parse::<f64>().ok()).unwrap_or(f64::NAN);
    (DVec3::new(v(u1), v(u1 + 1), v(u1 + 2)), DVec3::new(v(tau1), v(tau1 + 1), v(tau1 + 2)))
}

/// A run's rows derived from its records once for both readers, the trace's and the
/// timing's (a run made with `--no-csv`, neither file written): each row waits in its
/// reader's queue until taken, so what is held is the one row the timing reads ahead.
struct Joint {
    rows: DerivedRows,
    trace: VecDeque<TraceRow>,
    timing: VecDeque<TimingRow>,
}

impl Joint {
    /// Derives the next row into both queues; false after the last.
    fn pull(&mut self) -> bool {
        let Some((t, m)) = self.rows.next_pair() else { return false };
        self.trace.push_back(t);
        self.timing.push_back(m);
        true
    }

    fn peek_trace(&mut self) -> Option<u64> {
        if self.trace.is_empty() && !self.pull() {
            return None;
        }
        self.trace.front().map(|r| r.tick)
    }

    fn peek_timing(&mut self) -> Option<u64> {
        if self.timing.is_empty() && !self.pull() {
            return None;
        }
        self.timing.front().map(|r| r.tick)
    }
}

type Shared = Rc<RefCell<Joint>>;

/// A row of the run's trace: its line in `trace.csv`, or its values derived.
enum RunRow {
    Line(String),
    Derived(Box<TraceRow>),
}

/// The run's trace rows in tick order: `trace.csv`'s (or derived and formatted, where
/// only that file is missing), or derived with the timing's ([`Joint`]).
enum RunTrace {
    Lines(TickRows),
    Derived(Shared),
}

impl RunTrace {
    fn peek_tick(&mut self) -> Option<u64> {
        match self {
            Self::Lines(rows) => rows.peek_tick(),
            Self::Derived(j) => j.borrow_mut().peek_trace(),
        }
    }

    fn next_row(&mut self) -> Option<(u64, RunRow)> {
        match self {
            Self::Lines(rows) => rows.next_row().map(|(t, l)| (t, RunRow::Line(l))),
            Self::Derived(j) => {
                let mut j = j.borrow_mut();
                j.peek_trace()?;
                j.trace.pop_front().map(|r| (r.tick, RunRow::Derived(Box::new(r))))
            }
        }
    }

    /// Rows passed over as out of order (a file's).
    fn skipped(&self) -> u64 {
        match self {
            Self::Lines(rows) => rows.skipped,
            Self::Derived(_) => 0,
        }
    }
}

/// The run's timing rows in tick order: `timing.csv`'s (or derived and formatted, where
/// only that file is missing), or derived with the trace's ([`Joint`]).
enum RunTiming {
    File(TimingRows),
    Derived(Shared),
}

impl RunTiming {
    fn is_empty(&mut self) -> bool {
        match self {
            Self::File(t) => t.is_empty(),
            Self::Derived(j) => j.borrow_mut().peek_timing().is_none(),
        }
    }

    /// Whether a row of a tick after `k` follows (rows up to `k` are passed over).
    fn more_after(&mut self, k: u64) -> bool {
        match self {
            Self::File(t) => t.more_after(k),
            Self::Derived(j) => {
                let mut j = j.borrow_mut();
                while j.peek_timing().is_some_and(|t| t <= k) {
                    j.timing.pop_front();
                }
                j.peek_timing().is_some()
            }
        }
    }

    /// The row of tick `k` (ticks asked for in increasing order); a derived row is held to
    /// what its line would have to be to parse (its effects' offsets numbers).
    fn row(&mut self, k: u64) -> anyhow::Result<Option<TimingRow>> {
        let j = match self {
            Self::File(t) => return t.row(k),
            Self::Derived(j) => j,
        };
        let mut j = j.borrow_mut();
        while j.peek_timing().is_some_and(|t| t < k) {
            j.timing.pop_front();
        }
        if j.peek_timing() != Some(k) {
            return Ok(None);
        }
        let row = j.timing.pop_front();
        if let Some(i) = row.iter().flat_map(|r| r.recorded()).position(|(_, o)| !o.is_finite()) {
            anyhow::bail!(
                "timing.csv (derived) tick {k}: effect{}_offset_s is not a number",
                i + 1
            );
        }
        Ok(row)
    }
}

/// The run's trace read once, in tick order: each tick's torques for the replay's row, and
/// the torques of the last [`SOURCES_KEPT`] rows passed, where the tick whose torque took
/// effect is looked up (an effect's source is at or before the tick it takes effect in).
/// It is also what the replayed rows are compared with, as they are written.
struct Trace {
    rows: RunTrace,
    columns: (usize, usize),
    recent: BTreeMap<u64, Torques>,
    /// The newest row passed: its tick and row.
    newest: Option<(u64, RunRow)>,
    /// Rows passed.
    taken: u64,
}

/// Trace rows a [`Trace`] keeps behind its position.
const SOURCES_KEPT: usize = 256;

impl Trace {
    /// The torques of tick `k`'s row, if it has one (ticks asked for in increasing order);
    /// the rows up to it are kept as sources.
    fn row(&mut self, k: u64) -> Option<Torques> {
        while self.rows.peek_tick().is_some_and(|t| t <= k) {
            let Some((t, row)) = self.rows.next_row() else { break };
            let torques = match &row {
                RunRow::Line(line) => torques_of(line, self.columns),
                RunRow::Derived(r) => (DVec3::from_array(r.u), DVec3::from_array(r.tau)),
            };
            self.recent.insert(t, torques);
            if self.recent.len() > SOURCES_KEPT {
                self.recent.pop_first();
            }
            self.newest = Some((t, row));
            self.taken += 1;
        }
        self.recent.get(&k).copied()
    }

    /// The run's row of tick `k`, the last asked for with [`Self::row`], if it has one.
    fn newest(&self, k: u64) -> Option<&RunRow> {
        self.newest.as_ref().filter(|(t, _)| *t == k).map(|(_, r)| r)
    }

    /// Whether its rows are lines (compared as text) rather than values.
    fn is_text(&self) -> bool {
        matches!(self.rows, RunTrace::Lines(_))
    }

    /// What the torque of tick `j` (at or before the last row asked for) put on the body.
    fn input(&self, dir: &Path, j: u64, actuation: Actuation) -> anyhow::Result<BodyInput> {
        let (u, tau) = self.recent.get(&j).copied().ok_or_else(|| {
            bad(dir, &format!("the torque of tick {j} took effect but its trace row is missing"))
        })?;
        let used = if actuation == Actuation::Internal { u } else { tau };
        if !used.is_finite() {
            // The plant applies only finite torques: the record lost this one.
            anyhow::bail!("the torque of tick {j} took effect but the record lost it");
        }
        Ok(BodyInput::of(actuation, u, tau))
    }
}

/// The replayed trace against the run's, a row at a time as the replay writes it.
#[derive(Debug)]
struct Comparison {
    /// The first tick whose row is not the run's (0: the headers differ).
    first: Option<u64>,
}

impl Comparison {
    /// Replayed row `k` against the run's: as text (`line`, with its line end, written
    /// where the run's rows are lines), or as values, every float the same bits (or both
    /// NaN), which is the same as their lines being the same (each float is written in its
    /// shortest round-trip form, and every NaN as `NaN`).
    fn row(&mut self, k: u64, row: &TraceRow, line: &[u8], run: &Trace) {
        let same = match run.newest(k) {
            None => true,
            Some(RunRow::Line(l)) => l.as_bytes() == line.strip_suffix(b"\n").unwrap_or(line),
            Some(RunRow::Derived(r)) => same_values(r, row),
        };
        if !same && self.first.is_none() {
            self.first = Some(k);
        }
    }

    /// The run's rows after the replay's last: each is a row the replay does not have
    /// (but where it `stopped` at a hole of the record: those are not compared). Gives
    /// the run's rows in all (those skipped as out of order included).
    fn finish(&mut self, mut run: Trace, stopped: bool) -> u64 {
        while let Some((t, _)) = run.rows.next_row() {
            run.taken += 1;
            if !stopped {
                self.first.get_or_insert(t);
            }
        }
        run.taken + run.rows.skipped()
    }
}

/// Whether two trace rows would be written as the same line.
fn same_values(a: &TraceRow, b: &TraceRow) -> bool {
    let (a, b) = (rotorloop_monitor::trace::values(a), rotorloop_monitor::trace::values(b));
    a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()))
}

/// The replay's `trace.csv` in `out` (made), or nowhere.
fn trace_file(out: &Path, write_trace: bool) -> anyhow::Result<std::io::BufWriter<Box<dyn Write>>> {
    let made = rotorloop_common::outdir::OutDir::make(out)?;
    Ok(std::io::BufWriter::new(if write_trace {
        Box::new(
            made.create("trace.csv")
                .with_context(|| format!("cannot write {}", out.join("trace.csv").display()))?,
        )
    } else {
        Box::new(std::io::sink())
    }))
}

/// A tick's timing row and the inputs its effects schedule (source tick, offset, input).
type Effects = (TimingRow, Vec<(u64, f64, BodyInput)>);

/// The timing row `next` of the tick after the one replayed, with the input each of its
/// effects schedules; why not where the record lacks either (`None`: the row).
fn effects(
    next: Option<TimingRow>,
    run: &Trace,
    dir: &Path,
    actuation: Actuation,
) -> Result<Effects, Option<String>> {
    let next = next.ok_or(None)?;
    let inputs = next
        .recorded()
        .iter()
        .map(|(s, o)| Ok((*s, *o, run.input(dir, *s, actuation)?)))
        .collect::<anyhow::Result<Vec<_>>>()
        .map_err(|e| Some(format!("{e:#}")))?;
    Ok((next, inputs))
}

/// The run's trace and timing rows and the trace's header: its files, each derived from
/// the records where it is missing, and both derived once together where neither is
/// there (a run made with `--no-csv`).
fn run_rows(dir: &Path) -> anyhow::Result<(RunTrace, RunTiming, String)> {
    let missing = |c: Csv| !dir.join(c.name()).exists();
    if missing(Csv::Trace) && missing(Csv::Timing) {
        let rows = DerivedRows::of_run(dir).context("trace.csv and timing.csv")?;
        let joint =
            Rc::new(RefCell::new(Joint { rows, trace: VecDeque::new(), timing: VecDeque::new() }));
        let header = rotorloop_monitor::trace::HEADER.to_owned();
        return Ok((RunTrace::Derived(joint.clone()), RunTiming::Derived(joint), header));
    }
    let timing = rotorloop_monitor::derive::timing_rows(dir)?;
    let rows = rotorloop_monitor::derive::run_rows(dir, Csv::Trace)
        .map_err(|e| anyhow::anyhow!("trace.csv: {e:#}"))?;
    let header = rows.header().to_owned();
    Ok((RunTrace::Lines(rows), RunTiming::File(timing), header))
}

/// Replays the real-time run in `dir` into `out` (module docs): its `trace.csv` where
/// `write_trace`, and `replay.json`.
pub fn run(dir: &Path, out: &Path, write_trace: bool) -> anyhow::Result<ReplaySummary> {
    let summary = Summary::read(dir).map_err(|e| bad(dir, &e.to_string()))?;
    let scenario = summary.scenario().map_err(|e| bad(dir, &e))?;
    let timing_err = |e: anyhow::Error| -> anyhow::Error { bad(dir, &format!("{e:#}")).into() };
    let (rows, mut timing, header) = run_rows(dir).map_err(timing_err)?;
    let columns = torque_columns(dir, &header)?;
    let mut compared =
        Comparison { first: (header != rotorloop_monitor::trace::HEADER).then_some(0) };
    let mut run_trace = Trace { rows, columns, recent: BTreeMap::new(), newest: None, taken: 0 };
    let (actuation, dt, ticks) = (scenario.actuation(), scenario.dt(), scenario.ticks());
    let params = scenario.plant_params(actuation);
    let mut body = Body::new(params, scenario.plant_init);
    let mut reference = Reference::for_scenario(&scenario);
    let mut metrics = Metrics::new(params, &body.state()).with_disturbance(scenario.disturbance);
    let limits = scenario.limits_for(actuation);
    let mut line = DelayLine::new(ActuationDelay::Instant, dt);
    let mut file = trace_file(out, write_trace)?;
    writeln!(file, "{}", rotorloop_monitor::trace::HEADER)?;
    let mut written = Vec::new();
    let mut result = ReplaySummary {
        run: dir.display().to_string(),
        rows: 0,
        identical: true,
        first_difference: None,
        unrecorded_effects: Vec::new(),
        stopped: None,
    };
    let mut work = 0.0;
    // A run that ended early (its launcher killed, then `rotorloop recover`) is replayed
    // up to its last recorded tick: the tick with no timing row after it (a timing.csv
    // without rows is refused at tick 1).
    let no_timing = timing.is_empty();
    let lost = summary.flight.as_ref().and_then(|f| f.lost.as_ref()).map(|l| l.reason.as_str());
    for k in 0..=ticks {
        let t = k as f64 * dt;
        let x = body.state();
        let rd = reference.sample(t);
        let (u, tau) = run_trace.row(k).unwrap_or((DVec3::NAN, DVec3::NAN));
        let u_traced = if actuation == Actuation::Internal { u } else { DVec3::ZERO };
        let mut row = metrics.observe_work(k, t, &x, &rd, u_traced, tau, work);
        let last = k == ticks || (!no_timing && !timing.more_after(k));
        if let Some(reason) = lost.filter(|_| last && k > 0 && k < ticks) {
            // The record lost what came after tick k (its summary says so), the timing row
            // of tick k + 1 among it: what took effect in tick k, and so its row's delay,
            // is unknown. The rows before it are compared.
            let why = format!("the record has no timing row after tick {k} ({reason})");
            result.stopped = Some(Stopped { after_tick: k - 1, why });
            break;
        }
        if !last {
            // What happened in tick k, as the state of tick k + 1 recorded it. A run whose
            // record lacks it (a file missing or damaged) is replayed up to here.
            let next = timing.row(k + 1).map_err(timing_err)?;
            match effects(next, &run_trace, dir, actuation) {
                Ok((next, inputs)) => {
                    if next.flags & FLAG_SAFE_MODE != 0 {
                        line.clear();
                    }
                    if next.effects > next.recorded().len() as u64 {
                        result.unrecorded_effects.push(k);
                    }
                    for (source, offset, input) in inputs {
                        line.schedule(k, offset, source, input);
                    }
                    let step =
                        integrate_tick(&mut body, &mut line, k, &limits, scenario.disturbance);
                    work = step.work;
                    row.delay_s = step.effects.first_delay_s(k, dt);
                }
                Err(_) if no_timing => {
                    // Nothing of the run's timing: nothing to replay.
                    return Err(bad(dir, "timing.csv has no row for tick 1").into());
                }
                Err(why) => {
                    let why =
                        why.unwrap_or_else(|| format!("timing.csv has no row for tick {}", k + 1));
                    // Row k's delay (what took effect in tick k) is unknown too: the rows
                    // before it are compared.
                    let Some(after_tick) = k.checked_sub(1) else {
                        return Err(bad(dir, &format!("nothing to replay: {why}")).into());
                    };
                    eprintln!("replay: stopped after tick {after_tick}: {why}");
                    result.stopped = Some(Stopped { after_tick, why });
                    break;
                }
            }
        }
        reference.step(t, dt);
        written.clear();
        // Formatting is most of a replay's time: only for a file, or a run's lines.
        if write_trace || run_trace.is_text() {
            TraceWriter::append(&mut written).write(&row)?;
        }
        compared.row(k, &row, &written, &run_trace);
        file.write_all(&written)?;
        result.rows += 1;
        if last {
            break;
        }
    }
    file.flush()?;
    drop((file, timing));
    let rows = compared.finish(run_trace, result.stopped.is_some());
    result.first_difference = compared.first;
    // A replay that stopped at a hole of the record compares the rows before it. A trace
    // short of rows otherwise is not the run's.
    result.identical =
        compared.first.is_none() && (result.rows == rows || result.stopped.is_some());
    let text = serde_json::to_string_pretty(&result)?;
    rotorloop_common::outdir::write_file(&out.join("replay.json"), text + "\n")
        .with_context(|| format!("cannot write {}", out.display()))?;
    Ok(result)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A run's trace whose newest row is `row` (derived) at tick `k`.
    fn run_at(k: u64, row: TraceRow) -> Trace {
        let header = rotorloop_monitor::trace::HEADER.to_owned();
        let lines = TickRows::of_lines(Box::new(std::iter::empty()), header, "test").expect("rows");
        Trace {
            rows: RunTrace::Lines(lines),
            columns: (0, 0),
            recent: BTreeMap::new(),
            newest: Some((k, RunRow::Derived(Box::new(row)))),
            taken: 0,
        }
    }

    /// Compared as values, a replayed row is the run's where it would be written as the same
    /// line: the same bits, or NaN against any NaN; a float one ulp apart, or 0 against −0,
    /// is the first difference.
    #[test]
    fn derived_rows_compare_as_their_lines_would() {
        let row =
            TraceRow { tick: 7, t: 0.007, err_deg: 1.5, delay_s: f64::NAN, ..TraceRow::default() };
        let text = |r: &TraceRow| {
            let mut l = Vec::new();
            TraceWriter::append(&mut l).write(r).expect("vec");
            l
        };
        let mut other_nan = row;
        other_nan.delay_s = -f64::NAN;
        let mut ulp = row;
        ulp.err_deg = f64::from_bits(row.err_deg.to_bits() + 1);
        let mut zero = row;
        zero.werr = -0.0;
        for (replayed, same) in [(row, true), (other_nan, true), (ulp, false), (zero, false)] {
            assert_eq!(text(&replayed) == text(&row), same, "the lines");
            let mut c = Comparison { first: None };
            c.row(7, &replayed, &[], &run_at(7, row));
            assert_eq!(c.first.is_none(), same, "{replayed:?}");
            // A tick the run has no row of is not compared.
            let mut c = Comparison { first: None };
            c.row(8, &replayed, &[], &run_at(7, row));
            assert_eq!(c.first, None);
        }
    }
}
