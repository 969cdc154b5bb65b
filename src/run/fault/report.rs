//! The fault report of `rotorloop run --fault`: for each fault, what it cost, computed
//! after the run from the monitor's `trace.csv` and `timing.csv` and an in-process
//! no-fault run of the same scenario; added to `summary.json` as `faults`, and drawn in
//! `faults.png`.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::Context;
use rotorloop_common::scenario::Scenario;
use rotorloop_monitor::plot::{Series, YScale, line_chart};
use serde::Serialize;

use crate::run::fault::FaultEvent;
use crate::sim::closed_loop::ClosedLoop;

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
    /// Kill time (s after the first tick was published; if none was, after the launch).
    pub kill_s: f64,
    /// Restart time (s), if restarted; for a stop, when it was continued.
    pub restart_s: Option<f64>,
    /// The signal, where it is known (`SIGKILL`, `SIGSTOP`, `SIGTSTP`, …).
    pub signal: Option<&'static str>,
    /// How a stop ended: `continued`, `killed`, `crash`, `exited`, `hung` (the watchdog
    /// killed it), or `still stopped when the launcher ended`.
    pub ended: Option<&'static str>,
    /// When a stop ended (s).
    pub ended_s: Option<f64>,
    /// Newest tick published before the kill.
    pub kill_tick: Option<u64>,
    /// Ticks after the kill whose preceding torque was not fresh (held or safe mode).
    pub ticks_without_fresh_torque: u64,
    /// Ticks from the restart to the first fresh torque applied.
    pub ticks_to_first_fresh_torque: Option<u64>,
    /// What the fault cost the control: the peak attitude deviation of the run from the
    /// loop that had no incident, over the incident that holds the fault (deg; 0 where the
    /// loop did not feel it, a monitor's kill say). Filled in by the run's incidents
    /// (`crate::study::incidents`); `None` where they could not be computed.
    pub peak_deviation_deg: Option<f64>,
    /// From the incident's start until that deviation is below 10 % of its peak (s);
    /// `None`: not within the run.
    pub recovery_s: Option<f64>,
    /// The incident that holds the fault (its row in `incidents.csv`, from 1).
    pub incident: Option<usize>,
}

fn read_errors(path: &Path) -> anyhow::Result<BTreeMap<u64, (f64, f64)>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or("").split(',').collect();
    let col = |n: &str| header.iter().position(|h| *h == n);
    let (Some(ct), Some(ce), Some(ck)) = (col("t"), col("err_deg"), col("tick")) else {
        anyhow::bail!("{} lacks the t, err_deg or tick column", path.display());
    };
    let mut m = BTreeMap::new();
    for line in lines {
        let f: Vec<&str> = line.split(',').collect();
        if let (Some(t), Some(e), Some(k)) = (f.get(ct), f.get(ce), f.get(ck)) {
            if let (Ok(t), Ok(e), Ok(k)) = (t.parse(), e.parse(), k.parse()) {
                m.insert(k, (t, e));
            }
        }
    }
    Ok(m)
}

/// Computes the fault reports, adds them to `out/summary.json`, draws `out/faults.png`.
///
/// A run whose plant never published tick 0 (a controller that failed at once) still lists
/// its faults, timed from `launched_ns` (when the launcher started the roles), with no
/// tick and nothing to cost.
pub fn report(
    out: &Path,
    scenario: &Scenario,
    events: &[FaultEvent],
    launched_ns: u64,
) -> anyhow::Result<Vec<FaultReport>> {
    let timing = rotorloop_monitor::timing::read(&out.join("timing.csv")).unwrap_or_default();
    let errors = read_errors(&out.join("trace.csv")).unwrap_or_default();
    let t0 = timing.values().map(|t| t.state_publish_ns).min().unwrap_or(launched_ns);
    // The no-fault run: the same scenario in process.
    let mut lp = ClosedLoop::new(scenario, scenario.actuation(), None)?;
    let nofault: Vec<f64> = (0..=scenario.ticks()).map(|_| lp.tick().err_deg).collect();
    let last_tick = timing.keys().next_back().copied().unwrap_or(0);
    let fresh =
        |k: u64| timing.get(&k).is_some_and(|t| k > 0 && t.applied_torque_tick == Some(k - 1));

    let mut reports = Vec::new();
    for e in events {
        let kill_tick = timing
            .iter()
            .filter(|(_, t)| t.state_publish_ns <= e.kill_ns)
            .map(|(k, _)| *k)
            .next_back();
        let restart_tick = e
            .restart_ns
            .and_then(|r| timing.iter().find(|(_, t)| t.state_publish_ns >= r).map(|(k, _)| *k));
        let from = kill_tick.unwrap_or(0);
        let first_fresh_after_restart =
            restart_tick.and_then(|r| (r..=last_tick).find(|k| fresh(*k)));
        let until = first_fresh_after_restart.unwrap_or(last_tick);
        let without =
            ((from + 1)..=until).filter(|k| timing.contains_key(k) && !fresh(*k)).count() as u64;
        reports.push(FaultReport {
            role: e.role.clone(),
            kind: e.kind,
            detail: e.detail.clone(),
            kill_s: e.kill_ns.saturating_sub(t0) as f64 / 1e9,
            restart_s: e.restart_ns.map(|r| r.saturating_sub(t0) as f64 / 1e9),
            signal: e.signal,
            ended: e.ended.map(|(how, _)| how),
            ended_s: e.ended.map(|(_, at)| at.saturating_sub(t0) as f64 / 1e9),
            kill_tick,
            ticks_without_fresh_torque: without,
            ticks_to_first_fresh_torque: match (restart_tick, first_fresh_after_restart) {
                (Some(r), Some(f)) => Some(f.saturating_sub(r)),
                _ => None,
            },
            peak_deviation_deg: None,
            recovery_s: None,
            incident: None,
        });
    }

    let summary_path = out.join("summary.json");
    let mut j: serde_json::Value = match std::fs::read_to_string(&summary_path) {
        Ok(text) => serde_json::from_str(&text)?,
        // Stopped before the monitor had anything to report (a controller that failed at
        // once): the faults are the report.
        Err(_) if timing.is_empty() => serde_json::json!({
            "name": scenario.file.name,
            "completed": false,
            "trace_rows": 0,
            "note": "the run stopped before the plant published its first tick: no loop to report, only its faults",
        }),
        Err(_) => serde_json::json!({}),
    };
    if j.as_object().is_some_and(|o| !o.is_empty()) {
        j["faults"] = serde_json::to_value(&reports)?;
        rotorloop_common::output::write_json(&summary_path, &j)?;
    }

    if !errors.is_empty() {
        draw(out, scenario, &errors, &nofault, &reports)?;
    }
    Ok(reports)
}

/// Draws `out/faults.png`: the error of this run and of the no-fault run, faults marked.
fn draw(
    out: &Path,
    scenario: &Scenario,
    errors: &BTreeMap<u64, (f64, f64)>,
    nofault: &[f64],
    reports: &[FaultReport],
) -> anyhow::Result<()> {
    let run: Vec<(f64, f64)> = errors.values().copied().collect();
    let dt = scenario.dt();
    let every = (nofault.len() / 6000).max(1);
    let reference: Vec<(f64, f64)> =
        nofault.iter().enumerate().step_by(every).map(|(k, e)| (k as f64 * dt, *e)).collect();
    let top = run.iter().map(|p| p.1).fold(1.0f64, f64::max);
    let mut markers: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    for r in reports {
        let at = |k: Option<u64>| k.and_then(|k| errors.get(&k)).map(|(t, _)| *t);
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
