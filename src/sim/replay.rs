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
struct Trace {
    rows: TickRows,
    columns: (usize, usize),
    recent: BTreeMap<u64, Torques>,
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
        }
        self.recent.get(&k).copied()
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

/// Compares the replayed trace with the run's, a row at a time: the first tick whose row
/// differs (0 for the header), and the rows of each.
fn compare(dir: &Path, out: &Path) -> anyhow::Result<(Option<u64>, u64, u64)> {
    let open = |rows: anyhow::Result<TickRows>| rows.map_err(|e| bad(dir, &format!("{e:#}")));
    let run = open(rotorloop_monitor::derive::run_rows(dir, Csv::Trace))?;
    let (mut run, mut replayed) = (run, open(TickRows::open(&out.join("trace.csv")))?);
    let mut first = (run.header() != replayed.header()).then_some(0);
    let (mut rows, mut replayed_rows) = (0u64, 0u64);
    while let Some((k, line)) = run.next_row() {
        rows += 1;
        while replayed.peek_tick().is_some_and(|t| t < k) {
            replayed.next_row();
            replayed_rows += 1;
        }
        let same = replayed.row(k).is_some_and(|l| {
            replayed_rows += 1;
            l == line
        });
        if !same && first.is_none() {
            first = Some(k);
        }
    }
    while replayed.next_row().is_some() {
        replayed_rows += 1;
    }
    Ok((first, rows + run.skipped, replayed_rows))
}

/// Replays the real-time run in `dir` into `out` (module docs).
pub fn run(dir: &Path, out: &Path) -> anyhow::Result<ReplaySummary> {
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
    let mut run_trace = Trace { rows, columns, recent: BTreeMap::new() };
    let (actuation, dt, ticks) = (scenario.actuation(), scenario.dt(), scenario.ticks());
    let params = scenario.plant_params(actuation);
    let mut body = Body::new(params, scenario.plant_init);
    let mut reference = Reference::for_scenario(&scenario);
    let mut metrics = Metrics::new(params, &body.state()).with_disturbance(scenario.disturbance);
    let limits = scenario.limits_for(actuation);
    let mut line = DelayLine::new(ActuationDelay::Instant, dt);
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let mut trace = TraceWriter::new(std::io::BufWriter::new(
        std::fs::File::create(out.join("trace.csv"))
            .with_context(|| format!("cannot write {}", out.join("trace.csv").display()))?,
    ))?;
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
        trace.write(&row)?;
        result.rows += 1;
        if last {
            break;
        }
    }
    let mut file = trace.finish()?;
    file.flush()?;
    drop(file);
    // The run's rows read so far are done with: their readers go before the comparison
    // opens its own (three sets of readers at once made the replay's peak).
    drop((timing, run_trace));
    // Compare with the run's trace, row by row.
    let (first, rows, replayed) = compare(dir, out)?;
    result.first_difference = first;
    result.identical = first.is_none() && replayed == rows;
    let text = serde_json::to_string_pretty(&result)?;
    std::fs::write(out.join("replay.json"), text + "\n")
        .with_context(|| format!("cannot write {}", out.display()))?;
    Ok(result)
}
