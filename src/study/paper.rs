//! `rotorloop paper`: the paper's three tracking runs (reference torques zero, constant,
//! sinusoid). Each runs as the four-process loop over iceoryx2 in real time (trace,
//! latency histograms, figures in `DIR/<name>/`) and in process for the rotor vs gas-jet
//! effort comparison (`DIR/<name>/sim/`); then the gain analysis and a one-page
//! `report.md`. `--in-process` skips the four processes.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context;

use crate::sim::{self, EffortComparison, SimOptions, summary_table};
use crate::study::gains;
use rotorloop_common::role::UsageError;
use rotorloop_common::role::args::scenario_with_overrides;
use rotorloop_monitor::latency::Hop;
use rotorloop_monitor::summary::{Incidents, Summary};
use serde_json::json;

/// The built-in scenarios of the paper, in its order.
pub const PAPER_SCENARIOS: [&str; 3] = ["paper-zero", "paper-constant", "paper-sinusoid"];

/// Runs the three scenarios into `out/<name>/` and writes `out/report.md`.
pub fn run(out: &Path, duration: f64, rate: f64, in_process: bool) -> anyhow::Result<()> {
    let mut md = String::from("# The paper's scenario, three reference torques\n\n");
    let mut errs = Vec::new();
    let mut rows = String::new();
    let (mut loop_rows, mut incident_lines) = (String::new(), String::new());
    for name in PAPER_SCENARIOS {
        let scenario = scenario_with_overrides(name, Some(duration), Some(rate), None)?;
        let dir = if in_process { out.join(name) } else { out.join(name).join("sim") };
        if !in_process {
            let (row, incident) = four_process_run(out, name, duration, rate)?;
            loop_rows.push_str(&row);
            incident_lines.push_str(&incident);
        }
        println!("{name}: in process");
        let (s, rec) =
            sim::run(&SimOptions { progress: true, ..SimOptions::new(scenario, dir.clone()) })
                .with_context(|| format!("sim of {name}"))?;
        print!("{}", summary_table(&s));
        crate::export::mcap_after_run(&dir, false);
        let e = s.effort.as_ref().context("closed-loop runs have an effort comparison")?;
        let settle = s.settle_time_0p1deg_s.map_or("—".into(), |t| format!("{t:.2}"));
        let (e0, e1, drift) = (s.err_deg_initial, s.err_deg_final, s.momentum_drift_rel_max);
        let EffortComparison { internal_u_rms, internal_u_max, .. } = e;
        let EffortComparison { external_tau_rms, external_tau_max, .. } = e;
        let _ = writeln!(
            rows,
            "| {name} | {e0:.2} | {e1:.3e} | {settle} | {drift:.3e} | {internal_u_rms:.4} | \
             {internal_u_max:.4} | {external_tau_rms:.4} | {external_tau_max:.4} |"
        );
        errs.push(rec);
    }
    let _ = writeln!(
        md,
        "## In process: tracking and control effort\n\n\
         {duration} s at {rate} Hz. Figures and traces in `<run>/sim/` (`<run>/` with `--in-process`).\n\n\
         | run | error at 0 (deg) | final error (deg) | below 0.1° from (s) | momentum drift | ‖u‖ rms | ‖u‖ max | ‖τ‖ rms | ‖τ‖ max |\n\
         |---|---|---|---|---|---|---|---|---|\n{rows}"
    );
    if !in_process {
        let _ = writeln!(
            md,
            "## Four processes over iceoryx2, real time\n\n\
             Latency figures, histograms (`.hgrm`, `.hlog`) and traces in `<run>/`.\n\n\
             | run | ticks | misses | achieved Hz | sense-to-actuate p50 (µs) | p99 | max | tick lateness p99 (µs) | final error (deg) |\n\
             |---|---|---|---|---|---|---|---|---|\n{loop_rows}"
        );
        let _ = writeln!(
            md,
            "### The worst incident of each run\n\n\
             An incident is a window of abnormal ticks (a late plant wake, misses, a late \
             torque, faults); its cost is the peak attitude deviation from the same loop without \
             it, re-run in process from its first tick (docs/incidents.md). Every incident in \
             `<run>/incidents.md`.\n\n{incident_lines}"
        );
    }
    // In continuous time the error history is the same for all three profiles (spec).
    let mut diff = 0.0f64;
    for other in &errs[1..] {
        for ((t, a), b) in errs[0].t.iter().zip(&errs[0].err_deg).zip(&other.err_deg) {
            if *t <= 10.0 {
                diff = diff.max((a - b).abs());
            }
        }
    }
    let _ = writeln!(
        md,
        "Largest difference of the attitude-error histories between the three runs over the \
         first 10 s: {diff:.3e}° (identical in continuous time; zero-order hold makes them differ slightly).\n"
    );
    let scenario =
        rotorloop_common::scenario::Scenario::load(PAPER_SCENARIOS[0]).map_err(UsageError::from)?;
    let g = gains::render(&gains::analyse(&scenario));
    let _ = writeln!(md, "## Gains (Appendix A)\n\n```\n{g}```");
    if !scenario.warnings.is_empty() {
        let _ = writeln!(md, "\n## Warnings\n");
        for w in &scenario.warnings {
            let _ = writeln!(md, "- {w}");
        }
    }
    let path = out.join("report.md");
    rotorloop_common::outdir::write_file(&path, md)
        .with_context(|| format!("cannot write {}", path.display()))?;
    println!("report: {}", path.display());
    Ok(())
}

/// Runs `name` as the real-time four-process loop into `out/<name>/`; returns its row of
/// the report's loop table and its worst incident, in words.
fn four_process_run(
    out: &Path,
    name: &str,
    duration: f64,
    rate: f64,
) -> anyhow::Result<(String, String)> {
    println!("{name}: four processes, real time");
    let run_dir = out.join(name);
    let role = rotorloop_common::role::args::RoleArgs::realtime(
        name,
        duration,
        rate,
        rotorloop_common::ipc::wait::Wait::Event,
    );
    crate::run::launch::run(&crate::run::args::RunArgs::defaults(role, run_dir.clone()))
        .with_context(|| format!("four-process run of {name}"))?;
    let s = Summary::read(&run_dir).with_context(|| format!("no summary of the {name} run"))?;
    let (s2a, late) = (s.hop(Hop::SenseToActuate), s.hop(Hop::TickLateness));
    let us = |ns: Option<f64>| ns.unwrap_or(f64::NAN) / 1e3;
    let incident = worst_incident(name, s.incidents.as_ref());
    let row = format!(
        "| {name} | {} | {} | {:.3} | {:.1} | {:.1} | {:.1} | {:.1} | {:.3e} |\n",
        json!(s.ticks),
        json!(s.misses),
        s.achieved_rate_hz.unwrap_or(f64::NAN),
        us(s2a.p50),
        us(s2a.p99),
        us(s2a.max),
        us(late.p99),
        s.err_deg_final.unwrap_or(f64::NAN),
    );
    Ok((row, incident))
}

/// A run's worst incident (`summary.json`'s `incidents`), as a line of the report.
fn worst_incident(name: &str, inc: Option<&Incidents>) -> String {
    let Some(inc) = inc else {
        return format!("- **{name}**: no incidents computed (see the run's messages).\n");
    };
    let Some(w) = &inc.worst else {
        return format!("- **{name}**: no incident.\n");
    };
    let f = |v: Option<f64>| v.unwrap_or(f64::NAN);
    let cost = match (w.peak_deviation_deg, w.recovery_s) {
        (Some(p), Some(r)) => format!("peak deviation {p:.3}°, below a tenth of it after {r:.2} s"),
        (Some(p), None) => {
            format!("peak deviation {p:.3}°, not back below a tenth of it within the run")
        }
        (None, _) => "cost not computed".to_owned(),
    };
    format!(
        "- **{name}** ({} incidents): {} at {:.3} s for {:.1} ms, caused by {} ({}): {}. {}.\n",
        json!(inc.count),
        w.kind.as_deref().unwrap_or("?"),
        f(w.start_s),
        f(w.duration_s) * 1e3,
        w.cause_role.as_deref().unwrap_or("?"),
        w.cause_stage.as_deref().unwrap_or("?"),
        w.evidence.as_deref().unwrap_or(""),
        cost
    )
}
