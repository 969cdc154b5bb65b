//! Parameter and state types of a body with rotors and of the control law, in the glam
//! types the per-tick math uses. Built once from a validated [`crate::scenario::Scenario`].

use glam::{DMat3, DVec3};

/// Inertia parameters of a rigid body with three rotors on its principal body axes
/// (spec "Conventions"). A body without rotors (the gas-jet comparison body) has
/// `rotor_inertia = 0`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BodyParams {
    /// `I`: inertia of everything but the rotors' spin about their own axes (kg m²).
    pub inertia: DMat3,
    /// `I⁻¹`, precomputed.
    pub inertia_inv: DMat3,
    /// Diagonal of `K`: the rotors' spin inertia about their axes (kg m²).
    pub rotor_inertia: DVec3,
}

impl BodyParams {
    /// Parameters from `I` and the diagonal of `K`. `I` must be invertible (the scenario
    /// loader checks it is symmetric positive definite).
    pub fn new(inertia: DMat3, rotor_inertia: DVec3) -> Self {
        Self { inertia, inertia_inv: inertia.inverse(), rotor_inertia }
    }

    /// The same body with its rotors locked out of the model (`K = 0`): the externally
    /// actuated (gas-jet) body of the spec.
    pub fn without_rotors(&self) -> Self {
        Self { rotor_inertia: DVec3::ZERO, ..*self }
    }

    /// Body angular momentum `Π = (I+K) Ω + K Ω_r` (spec, "The plant").
    #[inline]
    pub fn body_momentum(&self, omega: DVec3, omega_r: DVec3) -> DVec3 {
        self.inertia * omega + self.rotor_inertia * (omega + omega_r)
    }

    /// Kinetic energy `T = ½ Ω·IΩ + ½ (Ω+Ω_r)·K(Ω+Ω_r)` (spec, "Conventions").
    #[inline]
    pub fn kinetic_energy(&self, omega: DVec3, omega_r: DVec3) -> f64 {
        let w = omega + omega_r;
        0.5 * omega.dot(self.inertia * omega) + 0.5 * w.dot(self.rotor_inertia * w)
    }
}

/// Gains of the geometric PID law (spec, "The control law").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gains {
    /// Proportional gain `k_p` (> 0).
    pub kp: f64,
    /// Derivative gain `k_d` (> 0).
    pub kd: f64,
    /// Integral gain `k_I` (≥ 0; 0 is the PD law).
    pub ki: f64,
    /// `P`: symmetric positive definite weight of the navigation function `ψ`.
    pub p: DMat3,
}

/// The kinematic state of a body with rotors at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RotorBodyState {
    /// Attitude `R` (body → inertial).
    pub r: DMat3,
    /// Body angular velocity `Ω` (rad/s, body frame).
    pub omega: DVec3,
    /// Rotor rates relative to the body `Ω_r = Θ̇` (rad/s).
    pub omega_r: DVec3,
    /// Rotor angles relative to the body `Θ` (rad).
    pub theta: DVec3,
}

impl RotorBodyState {
    /// Spatial angular momentum `h = R Π` (inertial frame).
    #[inline]
    pub fn spatial_momentum(&self, body: &BodyParams) -> DVec3 {
        self.r * body.body_momentum(self.omega, self.omega_r)
    }
}

/// What the reference generator hands the controller each tick (spec, "The reference
/// generator"): the desired attitude and its body rates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReferenceState {
    /// `R_d`.
    pub r_d: DMat3,
    /// `Ω_d` (rad/s, the reference body's frame).
    pub omega_d: DVec3,
    /// `Ω̇_d` (rad/s²) from the dummy body's own dynamics at the same instant.
    pub omega_d_dot: DVec3,
}

/// What the rotor motors can do (spec extension; off in the paper's scenarios). Applied
/// by the plant to every held torque, and known to the controller for anti-windup.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ActuatorLimits {
    /// `u_max`: each `|u_i|` is clamped to it (N m).
    pub rotor_torque: Option<f64>,
    /// `Ω_max`: a rotor at or beyond it gets no torque that would spin it further (rad/s).
    pub rotor_rate: Option<f64>,
}

impl ActuatorLimits {
    /// Whether any limit is set.
    pub fn any(&self) -> bool {
        self.rotor_torque.is_some() || self.rotor_rate.is_some()
    }

    /// The rotor torque the motors actually deliver for command `u` with the rotors at
    /// relative rates `omega_r`, and whether that differs from the command.
    ///
    /// Torque saturation clamps each `u_i` to `±u_max`. The speed limit cuts `u_i` to zero
    /// when `|Ω_r,i| ≥ Ω_max` and `u_i` has the sign of `Ω_r,i` (it would spin the rotor
    /// further). Body motion still moves `Ω_r` a little (`Ω̇_r = K⁻¹u − Ω̇`), so a rotor
    /// can pass `Ω_max` slightly; the limiter then only lets torque through that slows it.
    #[inline]
    pub fn apply(&self, u: DVec3, omega_r: DVec3) -> (DVec3, bool) {
        let mut v = match self.rotor_torque {
            Some(m) => u.clamp(DVec3::splat(-m), DVec3::splat(m)),
            None => u,
        };
        if let Some(w) = self.rotor_rate {
            for i in 0..3 {
                if omega_r[i].abs() >= w && v[i] * omega_r[i] > 0.0 {
                    v[i] = 0.0;
                }
            }
        }
        (v, v != u)
    }
}

/// What the controller does with its integral state while the actuators saturate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AntiWindup {
    /// Conditional integration: on a tick whose command the actuator limits change,
    /// `ξ_I` is advanced only if that shrinks it (`s·ξ_I < 0`); otherwise it is held.
    #[default]
    Conditional,
    /// Always integrate (the paper's law as written): the integral winds up.
    None,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn torque_saturation_clamps_each_axis_to_u_max() {
        let l = ActuatorLimits { rotor_torque: Some(2.0), rotor_rate: None };
        let (u, sat) = l.apply(DVec3::new(3.0, -5.0, 1.5), DVec3::ZERO);
        assert_eq!((u, sat), (DVec3::new(2.0, -2.0, 1.5), true));
        let (u, sat) = l.apply(DVec3::new(0.5, -2.0, 1.5), DVec3::ZERO);
        assert_eq!((u, sat), (DVec3::new(0.5, -2.0, 1.5), false));
    }

    #[test]
    fn the_speed_limit_cuts_only_torque_that_spins_a_rotor_further() {
        let l = ActuatorLimits { rotor_torque: None, rotor_rate: Some(10.0) };
        let omega_r = DVec3::new(10.0, -10.5, 9.9);
        // Axis 1 at the limit, speeding up: cut. Axis 2 beyond it, slowing down: kept.
        // Axis 3 below it: kept.
        let (u, sat) = l.apply(DVec3::new(1.0, 1.0, 1.0), omega_r);
        assert_eq!((u, sat), (DVec3::new(0.0, 1.0, 1.0), true));
        let (u, sat) = l.apply(DVec3::new(-1.0, -1.0, 1.0), omega_r);
        assert_eq!((u, sat), (DVec3::new(-1.0, 0.0, 1.0), true));
        assert!(!ActuatorLimits::default().any());
        assert_eq!(ActuatorLimits::default().apply(DVec3::ONE, omega_r), (DVec3::ONE, false));
    }
}
