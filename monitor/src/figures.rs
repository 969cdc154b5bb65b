//! The tracking figures of a run (the paper's plots and the invariant checks), drawn
//! from a decimated [`Recorder`] of trace rows.

use std::path::Path;

use crate::metrics::TraceRow;
use crate::plot::{PlotError, Series, YScale, line_chart, panel_grid};
use crate::prefaulted;

/// `(t, value)` points of one series.
type Points = Vec<(f64, f64)>;

/// Most points kept per series for figures.
pub const MAX_POINTS: u64 = 6000;

/// Whether a tick is a multiple of `every`, as `k % every == 0`, with the division done
/// only where `k` leaves the stretch known to lie between two multiples: once per `every`
/// ticks when they come in order. A 64-bit division costs tens of cycles, and the
/// simulator asks twice a tick (the trace's decimation and the figures').
#[derive(Debug, Clone, Copy, Default)]
pub struct EveryNth {
    every: u64,
    /// The multiple after the last tick divided (0: none known).
    next: u64,
}

impl EveryNth {
    /// Every `every`-th tick (1 or more).
    pub fn new(every: u64) -> Self {
        Self { every: every.max(1), next: 0 }
    }

    /// Whether `every` divides `k`.
    #[inline]
    pub fn holds(&mut self, k: u64) -> bool {
        // Ticks strictly between the multiples `next − every` and `next` are not ones.
        if k < self.next && k > self.next - self.every {
            return false;
        }
        let r = k % self.every;
        self.next = (k - r).checked_add(self.every).unwrap_or(0);
        r == 0
    }
}

/// Trace rows decimated for plotting. Capacity is reserved and faulted in up front, so
/// recording neither allocates nor grows resident memory during a run of the announced
/// length.
#[derive(Debug, Clone, Default)]
pub struct Recorder {
    every: EveryNth,
    /// Time (s).
    pub t: Vec<f64>,
    /// Entries (1,1), (1,2), (2,1), (2,2) of `R`.
    pub r: Vec<[f64; 4]>,
    /// The same entries of `R_d`.
    pub r_d: Vec<[f64; 4]>,
    /// Attitude error (deg).
    pub err_deg: Vec<f64>,
    /// Rotor rates (rad/s).
    pub omega_r: Vec<[f64; 3]>,
    /// Relative momentum drift.
    pub h_drift_rel: Vec<f64>,
    /// Energy residual (J).
    pub energy_residual: Vec<f64>,
    /// `‖u‖`.
    pub u_norm: Vec<f64>,
    /// `‖τ‖`.
    pub tau_norm: Vec<f64>,
}

impl Recorder {
    /// A recorder for a run of `rows` rows.
    pub fn new(rows: u64) -> Self {
        let every = rows.div_ceil(MAX_POINTS).max(1);
        let n = (rows / every + 2) as usize;
        Self {
            every: EveryNth::new(every),
            t: prefaulted(n),
            r: prefaulted(n),
            r_d: prefaulted(n),
            err_deg: prefaulted(n),
            omega_r: prefaulted(n),
            h_drift_rel: prefaulted(n),
            energy_residual: prefaulted(n),
            u_norm: prefaulted(n),
            tau_norm: prefaulted(n),
        }
    }

    /// Keeps the row if it falls on the decimation grid (or `force`, for the last row).
    pub fn record(&mut self, row: &TraceRow, force: bool) {
        if !self.every.holds(row.tick) && !force {
            return;
        }
        let pick = |m: &[f64; 9]| [m[0], m[1], m[3], m[4]];
        self.t.push(row.t);
        self.r.push(pick(&row.r));
        self.r_d.push(pick(&row.r_d));
        self.err_deg.push(row.err_deg);
        self.omega_r.push(row.omega_r);
        self.h_drift_rel.push(row.h_drift_rel);
        self.energy_residual.push(row.energy_residual);
        self.u_norm.push(row.u_norm());
        self.tau_norm.push(row.tau_norm());
    }

    fn xy(&self, f: impl Fn(usize) -> f64) -> Vec<(f64, f64)> {
        self.t.iter().enumerate().map(|(i, &t)| (t, f(i))).collect()
    }
}

/// Writes the tracking figures into `dir` and returns their file names.
///
/// `effort` is the control-effort comparison: the internally actuated run (`‖u‖`) and
/// the externally actuated run (`‖τ‖`) tracking the same reference.
pub fn tracking_figures(
    dir: &Path,
    name: &str,
    rec: &Recorder,
    effort: Option<(&Recorder, &Recorder)>,
) -> Result<Vec<String>, PlotError> {
    let mut files = vec![attitude_entries(dir, name, rec)?];
    // One chart against t, written as `file` and named in the list.
    let mut chart = |file: &str, title: &str, y: &str, series: &[Series<'_>], scale| {
        line_chart(&dir.join(file), &format!("{name}: {title}"), "t (s)", y, series, scale)?;
        files.push(file.to_owned());
        Ok::<_, PlotError>(())
    };
    fn one(points: &[(f64, f64)]) -> [Series<'_>; 1] {
        [Series { label: "", points, dashed: false }]
    }

    let err = rec.xy(|i| rec.err_deg[i]);
    chart(
        "attitude_error.png",
        "attitude error angle",
        "error (deg, log)",
        &one(&err),
        YScale::Log { floor: 1e-12 },
    )?;

    let rates: Vec<Vec<(f64, f64)>> = (0..3).map(|j| rec.xy(|i| rec.omega_r[i][j])).collect();
    let rate = |j: usize, label| Series { label, points: &rates[j], dashed: false };
    chart(
        "rotor_rates.png",
        "rotor rates relative to the body",
        "rad/s",
        &[rate(0, "Wr1"), rate(1, "Wr2"), rate(2, "Wr3")],
        YScale::Linear,
    )?;

    let drift = rec.xy(|i| rec.h_drift_rel[i]);
    chart(
        "momentum_drift.png",
        "spatial momentum drift |h(t) - h(0)| / |h(0)|",
        "relative drift",
        &one(&drift),
        YScale::Linear,
    )?;

    if rec.energy_residual.iter().any(|v| v.is_finite()) {
        let res = rec.xy(|i| rec.energy_residual[i]);
        let title = "energy change minus rotor work";
        chart("energy_residual.png", title, "J", &one(&res), YScale::Linear)?;
    }

    if let Some((internal, external)) = effort {
        let u = internal.xy(|i| internal.u_norm[i]);
        let tau = external.xy(|i| external.tau_norm[i]);
        chart(
            "control_effort.png",
            "control effort, rotors vs gas jets (same reference)",
            "N m",
            &[
                Series { label: "|u| rotor torque (internal)", points: &u, dashed: false },
                Series { label: "|tau| body torque (external)", points: &tau, dashed: false },
            ],
            YScale::Linear,
        )?;
    }
    Ok(files)
}

/// `attitude_entries.png`: four entries of `R` against those of `R_d`.
fn attitude_entries(dir: &Path, name: &str, rec: &Recorder) -> Result<String, PlotError> {
    let labels = ["(1,1)", "(1,2)", "(2,1)", "(2,2)"];
    let entries: Vec<(Points, Points)> =
        (0..4).map(|j| (rec.xy(|i| rec.r[i][j]), rec.xy(|i| rec.r_d[i][j]))).collect();
    let series: Vec<[Series<'_>; 2]> = entries
        .iter()
        .map(|(r, rd)| {
            [
                Series { label: "R (plant)", points: r, dashed: false },
                Series { label: "R_d (reference)", points: rd, dashed: true },
            ]
        })
        .collect();
    let panels: Vec<(String, &[Series<'_>])> =
        labels.iter().zip(&series).map(|(l, s)| (format!("entry {l}"), &s[..])).collect();
    let panels: Vec<(&str, &str, &[Series<'_>])> =
        panels.iter().map(|(t, s)| (t.as_str(), "", *s)).collect();
    let file = "attitude_entries.png";
    panel_grid(&dir.join(file), &format!("{name}: attitude R(t) against R_d(t)"), (2, 2), &panels)?;
    Ok(file.to_owned())
}

#[cfg(test)]
mod tests {
    use super::EveryNth;

    /// `EveryNth` answers as `k % every == 0` does, for ticks in order, repeated, skipped
    /// ahead, gone back and at the end of the range.
    #[test]
    fn every_nth_answers_as_the_remainder_does() {
        for every in [1, 2, 7, 1000] {
            let mut e = EveryNth::new(every);
            let odd = [5000, 4999, 3, 3, 12_345, 0, u64::MAX - 6, u64::MAX - 1, u64::MAX, 17];
            for k in (0..3000).chain(odd) {
                assert_eq!(e.holds(k), k % every == 0, "every {every}, tick {k}");
            }
        }
    }
}
