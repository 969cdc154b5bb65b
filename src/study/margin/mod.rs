//! `rotorloop margin`: how much actuation delay the loop tolerates, predicted and measured.
//!
//! 1. **Predicted** (spec, "Actuation delay"): linearised about `E = I` with a pure delay
//!    `τ` on the whole feedback, mode `m` (an eigenvalue of `tr(P)I − P`) has the loop
//!    `L(s) = (k_d s² + k_p m s + k_I m) e^{−sτ} / s³`. Its gain crossover `ω_c`
//!    (`|L(jω_c)| = 1`) solves `x³ − k_d² x² − (k_p² m² − 2 k_d k_I m) x − k_I² m² = 0` for
//!    `x = ω²`; the phase margin at `τ = 0` is `φ = π + arg L(jω_c)`, and the delay margin
//!    `τ* = φ / ω_c`.
//! 2. **Measured**: the nonlinear loop in process with every torque taking effect `τ`
//!    after its tick (the delayed zero-order hold the plant uses), for a sweep of `τ`:
//!    final error, worst error after 10 s, settle time, divergence.
//!
//! The two disagree, and the report says so: the law cancels the gyroscopic terms
//! `(IΩ)×Ω` and `K(Ω+Ω_r)×Ω` with the state it was given, which under delay is stale;
//! with the paper's large momentum (`‖h‖` ≈ 26 N m s) those terms dominate, so the
//! nonlinear loop degrades long before the linear `τ*`.

pub mod laws;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context;
use rotorloop_common::role::UsageError;
use rotorloop_common::scenario::Scenario;
use rotorloop_monitor::latency::Hop;
use rotorloop_monitor::plot::{Series, YScale, line_chart};
use rotorloop_monitor::summary::Summary;
use rotorloop_plant::actuator::ActuationDelay;
use serde::Serialize;

use crate::sim::closed_loop::ClosedLoop;
use crate::study::gains::cubic_roots;

/// The longest delay a sweep runs (s): `--delays`' bound, and the default delays'.
const MAX_DELAY_S: f64 = 60.0;

/// `rotorloop margin` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct MarginArgs {
    /// Built-in scenario name or TOML path.
    #[arg(long, default_value = "paper-sinusoid")]
    pub scenario: String,
    /// Delays to run (s), comma-separated, each 0 to 60 (default: 0 to twice the
    /// predicted margin).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true,
          value_parser = rotorloop_common::input::number_in(0.0, MAX_DELAY_S, "seconds"))]
    pub delays: Option<Vec<f64>>,
    /// Simulated seconds per run, 0.001 to 86400.
    #[arg(long, allow_hyphen_values = true, default_value_t = 60.0,
          value_parser = rotorloop_common::role::args::duration_s())]
    pub duration: f64,
    /// Tick rate (Hz), 1 to 100000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 1000.0,
          value_parser = rotorloop_common::role::args::rate_hz())]
    pub rate: f64,
    /// A real-time run's `summary.json`: its sense-to-actuate figures are put on the same
    /// scale as the margins.
    #[arg(long)]
    pub latency_from: Option<PathBuf>,
    /// Also compare these laws' measured margins on the same scenario (`geometric-pid`,
    /// `mrp-pid`: each with its own gains, `mrp-pid` with `mrp-regulation`'s unless the
    /// scenario names it): `laws.md`, `laws.csv`, `laws.png`.
    #[arg(long, value_delimiter = ',')]
    pub laws: Vec<String>,
    /// Output directory (`margin.md`, `margin.csv`, `margin.png`, `margin_final.png`).
    #[arg(long)]
    pub out: PathBuf,
}

/// One mode's predicted margin.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct ModeMargin {
    /// The mode (eigenvalue of `tr(P)I − P`).
    pub m: f64,
    /// Gain crossover (rad/s).
    pub omega_c: f64,
    /// Phase margin at zero delay (rad).
    pub phase_margin_rad: f64,
    /// Delay margin `φ / ω_c` (s).
    pub tau_star_s: f64,
}

/// The predicted margin of each mode of `s` (module docs).
pub fn predicted(s: &Scenario) -> Vec<ModeMargin> {
    let g = s.gains;
    let trace: f64 = s.p_eigenvalues.iter().sum();
    let mut out: Vec<ModeMargin> = s
        .p_eigenvalues
        .iter()
        .map(|p| {
            let m = trace - p;
            let roots = cubic_roots(
                -g.kd * g.kd,
                -(g.kp * g.kp * m * m - 2.0 * g.kd * g.ki * m),
                -g.ki * g.ki * m * m,
            );
            // Every positive real root is a crossover; the smallest margin counts.
            roots
                .iter()
                .filter(|x| x.im.abs() < 1e-9 * x.re.abs().max(1.0) && x.re > 0.0)
                .map(|x| {
                    let w = x.re.sqrt();
                    let arg =
                        (g.kp * m * w).atan2(g.ki * m - g.kd * w * w) + std::f64::consts::FRAC_PI_2;
                    let phi = (std::f64::consts::PI + arg).rem_euclid(2.0 * std::f64::consts::PI);
                    let phi = if phi > std::f64::consts::PI {
                        phi - 2.0 * std::f64::consts::PI
                    } else {
                        phi
                    };
                    ModeMargin {
                        m,
                        omega_c: w,
                        phase_margin_rad: phi,
                        tau_star_s: (phi / w).max(0.0),
                    }
                })
                .min_by(|a, b| a.tau_star_s.total_cmp(&b.tau_star_s))
                .unwrap_or(ModeMargin {
                    m,
                    omega_c: f64::NAN,
                    phase_margin_rad: f64::NAN,
                    tau_star_s: f64::NAN,
                })
        })
        .collect();
    out.sort_by(|a, b| a.m.total_cmp(&b.m));
    out
}

/// One delay's run.
#[derive(Debug, Clone, Serialize)]
pub struct SweepRun {
    /// The actuation delay (s).
    pub delay_s: f64,
    /// Attitude error at the end, or when it diverged (deg).
    pub final_err_deg: f64,
    /// Worst attitude error after 10 s (deg).
    pub worst_after_10s_deg: f64,
    /// From when the error stays below 0.1° (s).
    pub settle_s: Option<f64>,
    /// The state stopped being finite (the run could not go on), at this time (s).
    pub diverged_at_s: Option<f64>,
    /// Error history, about 600 points `(t, err_deg)`.
    #[serde(skip)]
    pub history: Vec<(f64, f64)>,
}

/// Worse than this after 10 s, a run has lost tracking (deg).
pub const LOST_DEG: f64 = 90.0;

impl SweepRun {
    /// Converged: finite to the end and below 0.1° at the end.
    pub fn converged(&self) -> bool {
        self.diverged_at_s.is_none() && self.final_err_deg < 0.1
    }

    /// Stable as far as the run shows: finite, and never worse than [`LOST_DEG`] after 10 s.
    pub fn stable(&self) -> bool {
        self.diverged_at_s.is_none() && self.worst_after_10s_deg < LOST_DEG
    }

    /// The outcome in words.
    pub fn outcome(&self) -> String {
        match self.diverged_at_s {
            Some(at) => format!("diverged at {at:.2} s (state no longer finite)"),
            None if !self.stable() => format!("lost tracking (worse than {LOST_DEG}° after 10 s)"),
            None if self.converged() => "converged".to_owned(),
            None => "stable, but not within 0.1° at the end".to_owned(),
        }
    }
}

/// The closed loop of `s` with every torque `delay_s` late, to the end or until it
/// diverges.
pub fn sweep_run(
    s: &Scenario,
    delay_s: f64,
) -> Result<SweepRun, rotorloop_controller::law::UnknownLaw> {
    let delay =
        if delay_s == 0.0 { ActuationDelay::Instant } else { ActuationDelay::Fixed(delay_s) };
    let mut lp = ClosedLoop::new(s, s.actuation(), None)?.with_delay(delay);
    let ticks = s.ticks();
    let every = (ticks / 600).max(1);
    let mut run = SweepRun {
        delay_s,
        final_err_deg: f64::NAN,
        worst_after_10s_deg: 0.0,
        settle_s: None,
        diverged_at_s: None,
        history: Vec::new(),
    };
    for k in 0..=ticks {
        let row = lp.tick();
        if !row.err_deg.is_finite() || !lp.plant().is_finite() {
            run.diverged_at_s = Some(row.t);
            run.worst_after_10s_deg = 180.0;
            break;
        }
        run.final_err_deg = row.err_deg;
        if row.t >= 10.0 {
            run.worst_after_10s_deg = run.worst_after_10s_deg.max(row.err_deg);
        }
        match (row.err_deg < 0.1, run.settle_s) {
            (true, None) => run.settle_s = Some(row.t),
            (false, Some(_)) => run.settle_s = None,
            _ => {}
        }
        if k % every == 0 || k == ticks {
            run.history.push((row.t, row.err_deg));
        }
    }
    Ok(run)
}

/// Runs the study and writes its files; returns the predicted margins and the sweep.
pub fn run(a: &MarginArgs) -> anyhow::Result<(Vec<ModeMargin>, Vec<SweepRun>)> {
    let s = rotorloop_common::role::args::scenario_with_overrides(
        &a.scenario,
        Some(a.duration),
        Some(a.rate),
        None,
    )?;
    let modes = predicted(&s);
    let tau_star = modes.iter().map(|m| m.tau_star_s).fold(f64::INFINITY, f64::min);
    let delays = match &a.delays {
        Some(d) => d.clone(),
        None => default_delays(tau_star),
    };
    // Read before the sweep: a bad file is refused before minutes of runs, not after.
    let latency = a.latency_from.as_deref().map(read_latency).transpose()?;
    rotorloop_common::outdir::OutDir::make(&a.out)
        .map(drop)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let runs = delays.iter().map(|d| sweep_run(&s, *d)).collect::<Result<Vec<_>, _>>()?;
    write_csv(&a.out.join("margin.csv"), &runs)?;
    let md = report(&s, &modes, &runs, latency.as_ref());
    rotorloop_common::outdir::write_file(&a.out.join("margin.md"), &md)
        .with_context(|| format!("cannot write {}", a.out.display()))?;
    plots(&a.out, &s.file.name, &runs, tau_star)?;
    print!("{md}");
    if !a.laws.is_empty() {
        let laws = laws::compare(&s, &a.laws, &delays, &a.out)?;
        print!("{laws}");
    }
    Ok((modes, runs))
}

fn default_delays(tau_star: f64) -> Vec<f64> {
    let mut d = vec![0.0, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4];
    if tau_star.is_finite() {
        d.extend([0.5 * tau_star, tau_star, 1.5 * tau_star, 2.0 * tau_star]);
    }
    d.retain(|d| *d <= MAX_DELAY_S);
    d.sort_by(f64::total_cmp);
    d.dedup();
    d
}

fn write_csv(path: &Path, runs: &[SweepRun]) -> anyhow::Result<()> {
    let mut t = String::from(
        "delay_s,final_err_deg,worst_after_10s_deg,settle_s,diverged_at_s,stable,converged\n",
    );
    for r in runs {
        let opt = |v: Option<f64>| v.map_or(String::new(), |v| v.to_string());
        let _ = writeln!(
            t,
            "{},{},{},{},{},{},{}",
            r.delay_s,
            r.final_err_deg,
            r.worst_after_10s_deg,
            opt(r.settle_s),
            opt(r.diverged_at_s),
            r.stable(),
            r.converged()
        );
    }
    rotorloop_common::outdir::write_file(path, t)
        .with_context(|| format!("cannot write {}", path.display()))
}

/// Sense-to-actuate p50, p99 and max (s) of a real-time run's `summary.json`, read as any
/// input named on the command line (`common::input`) and checked as the monitor writes
/// them: a count of at least one, whole nanoseconds within the histogram's hour, and
/// p50 ≤ p99 ≤ max. Anything else is refused naming the file and the figure (a summary of
/// −1 figures with count 0 was accepted).
fn read_latency(path: &Path) -> Result<(f64, f64, f64), UsageError> {
    const MAX_NS: u64 = 3_600_000_000_000;
    let bad = |why: String| UsageError(format!("--latency-from {}: {why}", path.display()));
    let h = Summary::read_file(path)
        .map_err(|e| UsageError(format!("--latency-from: {e}")))?
        .hop(Hop::SenseToActuate);
    let figure = |q: &str, v: Option<f64>, lo: u64| match v {
        Some(v) if v.fract() == 0.0 && (lo as f64..=MAX_NS as f64).contains(&v) => Ok(v as u64),
        _ => Err(bad(format!(
            "hops.sense_to_actuate.{q} = {} is not allowed: a whole number from {lo} to \
             {MAX_NS} (ns)",
            v.map_or("null".to_owned(), |v| v.to_string())
        ))),
    };
    figure("count", h.count.map(|c| c as f64), 1)?;
    let (p50, p99, max) =
        (figure("p50", h.p50, 0)?, figure("p99", h.p99, 0)?, figure("max", h.max, 0)?);
    if !(p50 <= p99 && p99 <= max) {
        return Err(bad(format!(
            "hops.sense_to_actuate p50 {p50}, p99 {p99}, max {max} are not allowed: \
             p50 ≤ p99 ≤ max"
        )));
    }
    Ok((p50 as f64 / 1e9, p99 as f64 / 1e9, max as f64 / 1e9))
}

fn report(
    s: &Scenario,
    modes: &[ModeMargin],
    runs: &[SweepRun],
    latency: Option<&(f64, f64, f64)>,
) -> String {
    let tau_star = modes.iter().map(|m| m.tau_star_s).fold(f64::INFINITY, f64::min);
    let g = s.gains;
    let mut t = format!(
        "# Delay margin: {}\n\nGains k_p = {}, k_d = {}, k_I = {}; {} Hz, {} s per run.\n\n\
         ## Predicted (linearised about E = I, pure delay on the whole feedback)\n\n\
         | mode m | gain crossover ω_c (rad/s) | phase margin φ (deg) | delay margin τ* = φ/ω_c (s) |\n|---|---|---|---|\n",
        s.file.name, g.kp, g.kd, g.ki, s.file.run.rate_hz, s.file.run.duration_s
    );
    for m in modes {
        let _ = writeln!(
            t,
            "| {:.4} | {:.4} | {:.2} | {:.4} |",
            m.m,
            m.omega_c,
            m.phase_margin_rad.to_degrees(),
            m.tau_star_s
        );
    }
    let _ = write!(
        t,
        "\n## Measured (the nonlinear loop in process, every torque τ late: delayed zero-order hold)\n\n\
         | delay τ (s) | τ / τ* | final error (deg) | worst after 10 s (deg) | below 0.1° from (s) | outcome |\n|---|---|---|---|---|---|\n"
    );
    for r in runs {
        let outcome = r.outcome();
        let _ = writeln!(
            t,
            "| {:.4} | {:.3} | {:.3e} | {:.3e} | {} | {outcome} |",
            r.delay_s,
            r.delay_s / tau_star,
            r.final_err_deg,
            r.worst_after_10s_deg,
            r.settle_s.map_or("—".to_owned(), |v| format!("{v:.2}"))
        );
    }
    let first = |bad: fn(&SweepRun) -> bool| {
        runs.iter().filter(|r| bad(r)).map(|r| r.delay_s).fold(f64::INFINITY, f64::min)
    };
    let last_before = |limit: f64| {
        runs.iter().filter(|r| r.delay_s < limit).map(|r| r.delay_s).fold(0.0, f64::max)
    };
    let (unstable, inaccurate) = (first(|r| !r.stable()), first(|r| !r.converged()));
    let _ = write!(
        t,
        "\n## Predicted against measured\n\n- predicted delay margin (smallest over modes): τ* = {tau_star:.4} s\n"
    );
    for (what, limit) in
        [("stays stable (tracks, error bounded)", unstable), ("converges below 0.1°", inaccurate)]
    {
        let _ = match limit.is_finite() {
            true => writeln!(
                t,
                "- measured: the loop {what} up to τ = {:.4} s and not from τ = {limit:.4} s (the sweep's resolution): {:.1} % of τ*",
                last_before(limit),
                100.0 * limit / tau_star
            ),
            false => writeln!(t, "- measured: the loop {what} at every delay of the sweep"),
        };
    }
    let _ = writeln!(
        t,
        "- why they differ: the linearisation treats the loop as three decoupled triple integrators. The \
         law also cancels the gyroscopic terms (IΩ)×Ω and K(Ω+Ω_r)×Ω with the state it was given; under \
         delay that state is stale, and with this scenario's momentum the cancellation error is a large \
         disturbance the linear model does not have. The linear τ* is an upper bound here, not a design value."
    );
    if let Some((p50, p99, max)) = latency {
        let _ = writeln!(
            t,
            "- this machine's loop (sense-to-actuate of the run given): p50 {:.1} µs, p99 {:.1} µs, max {:.1} µs: \
             {:.2e}, {:.2e} and {:.2e} of τ*",
            p50 * 1e6,
            p99 * 1e6,
            max * 1e6,
            p50 / tau_star,
            p99 / tau_star,
            max / tau_star
        );
    }
    t
}

fn plots(out: &Path, name: &str, runs: &[SweepRun], tau_star: f64) -> anyhow::Result<()> {
    let labels: Vec<String> = runs.iter().map(|r| format!("τ = {} s", r.delay_s)).collect();
    let series: Vec<Series<'_>> = runs
        .iter()
        .zip(&labels)
        .map(|(r, l)| Series { label: l, points: &r.history, dashed: false })
        .collect();
    line_chart(
        &out.join("margin.png"),
        &format!("{name}: attitude error with every torque τ late"),
        "t (s)",
        "error (deg, log)",
        &series,
        YScale::Log { floor: 1e-6 },
    )?;
    let finals: Vec<(f64, f64)> =
        runs.iter().map(|r| (r.delay_s, r.final_err_deg.max(1e-6))).collect();
    let top = finals.iter().map(|p| p.1).fold(1.0f64, f64::max).max(180.0);
    let marker = [(tau_star, 1e-3), (tau_star, top)];
    line_chart(
        &out.join("margin_final.png"),
        &format!(
            "{name}: final error against delay; predicted margin τ* = {tau_star:.3} s (dashed)"
        ),
        "delay τ (s)",
        "final error (deg, log)",
        &[
            Series { label: "measured (nonlinear, in process)", points: &finals, dashed: false },
            Series { label: "predicted margin τ*", points: &marker, dashed: true },
        ],
        YScale::Log { floor: 1e-3 },
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--latency-from` is read as the monitor writes it: a summary of −1 figures with count
    /// 0, figures out of order and a missing file are refused naming the file (exit 2).
    #[test]
    fn latency_from_refuses_figures_the_monitor_cannot_have_written() {
        let dir = std::env::temp_dir().join(format!("rl-margin-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("summary.json");
        let hops = |count: i64, p50: i64, p99: i64, max: i64| {
            let j = serde_json::json!({"hops": {"sense_to_actuate":
                {"count": count, "p50": p50, "p99": p99, "max": max}}});
            std::fs::write(&path, j.to_string()).expect("write");
        };
        hops(10, 20_000, 50_000, 90_000);
        let (p50, _, max) = read_latency(&path).expect("a sound summary");
        assert!((p50 - 20e-6).abs() < 1e-15 && (max - 90e-6).abs() < 1e-15);
        for (c, a, b, m, what) in [
            (0, -1, -1, -1, "hops.sense_to_actuate.count = 0"),
            (5, -1, 1, 2, "hops.sense_to_actuate.p50 = -1"),
            (5, 3, 2, 4, "p50 3, p99 2, max 4 are not allowed"),
        ] {
            hops(c, a, b, m);
            let e = read_latency(&path).expect_err(what).0;
            assert!(e.starts_with("--latency-from ") && e.contains(what), "{e}");
        }
        let e = read_latency(&dir.join("none.json")).expect_err("missing").0;
        assert!(e.ends_with("none.json: no such file"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
