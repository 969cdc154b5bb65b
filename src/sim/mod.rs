//! `rotorloop sim`: one scenario in one process, faster than real time, with its trace,
//! summary and figures.
//!
//! - [`closed_loop`]: the loop in one process, the same structs as the four processes;
//! - [`replay`]: a real-time run replayed from its flight records, bit for bit.

pub mod closed_loop;
pub mod replay;

use std::io::{BufWriter, IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use glam::DVec3;
use rotorloop_common::output::write_json;
use rotorloop_common::role::diverged;
use rotorloop_common::scenario::{Actuation, Scenario};
use rotorloop_common::so3::orthonormality_error;
use rotorloop_monitor::figures::tracking_figures;

use rotorloop_monitor::figures::{EveryNth, Recorder};
use rotorloop_monitor::metrics::TraceRow;
use rotorloop_monitor::trace::TraceWriter;
use serde::Serialize;

use crate::sim::closed_loop::ClosedLoop;
use crate::sim::closed_loop::DrawnDelays;
use rotorloop_common::role::UsageError;
use rotorloop_controller::law::UnknownLaw;
use rotorloop_plant::actuator::ActuationDelay;

/// What to simulate.
#[derive(Debug, Clone)]
pub struct SimOptions {
    /// The validated scenario, with duration, rate and actuation as run.
    pub scenario: Scenario,
    /// Constant rotor torque instead of the controller.
    pub open_loop: Option<DVec3>,
    /// Write every N-th row to `trace.csv` (the last row always).
    pub trace_every: u64,
    /// Output directory.
    pub out: PathBuf,
    /// Draw figures.
    pub figures: bool,
    /// Show progress on a terminal.
    pub progress: bool,
    /// When each torque takes effect (`Instant`: the plain zero-order hold).
    pub delay: ActuationDelay,
    /// Each torque's delay drawn from a measured distribution instead.
    pub drawn: Option<DrawnDelays>,
    /// Step the reference on the loop's own thread instead of a second one
    /// ([`ClosedLoop::drive_ahead`]): the loop on one core, as Basilisk runs.
    pub one_thread: bool,
}

impl SimOptions {
    /// A plain run of `scenario` into `out`: closed loop, every row, figures, the plain
    /// zero-order hold.
    pub fn new(scenario: Scenario, out: PathBuf) -> Self {
        Self {
            scenario,
            open_loop: None,
            trace_every: 1,
            out,
            figures: true,
            progress: false,
            delay: ActuationDelay::Instant,
            drawn: None,
            one_thread: false,
        }
    }

    /// The closed loop these options run, with `actuation`.
    /// An error if the scenario names no known law.
    pub fn closed_loop(
        &self,
        actuation: Actuation,
        open_loop: Option<DVec3>,
    ) -> Result<ClosedLoop, UnknownLaw> {
        let lp = ClosedLoop::new(&self.scenario, actuation, open_loop)?.with_delay(self.delay);
        Ok(match &self.drawn {
            Some(d) => lp.with_drawn_delays(d.clone()),
            None => lp,
        })
    }
}

/// The delays of `--delay-from FILE --seed S`: the inverse CDF of a `.hgrm` percentile
/// distribution (values in µs), drawn with the seed.
pub fn drawn_delays(path: &Path, seed: u64) -> Result<DrawnDelays, UsageError> {
    let q = rotorloop_common::hgrm::read_distribution(path)
        .map_err(|why| UsageError(format!("--delay-from {}: {why}", path.display())))?;
    Ok(DrawnDelays::new(q, seed))
}

/// The effort comparison of the internally and externally actuated runs.
#[derive(Debug, Clone, Serialize)]
pub struct EffortComparison {
    /// RMS of `‖u‖` over the run, internal actuation (N m).
    pub internal_u_rms: f64,
    /// Peak `‖u‖`, internal actuation (N m).
    pub internal_u_max: f64,
    /// RMS of `‖τ‖`, external actuation (N m).
    pub external_tau_rms: f64,
    /// Peak `‖τ‖`, external actuation (N m).
    pub external_tau_max: f64,
    /// Largest difference of the two runs' attitude error angles (deg).
    pub err_deg_max_difference: f64,
}

/// `summary.json`.
#[derive(Debug, Clone, Serialize)]
pub struct SimSummary {
    /// Scenario name.
    pub name: String,
    /// The scenario as run (TOML fields).
    pub scenario: rotorloop_common::scenario::ScenarioFile,
    /// Actuation of the traced run.
    pub actuation: Actuation,
    /// Open-loop rotor torque, if the controller was off.
    pub open_loop: Option<[f64; 3]>,
    /// Plant steps taken.
    pub ticks: u64,
    /// Rows in `trace.csv`.
    pub trace_rows: u64,
    /// Tick period (s).
    pub dt: f64,
    /// Attitude error at t = 0 (deg).
    pub err_deg_initial: f64,
    /// Attitude error at the end (deg).
    pub err_deg_final: f64,
    /// `‖Ω − Ω_d‖` at the end (rad/s).
    pub werr_final: f64,
    /// First time after which the error stays below 0.1° (s), if it does.
    pub settle_time_0p1deg_s: Option<f64>,
    /// Largest `‖h − h(0)‖/‖h(0)‖` (an invariant only for internal actuation).
    pub momentum_drift_rel_max: f64,
    /// Largest `|ΔT − rotor work|` (J); null for a body without rotors.
    pub energy_residual_max_abs: Option<f64>,
    /// The same relative to the initial kinetic energy.
    pub energy_residual_rel_max: Option<f64>,
    /// Largest `‖RᵀR − I‖_F`.
    pub orthonormality_error_max: f64,
    /// Largest `|det R − 1|`.
    pub det_error_max: f64,
    /// Ticks whose rotor torque the actuator limits changed.
    pub saturated_ticks: u64,
    /// `saturated_ticks / ticks`.
    pub saturated_fraction: f64,
    /// Largest `|Ω_r,i|` over the run (rad/s).
    pub rotor_rate_max: f64,
    /// Largest `‖u‖` (N m).
    pub u_norm_max: f64,
    /// Largest `‖τ‖` (N m).
    pub tau_norm_max: f64,
    /// Internal vs external actuation on the same reference (closed loop only).
    pub effort: Option<EffortComparison>,
    /// Wall time of the traced run, including trace I/O (s).
    pub wall_seconds: f64,
    /// Plant steps per wall-clock second of the traced run.
    pub ticks_per_second: f64,
    /// Scenario warnings.
    pub warnings: Vec<String>,
    /// Figures written.
    pub figures: Vec<String>,
}

/// Running statistics of one run.
#[derive(Debug, Clone, Default)]
struct Stats {
    /// The first row's attitude error (deg).
    first_err_deg: f64,
    /// The last row's attitude error (deg) and rate error (rad/s): what is kept of it (a
    /// copy of the whole row each tick cost more than the rest of these statistics).
    last_err: (f64, f64),
    settle: Option<f64>,
    drift_max: f64,
    energy_max: f64,
    ortho_max: f64,
    det_max: f64,
    u_max: f64,
    tau_max: f64,
    u_sq: f64,
    tau_sq: f64,
    rotor_rate_max: f64,
    saturated_ticks: u64,
    rows: u64,
}

impl Stats {
    fn new(first: &TraceRow) -> Self {
        let last_err = (first.err_deg, first.werr);
        Self { first_err_deg: first.err_deg, last_err, ..Self::default() }
    }

    fn add(&mut self, row: &TraceRow, lp: &ClosedLoop) {
        self.last_err = (row.err_deg, row.werr);
        self.rows += 1;
        if row.err_deg < 0.1 {
            self.settle.get_or_insert(row.t);
        } else {
            self.settle = None;
        }
        self.drift_max = self.drift_max.max(row.h_drift_rel);
        self.rotor_rate_max = row.omega_r.iter().fold(self.rotor_rate_max, |m, w| m.max(w.abs()));
        if row.energy_residual.is_finite() {
            self.energy_max = self.energy_max.max(row.energy_residual.abs());
        }
        let (o, d) = orthonormality_error(&lp.plant().state().r);
        self.ortho_max = self.ortho_max.max(o);
        self.det_max = self.det_max.max(d);
        let (u, tau) = (row.u_norm(), row.tau_norm());
        self.u_max = self.u_max.max(u);
        self.tau_max = self.tau_max.max(tau);
        self.u_sq += u * u;
        self.tau_sq += tau * tau;
    }
}

/// Runs a loop for the scenario's ticks (`ticks + 1` rows: the last state gets a row
/// too), calling `each` per row, the reference stepped ahead on a thread of its own
/// unless `one_thread` (the rows are the same, bit for bit). Returns the statistics.
fn drive(
    lp: &mut ClosedLoop,
    ticks: u64,
    one_thread: bool,
    mut each: impl FnMut(&TraceRow, bool) -> anyhow::Result<()>,
) -> anyhow::Result<Stats> {
    let mut stats: Option<Stats> = None;
    let mut row_done = |lp: &mut ClosedLoop, row: TraceRow| -> anyhow::Result<()> {
        let k = row.tick;
        if !lp.plant().is_finite() {
            return Err(diverged(k, row.t).into());
        }
        let st = stats.get_or_insert_with(|| Stats::new(&row));
        st.add(&row, lp);
        if k < ticks {
            // The last tick's torque would act beyond the run: not counted (as in the plant).
            st.saturated_ticks = lp.saturated_ticks();
        }
        each(&row, k == ticks)
    };
    if one_thread {
        for _ in 0..=ticks {
            let row = lp.tick();
            row_done(lp, row)?;
        }
    } else {
        lp.drive_ahead(ticks, row_done)?;
    }
    stats.context("a run has at least one row")
}

/// The traced run's loop as [`run`] drives it (its statistics, the figures' recorder, the
/// trace's decimation to every `trace_every`-th row) for `ticks` ticks, without writing
/// the rows it picks: what `sim`'s ticks/s measures, less the trace file. Returns how many
/// rows it picked. The benchmark that guards the simulator's speed runs this.
pub fn drive_unwritten(
    lp: &mut ClosedLoop,
    ticks: u64,
    trace_every: u64,
    one_thread: bool,
) -> anyhow::Result<u64> {
    let mut rec = Recorder::new(ticks + 1);
    let mut traced = EveryNth::new(trace_every);
    let mut rows = 0u64;
    drive(lp, ticks, one_thread, |row, last| {
        rows += u64::from(traced.holds(row.tick) || last);
        rec.record(row, last);
        Ok(())
    })?;
    Ok(rows)
}

/// Runs `sim` and writes `trace.csv`, `summary.json` and the figures into `opts.out`.
/// `summary.json` is written last: a directory without it is an unfinished run.
pub fn run(opts: &SimOptions) -> anyhow::Result<(SimSummary, Recorder)> {
    let s = &opts.scenario;
    let out = rotorloop_common::outdir::OutDir::make(&opts.out)?;
    let summary_path = opts.out.join("summary.json");
    out.remove("summary.json")
        .with_context(|| format!("cannot replace {}", summary_path.display()))?;
    let ticks = s.ticks();
    let actuation = s.actuation();
    let trace_path = opts.out.join("trace.csv");
    let file = out
        .create("trace.csv")
        .with_context(|| format!("cannot create {}", trace_path.display()))?;
    let mut trace = TraceWriter::new(BufWriter::with_capacity(1 << 20, file))?;
    let mut rec = Recorder::new(ticks + 1);
    let mut progress = Progress::new(opts.progress && ticks >= 200_000, ticks);
    let mut traced = EveryNth::new(opts.trace_every);
    let mut trace_rows = 0u64;

    let mut lp = opts.closed_loop(actuation, opts.open_loop).map_err(UsageError::from)?;
    let start = Instant::now();
    let stats = drive(&mut lp, ticks, opts.one_thread, |row, last| {
        if traced.holds(row.tick) || last {
            trace.write(row).with_context(|| format!("cannot write {}", trace_path.display()))?;
            trace_rows += 1;
        }
        rec.record(row, last);
        progress.update(row);
        Ok(())
    })?;
    trace.finish().with_context(|| format!("cannot write {}", trace_path.display()))?;
    let wall = start.elapsed().as_secs_f64();
    progress.done();

    // The effort comparison: the other actuation on the same reference.
    let (effort, other_rec) = match opts.open_loop {
        None => effort_comparison(opts, &stats, &rec).map(|(e, r)| (Some(e), Some(r)))?,
        Some(_) => (None, None),
    };

    let mut figures = Vec::new();
    if opts.figures {
        let pair = other_rec.as_ref().map(|o| match actuation {
            Actuation::Internal => (&rec, o),
            Actuation::External => (o, &rec),
        });
        figures = tracking_figures(&opts.out, &s.file.name, &rec, pair)?;
    }

    let has_rotors = actuation == Actuation::Internal;
    let e0 = lp.metrics().initial_energy();
    let summary = SimSummary {
        name: s.file.name.clone(),
        scenario: s.file.clone(),
        actuation,
        open_loop: opts.open_loop.map(|u| u.to_array()),
        ticks,
        trace_rows,
        dt: s.dt(),
        err_deg_initial: stats.first_err_deg,
        err_deg_final: stats.last_err.0,
        werr_final: stats.last_err.1,
        settle_time_0p1deg_s: stats.settle,
        momentum_drift_rel_max: stats.drift_max,
        energy_residual_max_abs: has_rotors.then_some(stats.energy_max),
        energy_residual_rel_max: has_rotors.then_some(stats.energy_max / e0),
        orthonormality_error_max: stats.ortho_max,
        det_error_max: stats.det_max,
        saturated_ticks: stats.saturated_ticks,
        saturated_fraction: stats.saturated_ticks as f64 / ticks as f64,
        rotor_rate_max: stats.rotor_rate_max,
        u_norm_max: stats.u_max,
        tau_norm_max: stats.tau_max,
        effort,
        wall_seconds: wall,
        ticks_per_second: ticks as f64 / wall.max(1e-12),
        warnings: s.warnings.clone(),
        figures,
    };
    write_json(&summary_path, &summary)?;
    Ok((summary, rec))
}

/// The short summary table printed after a run.
pub fn summary_table(s: &SimSummary) -> String {
    let mut t = String::new();
    let opt = |v: Option<f64>, unit: &str| v.map_or("n/a".to_owned(), |v| format!("{v:.3e}{unit}"));
    let lines = [
        (
            "scenario",
            format!(
                "{} ({} actuation{})",
                s.name,
                s.actuation,
                if s.open_loop.is_some() { ", open loop" } else { "" }
            ),
        ),
        ("ticks", format!("{} at dt = {} s", s.ticks, s.dt)),
        ("attitude error", format!("{:.4}° → {:.3e}°", s.err_deg_initial, s.err_deg_final)),
        (
            "settled below 0.1°",
            s.settle_time_0p1deg_s.map_or("no".into(), |t| format!("at t = {t:.3} s")),
        ),
        ("momentum drift (max, rel.)", format!("{:.3e}", s.momentum_drift_rel_max)),
        ("energy − work (max)", opt(s.energy_residual_max_abs, " J")),
        (
            "actuators",
            format!(
                "saturated {:.2} % of ticks; max |Ω_r,i| {:.4} rad/s",
                100.0 * s.saturated_fraction,
                s.rotor_rate_max
            ),
        ),
        ("‖RᵀR − I‖ (max)", format!("{:.3e}", s.orthonormality_error_max)),
        (
            "speed",
            format!(
                "{:.0} ticks/s ({:.3} s wall, incl. trace I/O)",
                s.ticks_per_second, s.wall_seconds
            ),
        ),
    ];
    for (k, v) in lines {
        t.push_str(&format!("  {k:<28} {v}\n"));
    }
    if let Some(e) = &s.effort {
        t.push_str(&format!(
            "  {:<28} rotors ‖u‖ rms {:.4} (max {:.4}) | gas jets ‖τ‖ rms {:.4} (max {:.4}) N m\n",
            "control effort",
            e.internal_u_rms,
            e.internal_u_max,
            e.external_tau_rms,
            e.external_tau_max
        ));
    }
    t
}

/// A progress line on stderr for long runs, updated a few times per second.
struct Progress {
    on: bool,
    total: u64,
    last: Instant,
}

impl Progress {
    fn new(on: bool, total: u64) -> Self {
        Self { on: on && std::io::stderr().is_terminal(), total, last: Instant::now() }
    }

    fn update(&mut self, row: &TraceRow) {
        if !self.on || row.tick % 8192 != 0 || self.last.elapsed().as_millis() < 250 {
            return;
        }
        self.last = Instant::now();
        let pct = 100.0 * row.tick as f64 / self.total as f64;
        let mut e = std::io::stderr().lock();
        let _ = write!(e, "\r  {pct:5.1}%  t = {:.2} s  error {:.3e}°   ", row.t, row.err_deg);
        let _ = e.flush();
    }

    fn done(&self) {
        if self.on {
            eprint!("\r{:60}\r", "");
        }
    }
}

/// Flies the other actuation (rotors ↔ gas jets) on the same reference and compares the
/// control effort with the run's `stats`; `rec` is the run's recorded error history.
fn effort_comparison(
    opts: &SimOptions,
    stats: &Stats,
    rec: &Recorder,
) -> anyhow::Result<(EffortComparison, Recorder)> {
    let s = &opts.scenario;
    let (actuation, ticks) = (s.actuation(), s.ticks());
    let other = match actuation {
        Actuation::Internal => Actuation::External,
        Actuation::External => Actuation::Internal,
    };
    let mut olp = opts.closed_loop(other, None)?;
    let mut orec = Recorder::new(ticks + 1);
    let mut err_diff = 0.0f64;
    let mut main_err = rec.err_deg.iter();
    let ostats = drive(&mut olp, ticks, opts.one_thread, |row, last| {
        let before = orec.t.len();
        orec.record(row, last);
        if orec.t.len() > before {
            if let Some(e) = main_err.next() {
                err_diff = err_diff.max((e - row.err_deg).abs());
            }
        }
        Ok(())
    })?;
    let (int, ext) = match actuation {
        Actuation::Internal => (stats, &ostats),
        Actuation::External => (&ostats, stats),
    };
    let n = (ticks + 1) as f64;
    let effort = EffortComparison {
        internal_u_rms: (int.u_sq / n).sqrt(),
        internal_u_max: int.u_max,
        external_tau_rms: (ext.tau_sq / n).sqrt(),
        external_tau_max: ext.tau_max,
        err_deg_max_difference: err_diff,
    };
    Ok((effort, orec))
}
