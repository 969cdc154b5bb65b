//! Per-tick metrics of a run: attitude error angle, rate error, control effort, spatial
//! momentum and its drift, and the residual of energy change minus rotor work.
//!
//! With a constant disturbance torque `τ_d` on the body (a scenario option), momentum
//! and energy are no longer conserved: `ḣ = R τ_d` and `Ṫ = u·Θ̇ + τ_d·Ω`. The drift
//! and the residual are then taken against `h(0) + ∫ R τ_d dt` and the rotor work plus
//! `∫ τ_d·Ω dt`, both by the trapezoidal rule over the ticks (second order, so they
//! stay small, not at rounding level).

use glam::DVec3;
use rotorloop_common::params::{BodyParams, ReferenceState, RotorBodyState};
use rotorloop_common::so3::{rotation_angle, to_row_major};

/// One row of `trace.csv`: the state, reference and torques at tick `k`, and metrics.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TraceRow {
    /// Tick index `k`.
    pub tick: u64,
    /// Simulated time `t_k = k dt` (s).
    pub t: f64,
    /// `R`, row-major.
    pub r: [f64; 9],
    /// `R_d`, row-major.
    pub r_d: [f64; 9],
    /// `Ω` (rad/s).
    pub omega: [f64; 3],
    /// `Ω_d` (rad/s).
    pub omega_d: [f64; 3],
    /// `Ω_r` (rad/s).
    pub omega_r: [f64; 3],
    /// Rotor torque `u` computed at this tick (N m); applied over `[t_k, t_k+1]` when
    /// the actuation is internal.
    pub u: [f64; 3],
    /// Body torque `τ` computed at this tick (N m); applied when the actuation is external.
    pub tau: [f64; 3],
    /// Attitude error angle of `E = R_d Rᵀ` (degrees).
    pub err_deg: f64,
    /// `‖Ω − Ω_d‖` (rad/s).
    pub werr: f64,
    /// Spatial angular momentum `h = RΠ` (N m s), from the reported state.
    pub h: [f64; 3],
    /// `‖h − h(0)‖ / ‖h(0)‖`.
    pub h_drift_rel: f64,
    /// `T_k − T_0 − Σ u·ΔΘ` (J): zero for exact dynamics; NaN for a body without rotors.
    pub energy_residual: f64,
    /// The actuation delay of the first torque that took effect during `[t_k, t_k+1]`
    /// (s): when it took effect minus its own tick's time; NaN when none did (a miss, the
    /// last tick, or a tick not seen). 0 for the plain zero-order hold.
    pub delay_s: f64,
}

impl TraceRow {
    /// `‖u‖`.
    pub fn u_norm(&self) -> f64 {
        DVec3::from_array(self.u).length()
    }
    /// `‖τ‖`.
    pub fn tau_norm(&self) -> f64 {
        DVec3::from_array(self.tau).length()
    }
}

/// Running metrics of one plant. Feed it every tick, in order, with the rotor torque that
/// was held over the tick before (what a state sample carries).
#[derive(Debug, Clone)]
pub struct Metrics {
    body: BodyParams,
    has_rotors: bool,
    h0: DVec3,
    h0_norm: f64,
    energy0: f64,
    work: f64,
    prev_theta: Option<DVec3>,
    last_residual: f64,
    rebase: bool,
    disturbance: DVec3,
    /// `∫ R τ_d dt` so far.
    h_disturbance: DVec3,
    /// `(t, R τ_d, τ_d·Ω)` at the previous row.
    prev_disturbance: Option<(f64, DVec3, f64)>,
}

/// Length of [`Metrics::save`].
pub const METRICS_STATE_LEN: usize = 16;

impl Metrics {
    /// Metrics for a plant with these parameters; `initial` is its state at tick 0.
    pub fn new(body: BodyParams, initial: &RotorBodyState) -> Self {
        let h0 = initial.spatial_momentum(&body);
        Self {
            body,
            has_rotors: body.rotor_inertia.cmpgt(DVec3::ZERO).all(),
            h0,
            h0_norm: h0.length(),
            energy0: body.kinetic_energy(initial.omega, initial.omega_r),
            work: 0.0,
            prev_theta: None,
            last_residual: 0.0,
            rebase: false,
            disturbance: DVec3::ZERO,
            h_disturbance: DVec3::ZERO,
            prev_disturbance: None,
        }
    }

    /// The same metrics for a plant under the constant body-frame disturbance `tau_d`.
    pub fn with_disturbance(mut self, tau_d: DVec3) -> Self {
        self.disturbance = tau_d;
        self
    }

    /// The row for tick `k`. `held_before` is the rotor torque the plant held over
    /// `[t_k−1, t_k]` (ignored at the first row; zero for a gas-jet body), for the rotor work
    /// `u · ΔΘ` of a plain zero-order hold.
    #[inline]
    #[allow(clippy::too_many_arguments)]
    pub fn observe(
        &mut self,
        tick: u64,
        t: f64,
        x: &RotorBodyState,
        reference: &ReferenceState,
        u: DVec3,
        tau: DVec3,
        held_before: DVec3,
    ) -> TraceRow {
        let work = self.prev_theta.map_or(0.0, |p| held_before.dot(x.theta - p));
        self.observe_work(tick, t, x, reference, u, tau, work)
    }

    /// The row for tick `k`, with `work_before` the rotor work over `[t_k−1, t_k]` as the
    /// plant integrated it (the sum over the tick's pieces of `u · ΔΘ`; a delayed
    /// zero-order hold changes the torque inside the tick).
    #[inline]
    #[allow(clippy::too_many_arguments)]
    pub fn observe_work(
        &mut self,
        tick: u64,
        t: f64,
        x: &RotorBodyState,
        reference: &ReferenceState,
        u: DVec3,
        tau: DVec3,
        work_before: f64,
    ) -> TraceRow {
        let e = reference.r_d * x.r.transpose();
        let h = x.spatial_momentum(&self.body);
        if self.disturbance != DVec3::ZERO {
            let now = (t, x.r * self.disturbance, self.disturbance.dot(x.omega));
            if self.rebase {
                // The impulse over a gap is unknown: the drift restarts from zero.
                self.h_disturbance = h - self.h0;
            } else if let Some((t0, rt0, p0)) = self.prev_disturbance {
                let half = 0.5 * (t - t0);
                self.h_disturbance += half * (rt0 + now.1);
                self.work += half * (p0 + now.2);
            }
            self.prev_disturbance = Some(now);
        }
        let energy_residual = if self.has_rotors {
            let energy = self.body.kinetic_energy(x.omega, x.omega_r);
            if self.rebase {
                // After a gap the rotor work of the missing ticks is unknown: continue
                // the residual from where it was.
                self.work = energy - self.energy0 - self.last_residual;
                self.rebase = false;
            } else if self.prev_theta.is_some() {
                // Rotor work over the previous tick, summed over its pieces: exact for a
                // torque held piecewise.
                self.work += work_before;
            }
            self.last_residual = energy - self.energy0 - self.work;
            self.last_residual
        } else {
            f64::NAN
        };
        self.prev_theta = Some(x.theta);
        TraceRow {
            tick,
            t,
            r: to_row_major(&x.r),
            r_d: to_row_major(&reference.r_d),
            omega: x.omega.to_array(),
            omega_d: reference.omega_d.to_array(),
            omega_r: x.omega_r.to_array(),
            u: u.to_array(),
            tau: tau.to_array(),
            err_deg: rotation_angle(&e).to_degrees(),
            werr: (x.omega - reference.omega_d).length(),
            h: h.to_array(),
            h_drift_rel: if self.h0_norm > 0.0 {
                (h - self.h0 - self.h_disturbance).length() / self.h0_norm
            } else {
                0.0
            },
            energy_residual,
            delay_s: f64::NAN,
        }
    }

    /// The running state, to continue in another process ([`Metrics::restore`]).
    pub fn save(&self) -> [f64; METRICS_STATE_LEN] {
        let t = self.prev_theta.unwrap_or(DVec3::NAN);
        [
            self.h0.x,
            self.h0.y,
            self.h0.z,
            self.energy0,
            self.work,
            self.last_residual,
            t.x,
            t.y,
            t.z,
            f64::from(u8::from(self.prev_theta.is_some())),
            self.disturbance.x,
            self.disturbance.y,
            self.disturbance.z,
            self.h_disturbance.x,
            self.h_disturbance.y,
            self.h_disturbance.z,
        ]
    }

    /// Metrics continuing from [`Metrics::save`], after a gap of unknown ticks: the energy
    /// residual is carried over rather than recomputed across the gap.
    pub fn restore(body: BodyParams, s: &[f64; METRICS_STATE_LEN]) -> Self {
        let h0 = DVec3::new(s[0], s[1], s[2]);
        Self {
            body,
            has_rotors: body.rotor_inertia.cmpgt(DVec3::ZERO).all(),
            h0,
            h0_norm: h0.length(),
            energy0: s[3],
            work: s[4],
            last_residual: s[5],
            prev_theta: (s[9] > 0.5).then(|| DVec3::new(s[6], s[7], s[8])),
            rebase: true,
            disturbance: DVec3::new(s[10], s[11], s[12]),
            h_disturbance: DVec3::new(s[13], s[14], s[15]),
            prev_disturbance: None,
        }
    }

    /// Kinetic energy at tick 0 (J), the scale of the energy residual.
    pub fn initial_energy(&self) -> f64 {
        self.energy0
    }
}
