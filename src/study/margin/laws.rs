//! `rotorloop margin --laws geometric-pid,mrp-pid`: the measured delay margins of several
//! laws on the same scenario, in one table and one figure. Each law runs the same
//! nonlinear sweep as `margin` (every torque `τ` late, in process); its measured margin is
//! the largest swept delay up to which every run stayed stable, and the largest up to
//! which every run converged. The linearised prediction is the geometric PID's alone
//! (its modes), so it is not part of this comparison.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context;
use rotorloop_common::role::UsageError;
use rotorloop_common::scenario::Scenario;
use rotorloop_monitor::plot::{Series, YScale, line_chart};

use crate::study::margin::{SweepRun, sweep_run};

/// `s` with `law`: its own gains where the scenario names that law, else the defaults of
/// the built-in scenario that uses it (`mrp-regulation` for `mrp-pid`).
pub fn with_law(s: &Scenario, law: &str) -> anyhow::Result<Scenario> {
    let named = s.law.as_deref().unwrap_or("geometric-pid");
    if named == law {
        return Ok(s.clone());
    }
    let mut file = s.file.clone();
    match law {
        "geometric-pid" => {
            file.controller.law = None;
            file.controller.law_params = toml::Table::new();
        }
        "mrp-pid" => {
            let gains = Scenario::load("mrp-regulation")?.file.controller;
            file.controller.law = gains.law;
            file.controller.law_params = gains.law_params;
        }
        other => {
            return Err(UsageError(format!(
                "--laws `{other}` is not allowed: geometric-pid, mrp-pid"
            ))
            .into());
        }
    }
    Ok(Scenario::from_file(file)?)
}

/// The largest swept delay up to which every run satisfies `ok` (`None`: not even 0).
fn margin(runs: &[SweepRun], ok: impl Fn(&SweepRun) -> bool) -> Option<f64> {
    runs.iter().take_while(|r| ok(r)).last().map(|r| r.delay_s)
}

/// Sweeps `delays` for each of `laws` on `s`; writes `laws.md`, `laws.csv`, `laws.png`
/// into `out`; returns the markdown.
pub fn compare(
    s: &Scenario,
    laws: &[String],
    delays: &[f64],
    out: &Path,
) -> anyhow::Result<String> {
    let mut sorted = delays.to_vec();
    sorted.sort_by(f64::total_cmp);
    let mut results = Vec::new();
    for law in laws {
        let sl = with_law(s, law)?;
        let runs = sorted.iter().map(|d| sweep_run(&sl, *d)).collect::<Result<Vec<_>, _>>()?;
        results.push((law.clone(), runs));
    }
    let mut md = format!(
        "\n# Laws compared on {}: measured delay margins\n\nEvery torque τ late (delayed \
         zero-order hold), the nonlinear loop in process, {} s at {} Hz. Margin: the largest \
         swept delay up to which every run stayed stable (never worse than 90° after 10 s) / \
         converged (within 0.1° at the end).\n\n| law | stable up to | converged up to |\n|---|---|---|\n",
        s.file.name, s.file.run.duration_s, s.file.run.rate_hz
    );
    let say = |m: Option<f64>| m.map_or("not at 0".to_owned(), |d| format!("{d} s"));
    for (law, runs) in &results {
        let _ = writeln!(
            md,
            "| {law} | {} | {} |",
            say(margin(runs, SweepRun::stable)),
            say(margin(runs, SweepRun::converged))
        );
    }
    md.push_str("\nFinal error (deg) per delay:\n\n| delay (s) |");
    for (law, _) in &results {
        let _ = write!(md, " {law} |");
    }
    md.push_str("\n|---|");
    md.push_str(&"---|".repeat(results.len()));
    md.push('\n');
    let mut csv = String::from("law,delay_s,final_err_deg,worst_after_10s_deg,stable,converged\n");
    for (i, d) in sorted.iter().enumerate() {
        let _ = write!(md, "| {d} |");
        for (law, runs) in &results {
            let r = &runs[i];
            let _ = write!(md, " {:.3e} ({}) |", r.final_err_deg, r.outcome());
            let _ = writeln!(
                csv,
                "{law},{d},{},{},{},{}",
                r.final_err_deg,
                r.worst_after_10s_deg,
                r.stable(),
                r.converged()
            );
        }
        md.push('\n');
    }
    rotorloop_common::outdir::write_file(&out.join("laws.md"), &md)
        .with_context(|| format!("cannot write {}", out.display()))?;
    rotorloop_common::outdir::write_file(&out.join("laws.csv"), csv)
        .with_context(|| format!("cannot write {}", out.display()))?;
    let points: Vec<Vec<(f64, f64)>> = results
        .iter()
        .map(|(_, runs)| runs.iter().map(|r| (r.delay_s, r.final_err_deg.max(1e-6))).collect())
        .collect();
    let series: Vec<Series<'_>> = results
        .iter()
        .zip(&points)
        .map(|((law, _), p)| Series { label: law, points: p, dashed: false })
        .collect();
    line_chart(
        &out.join("laws.png"),
        &format!("{}: final error against delay, per law", s.file.name),
        "delay τ (s)",
        "final error (deg, log)",
        &series,
        YScale::Log { floor: 1e-6 },
    )?;
    Ok(md)
}
