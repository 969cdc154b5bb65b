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
use rotorloop_monitor::metrics::Metrics;
use rotorloop_monitor::timing::TimingRow;
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

fn read_timing(dir: &Path) -> anyhow::Result<BTreeMap<u64, TimingRow>> {
    rotorloop_monitor::timing::read(&dir.join("timing.csv"))
        .map_err(|e| bad(dir, &format!("{e:#}")).into())
}

/// A trace row: the whole line, and its torques `u`, `τ`.
type Row = (String, DVec3, DVec3);

/// The trace's header and rows by tick.
fn read_trace(dir: &Path) -> anyhow::Result<(String, BTreeMap<u64, Row>)> {
    let text = std::fs::read_to_string(dir.join("trace.csv"))
        .map_err(|e| bad(dir, &format!("trace.csv: {e}")))?;
    let mut lines = text.lines();
    let header = lines.next().unwrap_or_default().to_owned();
    let cols: Vec<&str> = header.split(',').collect();
    let at = |name: &str| cols.iter().position(|c| *c == name);
    let (Some(u1), Some(tau1), Some(tick)) = (at("u1"), at("tau1"), at("tick")) else {
        return Err(bad(dir, "trace.csv has no u1, tau1 and tick columns").into());
    };
    let mut rows = BTreeMap::new();
    for line in lines {
        let f: Vec<&str> = line.split(',').collect();
        let v = |j: usize| f.get(j).and_then(|x| x.parse::<f64>().ok()).unwrap_or(f64::NAN);
        let k: u64 = f
            .get(tick)
            .and_then(|x| x.parse().ok())
            .ok_or_else(|| bad(dir, "a trace row without a tick"))?;
        let u = DVec3::new(v(u1), v(u1 + 1), v(u1 + 2));
        let tau = DVec3::new(v(tau1), v(tau1 + 1), v(tau1 + 2));
        rows.insert(k, (line.to_owned(), u, tau));
    }
    Ok((header, rows))
}

/// Replays the real-time run in `dir` into `out` (module docs).
pub fn run(dir: &Path, out: &Path) -> anyhow::Result<ReplaySummary> {
    let summary: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("summary.json"))
            .map_err(|e| bad(dir, &format!("summary.json: {e}")))?,
    )
    .map_err(|e| bad(dir, &format!("summary.json: {e}")))?;
    let file = serde_json::from_value(summary["scenario"].clone())
        .map_err(|e| bad(dir, &format!("summary.json has no scenario as run: {e}")))?;
    let scenario = Scenario::from_file(file).map_err(UsageError::from)?;
    let timing = read_timing(dir)?;
    let (header, rows) = read_trace(dir)?;
    let (actuation, dt, ticks) = (scenario.actuation(), scenario.dt(), scenario.ticks());
    let params = scenario.plant_params(actuation);
    let mut body = Body::new(params, scenario.plant_init);
    let mut reference = Reference::for_scenario(&scenario);
    let mut metrics = Metrics::new(params, &body.state()).with_disturbance(scenario.disturbance);
    let limits = scenario.limits_for(actuation);
    let mut line = DelayLine::new(ActuationDelay::Instant, dt);
    let input_of = |k: u64| -> anyhow::Result<BodyInput> {
        let (_, u, tau) = rows.get(&k).ok_or_else(|| {
            bad(dir, &format!("the torque of tick {k} took effect but its trace row is missing"))
        })?;
        Ok(match actuation {
            Actuation::Internal => BodyInput { rotor_torque: *u, body_torque: DVec3::ZERO },
            Actuation::External => BodyInput { rotor_torque: DVec3::ZERO, body_torque: *tau },
        })
    };
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
    // up to its last recorded tick.
    let last = timing.keys().next_back().map_or(ticks, |k| (*k).min(ticks));
    for k in 0..=last {
        let t = k as f64 * dt;
        let x = body.state();
        let rd = reference.sample(t);
        let (u, tau) = rows.get(&k).map_or((DVec3::NAN, DVec3::NAN), |r| (r.1, r.2));
        let u_traced = if actuation == Actuation::Internal { u } else { DVec3::ZERO };
        let mut row = metrics.observe_work(k, t, &x, &rd, u_traced, tau, work);
        if k < last {
            // What happened in tick k, as the state of tick k + 1 recorded it.
            let next = timing
                .get(&(k + 1))
                .ok_or_else(|| bad(dir, &format!("timing.csv has no row for tick {}", k + 1)))?;
            if next.flags & FLAG_SAFE_MODE != 0 {
                line.clear();
            }
            if next.effects > next.recorded().len() as u64 {
                result.unrecorded_effects.push(k);
            }
            for (source, offset) in next.recorded() {
                line.schedule(k, *offset, *source, input_of(*source)?);
            }
            let step = integrate_tick(&mut body, &mut line, k, &limits, scenario.disturbance);
            work = step.work;
            row.delay_s = step.effects.first_delay_s(k, dt);
        }
        reference.step(t, dt);
        trace.write(&row)?;
        result.rows += 1;
    }
    let mut file = trace.finish()?;
    file.flush()?;
    drop(file);
    // Compare with the run's trace, row by row.
    let (replayed_header, replayed) = read_trace(out)?;
    let mut first = (replayed_header != header).then_some(0);
    for (k, (line, _, _)) in &rows {
        if first.is_none() && replayed.get(k).map(|r| &r.0) != Some(line) {
            first = Some(*k);
        }
    }
    result.first_difference = first;
    result.identical = first.is_none() && replayed.len() == rows.len();
    let text = serde_json::to_string_pretty(&result)?;
    std::fs::write(out.join("replay.json"), text + "\n")
        .with_context(|| format!("cannot write {}", out.display()))?;
    Ok(result)
}
