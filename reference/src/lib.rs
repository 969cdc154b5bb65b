//! The reference generator (spec, "The reference generator"): a second, "dummy" body with
//! rotors, driven by a known rotor-torque profile `u_d(t)` through exactly the plant's
//! equations and integrator. It yields `R_d, Ω_d, Ω̇_d` each tick.
//!
//! Its rotor rates at `t = 0` are set by momentum matching, so that the reference lies on
//! the level set of the plant's momentum map: `Ω_rd(0) = K_d⁻¹(R_d(0)ᵀh − (I_d+K_d)Ω_d(0))`.
//! Time is passed in: [`Reference::step`] takes `t` and `dt`; nothing here reads a clock.
//!
//! [`policy`] holds what the reference process decides (how far ahead to publish, what a
//! restart re-publishes) and [`process`] the `reference` process around it.

pub mod policy;
pub mod process;

/// This crate's role in the loop, by name (its node, resume slot and flight record).
pub const ROLE: &str = rotorloop_common::graph::Role::Reference.name();

use glam::{DMat3, DVec3};
use rotorloop_common::params::{BodyParams, ReferenceState, RotorBodyState};
use rotorloop_common::scenario::TorqueProfile;
use rotorloop_plant::{Body, BodyInput};

/// The dummy body and its torque profile.
#[derive(Debug, Clone, Copy)]
pub struct Reference {
    body: Body,
    profile: TorqueProfile,
    /// `u_d` at the end of the last step, with the bits of its time: the next tick's
    /// sample and the first stage of its step ask for `u_d` at that same time (when
    /// `t + dt` of one tick is bit for bit the next tick's `t`), and take it from here
    /// instead of evaluating three sines again. The same argument gives the same bits.
    end_u: Option<(u64, DVec3)>,
}

/// Two references are equal when their bodies and profiles are (the kept `u_d` is a
/// value they would both compute).
impl PartialEq for Reference {
    fn eq(&self, other: &Self) -> bool {
        self.body == other.body && self.profile == other.profile
    }
}

/// `Ω_rd(0)` that gives the reference body the spatial momentum `h` (spec).
pub fn matched_rotor_rates(params: &BodyParams, r_d: &DMat3, omega_d: DVec3, h: DVec3) -> DVec3 {
    (r_d.transpose() * h - (params.inertia * omega_d + params.rotor_inertia * omega_d))
        / params.rotor_inertia
}

impl Reference {
    /// A reference whose rotor rates are matched to the plant's spatial momentum `h`.
    pub fn matched(
        params: BodyParams,
        r_d0: DMat3,
        omega_d0: DVec3,
        profile: TorqueProfile,
        plant_momentum: DVec3,
    ) -> Self {
        let omega_r = matched_rotor_rates(&params, &r_d0, omega_d0, plant_momentum);
        Self::resume(
            params,
            RotorBodyState { r: r_d0, omega: omega_d0, omega_r, theta: DVec3::ZERO },
            profile,
        )
    }

    /// The reference of a scenario, momentum-matched to the scenario's rotor-actuated
    /// plant (the same reference whatever the plant's actuation).
    pub fn for_scenario(s: &rotorloop_common::scenario::Scenario) -> Self {
        let h = s.plant_init.spatial_momentum(&s.plant);
        Self::matched(s.reference, s.reference_attitude, s.reference_omega, s.reference_torque, h)
    }

    /// A reference continuing from a full dummy-body state (e.g. the last one published).
    pub fn resume(params: BodyParams, state: RotorBodyState, profile: TorqueProfile) -> Self {
        Self::of(Body::new(params, state), profile)
    }

    fn of(body: Body, profile: TorqueProfile) -> Self {
        Self { body, profile, end_u: None }
    }

    /// `u_d(t)`: the one kept if `t` is its time, bit for bit.
    #[inline]
    fn u_d(&self, t: f64) -> DVec3 {
        match self.end_u {
            Some((bits, u)) if bits == t.to_bits() => u,
            _ => self.profile.at(t),
        }
    }

    /// The desired attitude at time `t` (the time of the current state).
    #[inline]
    pub fn sample(&self, t: f64) -> ReferenceState {
        let s = self.body.state();
        let input = BodyInput { rotor_torque: self.u_d(t), body_torque: DVec3::ZERO };
        ReferenceState { r_d: s.r, omega_d: s.omega, omega_d_dot: self.body.omega_dot(&input) }
    }

    /// The dummy body's integrator state (see `Body::internal`), for an exact resume.
    pub fn internal(&self) -> (DMat3, DVec3, DVec3, DVec3) {
        self.body.internal()
    }

    /// A reference continuing bit for bit from a saved integrator state.
    pub fn from_internal(
        params: BodyParams,
        (r, h, p, theta): (DMat3, DVec3, DVec3, DVec3),
        profile: TorqueProfile,
    ) -> Self {
        Self::of(Body::from_internal(params, r, h, p, theta), profile)
    }

    /// The full dummy-body state (for resuming and for momentum checks).
    pub fn body_state(&self) -> RotorBodyState {
        self.body.state()
    }

    /// The dummy body's spatial momentum.
    pub fn spatial_momentum(&self) -> DVec3 {
        self.body.spatial_momentum()
    }

    /// Advances from `t` to `t + dt`, following `u_d` within the step.
    #[inline]
    pub fn step(&mut self, t: f64, dt: f64) {
        // The times `step_with` would pass `u_d`: t + 0, t + dt/2, t + dt.
        let (t0, t_half, t_end) = (t + 0.0, t + 0.5 * dt, t + dt);
        let u_end = self.u_d(t_end);
        let input = |u: DVec3| BodyInput { rotor_torque: u, body_torque: DVec3::ZERO };
        let inputs = [input(self.u_d(t0)), input(self.profile.at(t_half)), input(u_end)];
        self.body.step_inputs(inputs, dt);
        self.end_u = Some((t_end.to_bits(), u_end));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rotorloop_common::scenario::Scenario;

    #[test]
    fn momentum_matching_makes_reference_momentum_equal_the_plants() {
        for name in ["paper-zero", "paper-constant", "paper-sinusoid"] {
            let s = Scenario::load(name).expect("builtin");
            let h = s.plant_init.spatial_momentum(&s.plant);
            let mut reference = Reference::matched(
                s.reference,
                s.reference_attitude,
                s.reference_omega,
                s.reference_torque,
                h,
            );
            // Recompute the reference's momentum from its reported state, by the spec's
            // formula h = R (I+K)Ω + R K Ω_r, not from the integrator's carried value.
            let check = |r: &Reference| {
                let st = r.body_state();
                st.spatial_momentum(&s.reference)
            };
            assert!((check(&reference) - h).length() <= 1e-12 * h.length(), "{name} at t=0");
            // The rotors are internal: it stays matched while the profile drives them.
            let dt = 1e-3;
            for k in 0..5000 {
                reference.step(k as f64 * dt, dt);
            }
            assert!((check(&reference) - h).length() <= 1e-11 * h.length(), "{name} at t=5");
        }
    }

    /// Keeping `u_d(t + dt)` for the next tick changes no bit: the reference samples and
    /// steps as the plant's integrator does with every `u_d` evaluated where it is asked.
    #[test]
    fn the_kept_end_torque_changes_no_bit_of_the_reference() {
        let s = Scenario::load("paper-sinusoid").expect("builtin");
        let mut r = Reference::for_scenario(&s);
        let (r0, h0, p0, th0) = r.internal();
        let mut body = Body::from_internal(s.reference, r0, h0, p0, th0);
        let profile = s.reference_torque;
        let input = |u: DVec3| BodyInput { rotor_torque: u, body_torque: DVec3::ZERO };
        let dt = s.dt();
        for k in 0..20_000 {
            let t = k as f64 * dt;
            let a = r.sample(t);
            let want = body.omega_dot(&input(profile.at(t)));
            assert_eq!(
                a.omega_d_dot.to_array().map(f64::to_bits),
                want.to_array().map(f64::to_bits)
            );
            r.step(t, dt);
            body.step_with(|s| input(profile.at(t + s)), dt);
            let bits = |(r, h, p, th): (DMat3, DVec3, DVec3, DVec3)| {
                let mut v = r.to_cols_array().to_vec();
                v.extend([h, p, th].iter().flat_map(|x| x.to_array()));
                v.into_iter().map(f64::to_bits).collect::<Vec<_>>()
            };
            assert_eq!(bits(r.internal()), bits(body.internal()), "tick {k}");
        }
    }

    #[test]
    fn omega_d_dot_is_the_derivative_of_omega_d() {
        let s = Scenario::load("paper-sinusoid").expect("builtin");
        let h = s.plant_init.spatial_momentum(&s.plant);
        let mut r = Reference::matched(
            s.reference,
            s.reference_attitude,
            s.reference_omega,
            s.reference_torque,
            h,
        );
        let dt = 1e-4;
        let t0 = 0.3;
        for k in 0..3000 {
            r.step(k as f64 * dt, dt);
        }
        // Central difference with a small probe step: truncation O(dt²) ≈ 1e-9 here.
        let dt = 1e-5;
        let before = r;
        let a = before.sample(t0);
        let mut fwd = before;
        fwd.step(t0, dt);
        let mut back = before;
        back.step(t0, -dt);
        let fd = (fwd.sample(t0 + dt).omega_d - back.sample(t0 - dt).omega_d) / (2.0 * dt);
        assert!(
            (fd - a.omega_d_dot).length() < 1e-7 * a.omega_d_dot.length(),
            "{fd} vs {}",
            a.omega_d_dot
        );
    }
}
