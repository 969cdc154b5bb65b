//! The paper's law: the geometric PID almost-global tracking law (spec, "The control
//! law"), for the internally actuated body (rotor torque `u`, Theorem 2) and the
//! externally actuated one (body torque `τ`).
//!
//! Discrete time (spec): at tick `k` the law uses `ξ_I,k`, then advances
//! `ξ_I,k+1 = ξ_I,k + dt · s_k` (forward Euler over the tick).
//!
//! # Anti-windup (an extension; inactive without actuator limits)
//!
//! With rotor limits ([`ActuatorLimits`]) the plant may deliver less than `u`. While it
//! does, the integral term keeps accumulating error that the actuators cannot act on
//! and overshoots once they recover ("windup"). [`AntiWindup::Conditional`] (the
//! default) is conditional integration: on a tick whose command the limits change, the
//! law holds `ξ_I` unless the step would shrink it (`s·ξ_I < 0`). The controller applies
//! the same limits the plant does, to the same state, so it knows exactly which ticks
//! saturate. The law's `u` itself is published unclamped: the plant's actuators clamp.

use glam::DVec3;
use rotorloop_common::so3::vee;

use super::{ControlOutput, Law, LawState};
use rotorloop_common::params::{
    ActuatorLimits, AntiWindup, BodyParams, Gains, ReferenceState, RotorBodyState,
};

/// The law of the spec for given gains and body model, evaluated with integral state `xi_i`.
/// Pure: it changes nothing. `body` is the controller's model of the plant.
#[inline]
pub fn control_law(
    gains: &Gains,
    body: &BodyParams,
    x: &RotorBodyState,
    reference: &ReferenceState,
    xi_i: DVec3,
) -> ControlOutput {
    let r = x.r;
    let e = reference.r_d * r.transpose(); // E = R_d Rᵀ
    let p = gains.p;
    let pe = p * e;
    let psi = (p.col(0).x + p.col(1).y + p.col(2).z) - (pe.col(0).x + pe.col(1).y + pe.col(2).z);
    let eta = r * (reference.omega_d - x.omega);
    let s = vee(pe - e.transpose() * p); // PE − EᵀP is skew: vee is exact
    let a = -gains.kp * s - gains.kd * eta - gains.ki * xi_i;
    let omega_dot_star =
        reference.omega_d_dot + x.omega.cross(reference.omega_d) - r.transpose() * a;
    let i_omega = body.inertia * x.omega;
    let tau = body.inertia * omega_dot_star - i_omega.cross(x.omega);
    let u = (body.rotor_inertia * (x.omega + x.omega_r)).cross(x.omega) - tau;
    ControlOutput { rotor_torque: u, body_torque: tau, s, eta, psi, xi_i, saturated: false }
}

/// The law with its integral state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeometricPid {
    gains: Gains,
    model: BodyParams,
    limits: ActuatorLimits,
    anti_windup: AntiWindup,
    xi_i: DVec3,
}

impl GeometricPid {
    /// A controller with zero integral state. `model` is its model of the plant's
    /// inertia (`I`, `K`).
    pub fn new(gains: Gains, model: BodyParams) -> Self {
        Self {
            gains,
            model,
            limits: ActuatorLimits::default(),
            anti_windup: AntiWindup::default(),
            xi_i: DVec3::ZERO,
        }
    }

    /// The same law aware of the plant's actuator limits, with an anti-windup rule.
    pub fn with_limits(mut self, limits: ActuatorLimits, anti_windup: AntiWindup) -> Self {
        self.limits = limits;
        self.anti_windup = anti_windup;
        self
    }

    /// Continue from a known integral state (bumpless restart).
    pub fn with_integral_state(mut self, xi_i: DVec3) -> Self {
        self.xi_i = xi_i;
        self
    }

    /// The current integral state `ξ_I`.
    pub fn integral_state(&self) -> DVec3 {
        self.xi_i
    }

    /// The gains.
    pub fn gains(&self) -> &Gains {
        &self.gains
    }
}

impl Law for GeometricPid {
    /// Computes the tick's torques from the state and reference at tick `k`, then
    /// advances `ξ_I` over the tick.
    #[inline]
    fn step(&mut self, x: &RotorBodyState, reference: &ReferenceState, dt: f64) -> ControlOutput {
        let mut out = control_law(&self.gains, &self.model, x, reference, self.xi_i);
        if self.limits.any() {
            out.saturated = self.limits.apply(out.rotor_torque, x.omega_r).1;
        }
        let hold = out.saturated
            && self.anti_windup == AntiWindup::Conditional
            && out.s.dot(self.xi_i) >= 0.0;
        if !hold {
            self.xi_i += dt * out.s;
        }
        out
    }

    fn state(&self) -> LawState {
        LawState::of_vector(self.xi_i)
    }

    fn restore(&mut self, state: &LawState) {
        self.xi_i = state.vector();
    }
}
