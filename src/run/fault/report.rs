//! The fault report of `rotorloop run --fault`: for each fault, what it cost, computed
//! after the run from the monitor's `trace.csv` and `timing.csv` and an in-process
//! no-fault run of the same scenario; added to `summary.json` as `faults`, and drawn in
//! `faults.png`.

use std::collections::BTreeMap;
use std::path::Path;

use rotorloop_common::scenario::Scenario;
use rotorloop_monitor::plot::{Series, YScale, line_chart};
use rotorloop_monitor::summary::{SummaryError, read_json};
use serde::Serialize;

use crate::run::fault::FaultEvent;
use crate::sim::closed_loop::ClosedLoop;
use rotorloop_monitor::timing::TimingRow;

/// One fault's cost.
#[derive(Debug, Clone, Serialize)]
pub struct FaultReport {
    /// The role.
    pub role: String,
    /// `kill` (injected by `--fault`), `stop` (a SIGSTOP or another stop signal, from
    /// `--fault` or from anyone else: the detail says which); `killed` (SIGKILL by anyone else),
    /// `crash` (another signal or a non-zero exit), `exited` (a clean exit restarted by
    /// `--restart always`), `hang` (the watchdog found it making no progress) or
    /// `link-lost` (split: after this role's restart the plant received no torque within
    /// the start timeout; the run was stopped).
    pub kind: &'static str,
    /// What happened, in words: the exit status, what the watchdog and the supervisor did.
    pub detail: String,
    /// Kill time, s of the run: in lockstep the time of `kill_tick` (the run's clock is
    /// the plant's ticks, many times faster than the wall's there); in real time the wall
    /// time since the first tick was published (if none was, since the launch).
    pub kill_s: f64,
    /// Restart time (s, as `kill_s`), if restarted; for a stop, when it was continued.
    pub restart_s: Option<f64>,
    /// The signal, where it is known (`SIGKILL`, `SIGSTOP`, `SIGTSTP`, …).
    pub signal: Option<&'static str>,
    /// How a stop ended: `continued`, `killed`, `crash`, `exited`, `hung` (the watchdog
    /// killed it), or `still stopped when the launcher ended`.
    pub ended: Option<&'static str>,
    /// When a stop ended (s, as `kill_s`).
    pub ended_s: Option<f64>,
    /// Newest tick published before the kill.
    pub kill_tick: Option<u64>,
    /// First tick published after the restart (or the continue), if any.
    pub restart_tick: Option<u64>,
    /// Ticks after the kill whose preceding torque was not fresh (held or safe mode).
    pub ticks_without_fresh_torque: u64,
    /// Ticks from the restart to the first fresh torque applied.
    pub ticks_to_first_fresh_torque: Option<u64>,
    /// What the fault cost the control: the peak attitude deviation of the run from the
    /// loop that had no incident, over the incident that holds the fault (deg; 0 where the
    /// loop did not feel it, a monitor's kill say). Filled in by the run's incidents
    /// (`crate::pipeline::incidents`); `None` where they could not be computed.
    pub peak_deviation_deg: Option<f64>,
    /// From the incident's start until that deviation is below 10 % of its peak (s);
    /// `None`: not within the run.
    pub recovery_s: Option<f64>,
    /// The incident that holds the fault (its row in `incidents.csv`, from 1).
    pub incident: Option<usize>,
    /// Whether the `--fault` schedule asked for it.
    pub scheduled: bool,
}

/// Most points of each curve in `faults.png` (the run's and the no-fault run's).
const CURVE_POINTS: u64 = 6000;

/// The run's error curve `(t, err_deg)`, and the times of the ticks asked for.
type ErrorCurve = (Vec<(f64, f64)>, BTreeMap<u64, f64>);

/// The run's attitude error from `trace.csv`, a row at a time: every `every`-th row as
/// `(t, err_deg)`, and the time of each tick of `at`.
fn read_errors(out: &Path, every: u64, at: &[u64]) -> anyhow::Result<ErrorCurve> {
    use rotorloop_monitor::derive::Csv;
    let mut rows = rotorloop_monitor::derive::run_rows(out, Csv::Trace)?;
    let path = out.join(Csv::Trace.name());
    let header = rows.columns();
    let col = |n: &str| header.iter().position(|h| *h == n);
    let (Some(ct), Some(ce)) = (col("t"), col("err_deg")) else {
        anyhow::bail!("{} lacks the t, err_deg or tick column", path.display());
    };
    let (mut curve, mut times) = (Vec::new(), BTreeMap::new());
    while let Some((k, line)) = rows.next_row() {
        let f: Vec<&str> = line.split(',').collect();
        let value = |c: usize| f.get(c).and_then(|v| v.parse::<f64>().ok());
        let (Some(t), Some(e)) = (value(ct), value(ce)) else { continue };
        if k % every == 0 {
            curve.push((t, e));
        }
        if at.contains(&k) {
            times.insert(k, t);
        }
    }
    Ok((curve, times))
}

/// `timing.csv`'s rows in tick order, as far as they read (none without the file).
fn timing_rows(out: &Path) -> impl Iterator<Item = TimingRow> {
    let mut rows = rotorloop_monitor::derive::timing_rows(out).ok();
    std::iter::from_fn(move || rows.as_mut()?.next_row().ok().flatten())
}

/// Where a fault lies in `timing.csv`'s ticks: the newest tick published before it, the
/// first published after its restart (first pass); the ticks after the kill without a
/// fresh torque until the first fresh one at or after the restart (second pass).
#[derive(Debug, Clone, Copy, Default)]
struct Placed {
    kill_tick: Option<u64>,
    restart_tick: Option<u64>,
    /// Newest ticks published before the restart and before a stop's end.
    before_restart: Option<u64>,
    before_end: Option<u64>,
    without: u64,
    first_fresh: Option<u64>,
}

/// Computes the fault reports, adds them to `out/summary.json`, draws `out/faults.png`:
/// two passes over `timing.csv` and one over `trace.csv`, a row at a time, so its memory
/// is the same whatever the run's length.
///
/// A run whose plant never published tick 0 (a controller that failed at once) still lists
/// its faults, timed from `launched_ns` (when the launcher started the roles), with no
/// tick and nothing to cost. In `lockstep` each time is its tick's (see `kill_s`).
pub fn report(
    out: &Path,
    scenario: &Scenario,
    events: &[FaultEvent],
    (launched_ns, lockstep): (u64, bool),
) -> anyhow::Result<Vec<FaultReport>> {
    let mut placed = vec![Placed::default(); events.len()];
    let mut t0 = None::<u64>;
    for t in timing_rows(out) {
        t0 = Some(t0.map_or(t.state_publish_ns, |t0| t0.min(t.state_publish_ns)));
        for (p, e) in placed.iter_mut().zip(events) {
            if t.state_publish_ns <= e.kill_ns {
                p.kill_tick = Some(t.tick);
            }
            if e.restart_ns.is_some_and(|r| t.state_publish_ns <= r) {
                p.before_restart = Some(t.tick);
            }
            if e.ended.is_some_and(|(_, at)| t.state_publish_ns <= at) {
                p.before_end = Some(t.tick);
            }
            if p.restart_tick.is_none() && e.restart_ns.is_some_and(|r| t.state_publish_ns >= r) {
                p.restart_tick = Some(t.tick);
            }
        }
    }
    let no_timing = t0.is_none();
    let t0 = t0.unwrap_or(launched_ns);
    for t in timing_rows(out) {
        let k = t.tick;
        let fresh = k > 0 && t.applied_torque_tick == Some(k - 1);
        for p in placed.iter_mut().filter(|p| p.first_fresh.is_none()) {
            if p.restart_tick.is_some_and(|r| k >= r) && fresh {
                p.first_fresh = Some(k);
            } else if k > p.kill_tick.unwrap_or(0) && !fresh {
                p.without += 1;
            }
        }
    }
    let mut reports = Vec::new();
    let dt = scenario.dt();
    // The time of an event: in lockstep its tick's, in real time the wall's since tick 0.
    let at = |ns: u64, tick: Option<u64>| match (lockstep, tick) {
        (true, Some(k)) => k as f64 * dt,
        _ => ns.saturating_sub(t0) as f64 / 1e9,
    };
    for (e, p) in events.iter().zip(&placed) {
        reports.push(FaultReport {
            role: e.role.clone(),
            kind: e.kind,
            detail: e.detail.clone(),
            kill_s: at(e.kill_ns, p.kill_tick),
            restart_s: e.restart_ns.map(|r| at(r, p.before_restart)),
            signal: e.signal,
            ended: e.ended.map(|(how, _)| how),
            ended_s: e.ended.map(|(_, ns)| at(ns, p.before_end)),
            kill_tick: p.kill_tick,
            restart_tick: p.restart_tick,
            ticks_without_fresh_torque: p.without,
            ticks_to_first_fresh_torque: match (p.restart_tick, p.first_fresh) {
                (Some(r), Some(f)) => Some(f.saturating_sub(r)),
                _ => None,
            },
            peak_deviation_deg: None,
            recovery_s: None,
            incident: None,
            scheduled: e.scheduled,
        });
    }

    let mut j = match read_json(&out.join("summary.json")) {
        Ok(j) => j,
        // Stopped before the monitor had anything to report (a controller that failed at
        // once): the faults are the report.
        Err(SummaryError::Read(..)) if no_timing => serde_json::json!({
            "name": scenario.file.name,
            "completed": false,
            "trace_rows": 0,
            "note": "the run stopped before the plant published its first tick: no loop to report, only its faults",
        }),
        Err(SummaryError::Read(..)) => serde_json::json!({}),
        Err(e) => return Err(e.into()),
    };
    if j.as_object().is_some_and(|o| !o.is_empty()) {
        j["faults"] = serde_json::to_value(&reports)?;
        rotorloop_common::output::write_json(&out.join("summary.json"), &j)?;
    }

    draw(out, scenario, &reports)?;
    Ok(reports)
}

/// Draws `out/faults.png`: the error of this run and of the no-fault run, faults marked.
fn draw(out: &Path, scenario: &Scenario, reports: &[FaultReport]) -> anyhow::Result<()> {
    let dt = scenario.dt();
    let every = ((scenario.ticks() + 1) / CURVE_POINTS).max(1);
    let marked: Vec<u64> = reports
        .iter()
        .flat_map(|r| [r.kill_tick, r.kill_tick.map(|k| k + r.ticks_without_fresh_torque)])
        .flatten()
        .collect();
    let Ok((run, times)) = read_errors(out, every, &marked) else {
        return Ok(());
    };
    if run.is_empty() {
        return Ok(());
    }
    // The no-fault run: the same scenario in process, every `every`-th tick kept.
    let mut lp = ClosedLoop::new(scenario, scenario.actuation(), None)?;
    let mut reference = Vec::new();
    for k in 0..=scenario.ticks() {
        let e = lp.tick().err_deg;
        if k % every == 0 {
            reference.push((k as f64 * dt, e));
        }
    }
    let top = run.iter().map(|p| p.1).fold(1.0f64, f64::max);
    let mut markers: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    for r in reports {
        let at = |k: Option<u64>| k.and_then(|k| times.get(&k)).copied();
        if let Some(t) = at(r.kill_tick) {
            markers.push((format!("{} {}", r.kind, r.role), vec![(t, 1e-6), (t, top)]));
        }
        let restart_tick =
            r.restart_s.and_then(|_| r.kill_tick.map(|k| k + r.ticks_without_fresh_torque));
        if let (Some(_), Some(t)) = (r.restart_s, at(restart_tick)) {
            markers.push((format!("{} fresh again", r.role), vec![(t, 1e-6), (t, top)]));
        }
    }
    let mut series = vec![
        Series { label: "this run", points: &run, dashed: false },
        Series { label: "no-fault run (in process)", points: &reference, dashed: true },
    ];
    for (label, pts) in &markers {
        series.push(Series { label, points: pts, dashed: true });
    }
    line_chart(
        &out.join("faults.png"),
        &format!("{}: attitude error with faults marked", scenario.file.name),
        "t (s)",
        "error (deg, log)",
        &series,
        YScale::Log { floor: 1e-6 },
    )?;
    Ok(())
}
