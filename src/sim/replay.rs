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

use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

use anyhow::Context;
use glam::DVec3;
use rotorloop_common::scenario::{Actuation, Scenario};
use rotorloop_common::wire::FLAG_SAFE_MODE;
use rotorloop_monitor::derive::Csv;
use rotorloop_monitor::metrics::Metrics;
use rotorloop_monitor::rows::TickRows;
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
    /// Whether the replayed trace equals the run's, byte for byte.
    pub identical: bool,
    /// The first row (tick) that differs, if any.
    pub first_difference: Option<u64>,
    /// Ticks in which more torques took effect than `timing.csv` records (not replayable).
    pub unrecorded_effects: Vec<u64>,
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

/// `trace.csv` read once, in tick order: each tick's torques for the replay's row, and the
/// torques of the last [`SOURCES_KEPT`] rows passed, where the tick whose torque took
/// effect is looked up (an effect's source is at or before the tick it takes effect in).
/// It is also what the replayed rows are compared with, as they are written.
struct Trace {
    rows: TickRows,
    columns: (usize, usize),
    recent: BTreeMap<u64, Torques>,
    /// The newest row passed: its tick and line.
    newest: Option<(u64, String)>,
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
            let Some((t, line)) = self.rows.next_row() else { break };
            self.recent.insert(t, torques_of(&line, self.columns));
            if self.recent.len() > SOURCES_KEPT {
                self.recent.pop_first();
            }
            self.newest = Some((t, line));
            self.taken += 1;
        }
        self.recent.get(&k).copied()
    }

    /// The run's line of tick `k`, the last asked for with [`Self::row`], if it has one.
    fn line(&self, k: u64) -> Option<&str> {
        self.newest.as_ref().filter(|(t, _)| *t == k).map(|(_, l)| l.as_str())
    }

    /// What the torque of tick `j` (at or before the last row asked for) put on the body.
    fn input(&self, dir: &Path, j: u64, actuation: Actuation) -> anyhow::Result<BodyInput> {
        let (u, tau) = self.recent.get(&j).copied().ok_or_else(|| {
            bad(dir, &format!("the torque of tick {j} took effect but its trace row is missing"))
        })?;
        Ok(match actuation {
            Actuation::Internal => BodyInput { rotor_torque: u, body_torque: DVec3::ZERO },
            Actuation::External => BodyInput { rotor_torque: DVec3::ZERO, body_torque: tau },
        })
    }
}

/// The replayed trace against the run's, a row at a time as the replay writes it.
#[derive(Debug)]
struct Comparison {
    /// The first tick whose row is not the run's (0: the headers differ).
    first: Option<u64>,
}

impl Comparison {
    /// Replayed row `k` (`line`, with its line end) against the run's.
    fn row(&mut self, k: u64, line: &[u8], run: &Trace) {
        let ours = line.strip_suffix(b"\n").unwrap_or(line);
        if run.line(k).is_some_and(|l| l.as_bytes() != ours) && self.first.is_none() {
            self.first = Some(k);
        }
    }

    /// The run's rows after the replay's last: each is a row the replay does not have.
    /// Gives the run's rows in all (those skipped as out of order included).
    fn finish(&mut self, mut run: Trace) -> u64 {
        while let Some((t, _)) = run.rows.next_row() {
            run.taken += 1;
            self.first.get_or_insert(t);
        }
        run.taken + run.rows.skipped
    }
}

/// Replays the real-time run in `dir` into `out` (module docs): its `trace.csv` where
/// `write_trace`, and `replay.json`.
pub fn run(dir: &Path, out: &Path, write_trace: bool) -> anyhow::Result<ReplaySummary> {
    let summary: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("summary.json"))
            .map_err(|e| bad(dir, &format!("summary.json: {e}")))?,
    )
    .map_err(|e| bad(dir, &format!("summary.json: {e}")))?;
    let scenario = Scenario::of_summary(&summary).map_err(|e| bad(dir, &e))?;
    let timing_err = |e: anyhow::Error| -> anyhow::Error { bad(dir, &format!("{e:#}")).into() };
    let mut timing = rotorloop_monitor::derive::timing_rows(dir).map_err(timing_err)?;
    let rows = rotorloop_monitor::derive::run_rows(dir, Csv::Trace)
        .map_err(|e| bad(dir, &format!("trace.csv: {e:#}")))?;
    let columns = torque_columns(dir, rows.header())?;
    let mut compared =
        Comparison { first: (rows.header() != rotorloop_monitor::trace::HEADER).then_some(0) };
    let mut run_trace = Trace { rows, columns, recent: BTreeMap::new(), newest: None, taken: 0 };
    let (actuation, dt, ticks) = (scenario.actuation(), scenario.dt(), scenario.ticks());
    let params = scenario.plant_params(actuation);
    let mut body = Body::new(params, scenario.plant_init);
    let mut reference = Reference::for_scenario(&scenario);
    let mut metrics = Metrics::new(params, &body.state()).with_disturbance(scenario.disturbance);
    let limits = scenario.limits_for(actuation);
    let mut line = DelayLine::new(ActuationDelay::Instant, dt);
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let mut file: std::io::BufWriter<Box<dyn Write>> = std::io::BufWriter::new(if write_trace {
        Box::new(
            std::fs::File::create(out.join("trace.csv"))
                .with_context(|| format!("cannot write {}", out.join("trace.csv").display()))?,
        )
    } else {
        Box::new(std::io::sink())
    });
    writeln!(file, "{}", rotorloop_monitor::trace::HEADER)?;
    let mut written = Vec::new();
    let mut result = ReplaySummary {
        run: dir.display().to_string(),
        rows: 0,
        identical: true,
        first_difference: None,
        unrecorded_effects: Vec::new(),
    };
    let mut work = 0.0;
    // A run that ended early (its launcher killed, then `rotorloop recover`) is replayed
    // up to its last recorded tick: the tick with no timing row after it (a timing.csv
    // without rows is refused at tick 1).
    let no_timing = timing.is_empty();
    for k in 0..=ticks {
        let t = k as f64 * dt;
        let x = body.state();
        let rd = reference.sample(t);
        let (u, tau) = run_trace.row(k).unwrap_or((DVec3::NAN, DVec3::NAN));
        let u_traced = if actuation == Actuation::Internal { u } else { DVec3::ZERO };
        let mut row = metrics.observe_work(k, t, &x, &rd, u_traced, tau, work);
        let last = k == ticks || (!no_timing && !timing.more_after(k));
        if !last {
            // What happened in tick k, as the state of tick k + 1 recorded it.
            let next = timing
                .row(k + 1)
                .map_err(timing_err)?
                .ok_or_else(|| bad(dir, &format!("timing.csv has no row for tick {}", k + 1)))?;
            if next.flags & FLAG_SAFE_MODE != 0 {
                line.clear();
            }
            if next.effects > next.recorded().len() as u64 {
                result.unrecorded_effects.push(k);
            }
            for (source, offset) in next.recorded() {
                line.schedule(k, *offset, *source, run_trace.input(dir, *source, actuation)?);
            }
            let step = integrate_tick(&mut body, &mut line, k, &limits, scenario.disturbance);
            work = step.work;
            row.delay_s = step.effects.first_delay_s(k, dt);
        }
        reference.step(t, dt);
        written.clear();
        TraceWriter::append(&mut written).write(&row)?;
        compared.row(k, &written, &run_trace);
        file.write_all(&written)?;
        result.rows += 1;
        if last {
            break;
        }
    }
    file.flush()?;
    drop((file, timing));
    let rows = compared.finish(run_trace);
    result.first_difference = compared.first;
    result.identical = compared.first.is_none() && result.rows == rows;
    let text = serde_json::to_string_pretty(&result)?;
    std::fs::write(out.join("replay.json"), text + "\n")
        .with_context(|| format!("cannot write {}", out.display()))?;
    Ok(result)
}
