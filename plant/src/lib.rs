//! The plant: a rigid body with three internal rotors (spec, "The plant"), and the same
//! integrator for the externally actuated gas-jet body (spec, "The externally actuated
//! body"). No IPC and no clock: the caller passes `dt` and the held inputs.
//!
//! # State and integrator
//!
//! The integrator's state is `(R, h, p, Θ)`:
//! - `R ∈ SO(3)`, the attitude;
//! - `h = R Π`, the spatial angular momentum (inertial frame);
//! - `p = K(Ω + Ω_r)`, the rotors' axial angular momenta;
//! - `Θ`, the rotor angles.
//!
//! From these, `Π = Rᵀh`, `Ω = I⁻¹(Π − p)` (since `Π = IΩ + p`) and `Ω_r = K⁻¹p − Ω`.
//! The spec's equations become `Ṙ = R hat(Ω)`, `ḣ = R τ_b`, `ṗ = u`, `Θ̇ = Ω_r`, where
//! `τ_b` is an external body torque (gas jets or a disturbance; zero for the paper's
//! internally actuated body). Substituting shows this is the spec's system: `Π̇ = Π×Ω + τ_b`
//! and `K(Ω̇ + Ω̇_r) = u`, so `IΩ̇ = Π×Ω − u + τ_b` and `Ω̇_r = K⁻¹u − Ω̇`.
//!
//! **Why this integrator.** A fourth-order Runge–Kutta–Munthe-Kaas method (RKMK4) on the
//! Lie group `SO(3) × R⁹`: `R` is advanced by right-multiplying with `exp` of a stage
//! combination, so it stays on SO(3) to rounding without re-orthonormalisation (which
//! would perturb it by a non-physical projection every tick), and the vector part
//! `(h, p, Θ)` is classical RK4. With the rotor torque held over a tick (zero-order hold),
//! `p` is integrated exactly, and with no external torque `h` is not changed at all, so
//! the spatial momentum the rotors cannot change is conserved to rounding by construction
//! instead of drifting with the truncation error. `Θ` gets fourth-order quadrature of the
//! stage rates, so the rotor work `u·ΔΘ` matches the energy change to truncation level.
//! Cost: four `exp` and three `dexp⁻¹` per step; no allocation.
//!
//! [`actuator`] is the actuator model (the delayed zero-order hold, one tick's piecewise
//! integration through the limits), [`policy`] what the plant decides beyond the dynamics
//! (the hold rule, misses, safe mode, restarts, the state sample), and [`process`] the
//! `plant` process around it.

pub mod actuator;
pub mod policy;
pub mod process;

/// This crate's role in the loop, by name (its node, resume slot and flight record).
pub const ROLE: &str = rotorloop_common::graph::Role::Plant.name();

use glam::{DMat3, DVec3};
use rotorloop_common::params::{BodyParams, RotorBodyState};
use rotorloop_common::scenario::Actuation;
use rotorloop_common::so3::{dexp_inv, exp};

/// Inputs held constant over one tick (zero-order hold).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct BodyInput {
    /// Rotor motor torques `u` (N m): torque on rotor `i` about `e_i`, reaction on the body.
    pub rotor_torque: DVec3,
    /// External torque on the body `τ_b` (N m, body frame): gas jets or a disturbance.
    pub body_torque: DVec3,
}

impl BodyInput {
    /// What an answer of rotor torques `u` and body torque `τ` puts on a body of
    /// `actuation`: `u` (internal) or `τ` (external), the other zero.
    pub fn of(actuation: Actuation, u: DVec3, tau: DVec3) -> Self {
        match actuation {
            Actuation::Internal => Self { rotor_torque: u, body_torque: DVec3::ZERO },
            Actuation::External => Self { rotor_torque: DVec3::ZERO, body_torque: tau },
        }
    }
}

/// A rigid body with three rotors, or without (`K = 0`: the gas-jet body), integrated
/// with RKMK4. See the module documentation for the state and the choice of integrator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Body {
    params: BodyParams,
    rotor_inertia_inv: DVec3,
    has_rotors: bool,
    r: DMat3,
    h: DVec3,
    p: DVec3,
    theta: DVec3,
}

/// The rates of the vector part `(h, p, Θ)` and the body rate `Ω` at one stage.
#[derive(Clone, Copy)]
struct Rates {
    omega: DVec3,
    h_dot: DVec3,
    p_dot: DVec3,
    theta_dot: DVec3,
}

impl Body {
    /// A body in the given state. With `params.rotor_inertia == 0` the body has no rotors:
    /// rotor torques are ignored and `Ω_r`, `Θ` stay zero.
    pub fn new(params: BodyParams, state: RotorBodyState) -> Self {
        let has_rotors = params.rotor_inertia.cmpgt(DVec3::ZERO).all();
        let rotor_inertia_inv = if has_rotors { params.rotor_inertia.recip() } else { DVec3::ZERO };
        let (omega_r, theta) =
            if has_rotors { (state.omega_r, state.theta) } else { (DVec3::ZERO, DVec3::ZERO) };
        Self {
            params,
            rotor_inertia_inv,
            has_rotors,
            r: state.r,
            h: state.r * params.body_momentum(state.omega, omega_r),
            p: params.rotor_inertia * (state.omega + omega_r),
            theta,
        }
    }

    /// The body's parameters.
    pub fn params(&self) -> &BodyParams {
        &self.params
    }

    /// Whether the body has rotors (`K ≠ 0`).
    pub fn has_rotors(&self) -> bool {
        self.has_rotors
    }

    /// `Ω` from the integrator state at attitude `r`, momentum `h`, rotor momenta `p`.
    #[inline]
    fn omega_of(&self, r: &DMat3, h: DVec3, p: DVec3) -> DVec3 {
        self.params.inertia_inv * (r.transpose() * h - p)
    }

    #[inline]
    fn rates(&self, r: &DMat3, h: DVec3, p: DVec3, input: &BodyInput) -> Rates {
        let omega = self.omega_of(r, h, p);
        let (p_dot, theta_dot) = if self.has_rotors {
            (input.rotor_torque, self.rotor_inertia_inv * p - omega)
        } else {
            (DVec3::ZERO, DVec3::ZERO)
        };
        Rates { omega, h_dot: *r * input.body_torque, p_dot, theta_dot }
    }

    /// The current state `(R, Ω, Ω_r, Θ)`.
    #[inline]
    pub fn state(&self) -> RotorBodyState {
        let omega = self.omega_of(&self.r, self.h, self.p);
        let omega_r =
            if self.has_rotors { self.rotor_inertia_inv * self.p - omega } else { DVec3::ZERO };
        RotorBodyState { r: self.r, omega, omega_r, theta: self.theta }
    }

    /// Whether every number of the state is finite (an unstable configuration, such as
    /// gains far too high for the tick rate, can make the integration blow up).
    #[inline]
    pub fn is_finite(&self) -> bool {
        self.r.is_finite() && self.h.is_finite() && self.p.is_finite() && self.theta.is_finite()
    }

    /// The integrator's own state `(R, h, p, Θ)`: resuming from it with
    /// [`Body::from_internal`] continues bit for bit.
    pub fn internal(&self) -> (DMat3, DVec3, DVec3, DVec3) {
        (self.r, self.h, self.p, self.theta)
    }

    /// A body continuing from an integrator state saved with [`Body::internal`].
    pub fn from_internal(params: BodyParams, r: DMat3, h: DVec3, p: DVec3, theta: DVec3) -> Self {
        let mut b = Self::new(
            params,
            RotorBodyState { r, omega: DVec3::ZERO, omega_r: DVec3::ZERO, theta },
        );
        b.h = h;
        b.p = if b.has_rotors { p } else { DVec3::ZERO };
        b.theta = if b.has_rotors { theta } else { DVec3::ZERO };
        b
    }

    /// Spatial angular momentum `h = RΠ` as carried by the integrator.
    pub fn spatial_momentum(&self) -> DVec3 {
        self.h
    }

    /// `Ω̇` at the current state under `input`: `IΩ̇ = Π×Ω − u + τ_b` (spec, "The plant").
    #[inline]
    pub fn omega_dot(&self, input: &BodyInput) -> DVec3 {
        let pi = self.r.transpose() * self.h;
        let omega = self.params.inertia_inv * (pi - self.p);
        let u = if self.has_rotors { input.rotor_torque } else { DVec3::ZERO };
        self.params.inertia_inv * (pi.cross(omega) - u + input.body_torque)
    }

    /// Advances by `dt` with `input` held constant (zero-order hold).
    #[inline]
    pub fn step(&mut self, input: BodyInput, dt: f64) {
        self.step_with(|_| input, dt);
    }

    /// Advances by `dt` with inputs given as a function of the time offset into the step
    /// (`0 ≤ s ≤ dt`): the reference generator uses it to follow a known torque profile
    /// within the step. One RKMK4 step (module documentation).
    #[inline]
    pub fn step_with(&mut self, input: impl Fn(f64) -> BodyInput, dt: f64) {
        let half = 0.5 * dt;
        self.step_inputs([input(0.0), input(half), input(dt)], dt);
    }

    /// Advances by `dt` with the inputs at the step's start, middle and end given: one
    /// RKMK4 step (module documentation), what [`Body::step_with`] does once it has them.
    #[inline]
    pub fn step_inputs(&mut self, [in0, in_half, in_end]: [BodyInput; 3], dt: f64) {
        let (r0, h0, p0, th0) = (self.r, self.h, self.p, self.theta);
        let half = 0.5 * dt;

        let f1 = self.rates(&r0, h0, p0, &in0);
        let k1 = f1.omega * dt;

        let th2 = 0.5 * k1;
        let r2 = r0 * exp(th2);
        let f2 = self.rates(&r2, h0 + half * f1.h_dot, p0 + half * f1.p_dot, &in_half);
        let k2 = dexp_inv(-th2, f2.omega) * dt;

        let th3 = 0.5 * k2;
        let r3 = r0 * exp(th3);
        let f3 = self.rates(&r3, h0 + half * f2.h_dot, p0 + half * f2.p_dot, &in_half);
        let k3 = dexp_inv(-th3, f3.omega) * dt;

        let r4 = r0 * exp(k3);
        let f4 = self.rates(&r4, h0 + dt * f3.h_dot, p0 + dt * f3.p_dot, &in_end);
        let k4 = dexp_inv(-k3, f4.omega) * dt;

        let w = dt / 6.0;
        self.r = r0 * exp((k1 + 2.0 * (k2 + k3) + k4) * (1.0 / 6.0));
        self.h = h0 + w * (f1.h_dot + 2.0 * (f2.h_dot + f3.h_dot) + f4.h_dot);
        self.p = p0 + w * (f1.p_dot + 2.0 * (f2.p_dot + f3.p_dot) + f4.p_dot);
        self.theta = th0 + w * (f1.theta_dot + 2.0 * (f2.theta_dot + f3.theta_dot) + f4.theta_dot);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rotorloop_common::so3::orthonormality_error;

    fn paper_body() -> (BodyParams, RotorBodyState) {
        let s = rotorloop_common::scenario::Scenario::load("paper-zero").expect("builtin");
        (s.plant, s.plant_init)
    }

    #[test]
    fn state_round_trips_through_the_integrator_representation() {
        let (params, init) = paper_body();
        let b = Body::new(params, init);
        let s = b.state();
        assert!((s.omega - init.omega).length() < 1e-14);
        assert!((s.omega_r - init.omega_r).length() < 1e-14);
        assert_eq!(s.r, init.r);
    }

    #[test]
    fn resuming_from_the_internal_state_continues_bit_for_bit() {
        let (params, init) = paper_body();
        let input =
            BodyInput { rotor_torque: DVec3::new(0.3, -0.2, 0.1), body_torque: DVec3::ZERO };
        let mut a = Body::new(params, init);
        for _ in 0..100 {
            a.step(input, 1e-3);
        }
        let (r, h, p, th) = a.internal();
        let mut b = Body::from_internal(params, r, h, p, th);
        for _ in 0..100 {
            a.step(input, 1e-3);
            b.step(input, 1e-3);
        }
        assert_eq!(a, b);
    }

    #[test]
    fn integrator_converges_at_fourth_order() {
        // Error against a fine-step solution shrinks ~16x per halving of dt.
        let (params, init) = paper_body();
        let input = |s: f64| BodyInput {
            rotor_torque: DVec3::new(0.3 + s, -0.2, 0.1),
            body_torque: DVec3::ZERO,
        };
        let run = |n: u32| {
            let mut b = Body::new(params, init);
            let dt = 1.0 / f64::from(n);
            for k in 0..n {
                let t0 = f64::from(k) * dt;
                b.step_with(|s| input(t0 + s), dt);
            }
            b.state()
        };
        let reference = run(3200);
        let err = |n| {
            let s = run(n);
            (s.r - reference.r).to_cols_array().iter().map(|d| d.abs()).fold(0.0, f64::max)
                + (s.omega - reference.omega).length()
        };
        let (e1, e2) = (err(25), err(50));
        let ratio = e1 / e2;
        assert!(ratio > 12.0 && ratio < 20.0, "e(25)={e1:e} e(50)={e2:e} ratio={ratio}");
    }

    #[test]
    fn gas_jet_body_ignores_rotor_torque_and_keeps_r_orthonormal() {
        let (params, init) = paper_body();
        let mut b = Body::new(params.without_rotors(), init);
        for _ in 0..1000 {
            b.step(
                BodyInput {
                    rotor_torque: DVec3::splat(5.0),
                    body_torque: DVec3::new(0.1, 0.0, -0.2),
                },
                1e-3,
            );
        }
        let s = b.state();
        assert_eq!(s.omega_r, DVec3::ZERO);
        let (o, d) = orthonormality_error(&s.r);
        assert!(o < 1e-13 && d < 1e-13);
    }
}
