//! `rotorloop montecarlo`: the "almost-global" claim, shown. Random initial attitudes
//! (uniform on SO(3)) and rates; a share of the runs start within 2° of a 180° attitude
//! error, where a naive controller stalls. Each run is the full closed loop of `sim`.

use std::path::{Path, PathBuf};

use anyhow::Context;
use glam::DVec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rotorloop_common::scenario::{Actuation, Scenario};
use rotorloop_common::so3::axis_angle;
use rotorloop_monitor::plot::histogram;
use serde::Serialize;

use crate::sim::closed_loop::ClosedLoop;

/// Convergence criterion on the final attitude error (deg).
pub const CONVERGED_DEG: f64 = 0.1;

/// What to run.
#[derive(Debug, Clone)]
pub struct McOptions {
    /// Base scenario: bodies, reference, gains, rate, duration.
    pub scenario: Scenario,
    /// Number of runs.
    pub runs: usize,
    /// RNG seed (ChaCha8): the same seed gives the same runs.
    pub seed: u64,
    /// Every `near_pi_every`-th run starts within 2° of a 180° error.
    pub near_pi_every: usize,
    /// Largest `|IΩ(0)|` component and `|Ω_r(0)|` component drawn.
    pub max_rate: f64,
    /// Worker threads.
    pub threads: usize,
    /// Output directory (None: no files).
    pub out: Option<PathBuf>,
}

/// One run's initial condition and outcome.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct McRun {
    /// Run index.
    pub run: usize,
    /// Started near π.
    pub near_pi: bool,
    /// Initial attitude error (deg).
    pub err_deg_initial: f64,
    /// `|Ω(0)|` (rad/s).
    pub omega0_norm: f64,
    /// `|Ω_r(0)|` (rad/s).
    pub omega_r0_norm: f64,
    /// Final attitude error (deg).
    pub err_deg_final: f64,
    /// Largest error seen (deg).
    pub err_deg_max: f64,
    /// Final error below [`CONVERGED_DEG`].
    pub converged: bool,
}

/// The study's summary.
#[derive(Debug, Clone, Serialize)]
pub struct McSummary {
    /// Base scenario name.
    pub scenario: String,
    /// Runs.
    pub runs: usize,
    /// Seed.
    pub seed: u64,
    /// Runs started within 2° of 180°.
    pub near_pi_runs: usize,
    /// Smallest distance of an initial error from 180° (deg).
    pub closest_to_pi_deg: f64,
    /// Fraction with final error < 0.1°.
    pub fraction_converged: f64,
    /// Largest final error (deg).
    pub worst_final_err_deg: f64,
    /// Simulated seconds per run.
    pub duration_s: f64,
    /// Tick rate.
    pub rate_hz: f64,
}

/// Draws run `i`'s initial state into a copy of the scenario.
fn draw(base: &Scenario, opts: &McOptions, i: usize) -> (Scenario, bool) {
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    rng.set_stream(i as u64);
    let unit = |rng: &mut ChaCha8Rng| loop {
        let v = DVec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let n = v.length();
        if n > 1e-3 && n <= 1.0 {
            return v / n;
        }
    };
    let near_pi = opts.near_pi_every > 0 && i % opts.near_pi_every == 0;
    let mut s = base.clone();
    let rd0 = s.reference_attitude;
    s.plant_init.r = if near_pi {
        // E(0) = R_d(0) R(0)ᵀ = rotation by 178°…180° about a random axis.
        let angle = std::f64::consts::PI - rng.random_range(0.0..2.0f64.to_radians());
        axis_angle(unit(&mut rng), angle).transpose() * rd0
    } else {
        // Uniform on SO(3): a uniformly random unit quaternion.
        let q = glam::DQuat::from_xyzw(
            gauss(&mut rng),
            gauss(&mut rng),
            gauss(&mut rng),
            gauss(&mut rng),
        )
        .normalize();
        glam::DMat3::from_quat(q)
    };
    let m = opts.max_rate;
    let i_omega =
        DVec3::new(rng.random_range(-m..m), rng.random_range(-m..m), rng.random_range(-m..m));
    s.plant_init.omega = s.plant.inertia_inv * i_omega;
    s.plant_init.omega_r =
        DVec3::new(rng.random_range(-m..m), rng.random_range(-m..m), rng.random_range(-m..m));
    (s, near_pi)
}

fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    // Box–Muller.
    let u1: f64 = rng.random_range(f64::EPSILON..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Runs one Monte Carlo case.
pub fn run_one(opts: &McOptions, i: usize) -> Result<McRun, rotorloop_controller::law::UnknownLaw> {
    let (s, near_pi) = draw(&opts.scenario, opts, i);
    let mut lp = ClosedLoop::new(&s, Actuation::Internal, None)?;
    let ticks = s.ticks();
    let first = lp.tick();
    let mut last = first;
    let mut max = first.err_deg;
    for _ in 0..ticks {
        last = lp.tick();
        max = max.max(last.err_deg);
    }
    Ok(McRun {
        run: i,
        near_pi,
        err_deg_initial: first.err_deg,
        omega0_norm: s.plant_init.omega.length(),
        omega_r0_norm: s.plant_init.omega_r.length(),
        err_deg_final: last.err_deg,
        err_deg_max: max,
        converged: last.err_deg < CONVERGED_DEG,
    })
}

/// Runs the study on `opts.threads` threads and writes its files.
pub fn run(opts: &McOptions) -> anyhow::Result<(McSummary, Vec<McRun>)> {
    let threads = opts.threads.clamp(1, 64);
    let results: Vec<Result<McRun, _>> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..threads)
            .map(|w| {
                scope.spawn(move || {
                    (w..opts.runs).step_by(threads).map(|i| run_one(opts, i)).collect::<Vec<_>>()
                })
            })
            .collect();
        handles.into_iter().flat_map(|h| h.join().unwrap_or_default()).collect()
    });
    anyhow::ensure!(results.len() == opts.runs, "a Monte Carlo worker thread panicked");
    let mut results = results.into_iter().collect::<Result<Vec<_>, _>>()?;
    results.sort_by_key(|r| r.run);
    let n = results.len().max(1) as f64;
    let summary = McSummary {
        scenario: opts.scenario.file.name.clone(),
        runs: results.len(),
        seed: opts.seed,
        near_pi_runs: results.iter().filter(|r| r.near_pi).count(),
        closest_to_pi_deg: results
            .iter()
            .map(|r| 180.0 - r.err_deg_initial)
            .fold(f64::INFINITY, f64::min),
        fraction_converged: results.iter().filter(|r| r.converged).count() as f64 / n,
        worst_final_err_deg: results.iter().map(|r| r.err_deg_final).fold(0.0, f64::max),
        duration_s: opts.scenario.file.run.duration_s,
        rate_hz: opts.scenario.file.run.rate_hz,
    };
    if let Some(dir) = &opts.out {
        write_outputs(dir, &summary, &results)?;
    }
    Ok((summary, results))
}

fn write_outputs(dir: &Path, summary: &McSummary, runs: &[McRun]) -> anyhow::Result<()> {
    rotorloop_common::outdir::OutDir::make(dir)
        .map(drop)
        .with_context(|| format!("cannot create {}", dir.display()))?;
    let mut csv = String::from(
        "run,near_pi,err_deg_initial,omega0_norm,omega_r0_norm,err_deg_final,err_deg_max,converged\n",
    );
    for r in runs {
        let McRun { run, near_pi, err_deg_initial, omega0_norm, omega_r0_norm, .. } = r;
        let McRun { err_deg_final, err_deg_max, converged, .. } = r;
        csv.push_str(&format!(
            "{run},{near_pi},{err_deg_initial},{omega0_norm},{omega_r0_norm},{err_deg_final},\
             {err_deg_max},{converged}\n"
        ));
    }
    let path = dir.join("runs.csv");
    rotorloop_common::outdir::write_file(&path, csv)
        .with_context(|| format!("cannot write {}", path.display()))?;
    let log_final: Vec<f64> = runs.iter().map(|r| r.err_deg_final.max(1e-16).log10()).collect();
    histogram(
        &dir.join("final_error_histogram.png"),
        &format!("{} runs: final attitude error (converged: error < 0.1° = 10^-1)", runs.len()),
        "log10(final error / deg)",
        &log_final,
        30,
    )?;
    let initial: Vec<f64> = runs.iter().map(|r| r.err_deg_initial).collect();
    histogram(
        &dir.join("initial_error_histogram.png"),
        "initial attitude error",
        "deg",
        &initial,
        36,
    )?;
    rotorloop_common::output::write_json(&dir.join("summary.json"), summary)
}
