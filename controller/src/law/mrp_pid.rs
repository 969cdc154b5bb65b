//! Basilisk's MRP feedback law (`mrpFeedback`, AVSLab/basilisk
//! `src/fswAlgorithms/attControl/mrpFeedback/mrpFeedback.c`, control law type 0; H. Schaub
//! and J. Junkins, *Analytical Mechanics of Space Systems*, 4th ed., section 8.4):
//! proportional on the attitude error's modified Rodrigues parameters, derivative on the
//! rate error, an integral term and gyroscopic compensation, for the body without its
//! rotors. The rotor torques come from that body torque through the same
//! internal-actuation relation as the paper's law, `u = K(Ω + Ω_r) × Ω − τ`, which
//! cancels the rotors' gyroscopic torque (so Basilisk's wheel momentum `[G_s] h_s` is left
//! out of its `h`: the relation accounts for it).
//!
//! In rotorloop's frames (`R` maps body to inertial components, `R_d` the reference's):
//!
//! ```text
//! [BR]    = Rᵀ R_d                      the body relative to the reference
//! σ       = MRP([BR]), |σ| ≤ 1          (the short way round: the shadow set)
//! ω_r     = [BR] Ω_d,  ω̇_r = [BR] Ω̇_d   the reference's rate and its derivative, body frame
//! δω      = Ω − ω_r
//! ∫σ     += K dt σ                      each tick, before use; each entry clamped to the
//!                                       integral limit
//! z       = ∫σ + I δω                   (z = 0 when Ki = 0)
//! L_r     = K σ + P δω + P Ki z − (ω_r + Ki z) × (I Ω) + I(Ω × ω_r − ω̇_r)
//! τ       = −L_r
//! u       = K(Ω + Ω_r) × Ω − τ
//! ```
//!
//! `K`, `P`, `Ki` (and the optional `integral_limit`) come from `[controller.law_params]`
//! (`k`, `p`, `ki`, `integral_limit`). `I` is the model of the body without the rotors'
//! spin inertia (that is `K_rotor`). The one difference from Basilisk: Basilisk
//! integrates with the time since its previous call and reads a previous call time of 0
//! as none, so a simulation started at t = 0 leaves `∫σ` at zero for its first **two**
//! calls; here every tick, the first included, integrates with the tick's `dt`
//! (docs/scenarios.md). The law's state is `∫σ`.

use glam::{DMat3, DVec3};
use rotorloop_common::params::{BodyParams, ReferenceState, RotorBodyState};
use rotorloop_common::scenario::MAX_MAGNITUDE;

use super::{ControlOutput, Law, LawState, UnknownLaw};

/// The MRP feedback law with its integral state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MrpPid {
    k: f64,
    p: f64,
    ki: f64,
    integral_limit: f64,
    model: BodyParams,
    int_sigma: DVec3,
}

/// The modified Rodrigues parameters of the direction cosine matrix `c` (components of
/// frame 2 from components of frame 1), the short way round (`|σ| ≤ 1`). Sheppard's
/// method through the Euler parameters, so every attitude is handled without a division
/// by a small number.
pub fn mrp(c: DMat3) -> DVec3 {
    // c_ij = row i, column j.
    let m = |i: usize, j: usize| c.col(j)[i];
    let tr = m(0, 0) + m(1, 1) + m(2, 2);
    let b2 = [
        (1.0 + tr) / 4.0,
        (1.0 + 2.0 * m(0, 0) - tr) / 4.0,
        (1.0 + 2.0 * m(1, 1) - tr) / 4.0,
        (1.0 + 2.0 * m(2, 2) - tr) / 4.0,
    ];
    let largest = (0..4).fold(0, |a, i| if b2[i] > b2[a] { i } else { a });
    let s = b2[largest].max(0.0).sqrt();
    let (d12, d23, d31) = (m(0, 1) - m(1, 0), m(1, 2) - m(2, 1), m(2, 0) - m(0, 2));
    let (s12, s23, s31) = (m(0, 1) + m(1, 0), m(1, 2) + m(2, 1), m(2, 0) + m(0, 2));
    let b = match largest {
        0 => [s, d23 / (4.0 * s), d31 / (4.0 * s), d12 / (4.0 * s)],
        1 => [d23 / (4.0 * s), s, s12 / (4.0 * s), s31 / (4.0 * s)],
        2 => [d31 / (4.0 * s), s12 / (4.0 * s), s, s23 / (4.0 * s)],
        _ => [d12 / (4.0 * s), s31 / (4.0 * s), s23 / (4.0 * s), s],
    };
    let sign = if b[0] < 0.0 { -1.0 } else { 1.0 };
    DVec3::new(b[1], b[2], b[3]) * (sign / (1.0 + sign * b[0]))
}

impl MrpPid {
    /// The law of `[controller.law_params]` (`k`, `p`, `ki`, `integral_limit`) for the
    /// body model `model` (its `I` and `K`), with zero integral state.
    pub fn from_params(params: &toml::Table, model: BodyParams) -> Result<Self, UnknownLaw> {
        const LAW: &str = "mrp-pid";
        let takes = "k > 0, p > 0, ki ≥ 0 and integral_limit > 0 (optional), numbers ≤ 1e6 \
                     (as the common gains)";
        for key in params.keys() {
            if !["k", "p", "ki", "integral_limit"].contains(&key.as_str()) {
                return Err(UnknownLaw::Param(LAW, key.clone(), takes));
            }
        }
        let get = |key: &str, default: Option<f64>, ok: fn(f64) -> bool| {
            let v = match params.get(key) {
                Some(toml::Value::Float(x)) => *x,
                Some(toml::Value::Integer(i)) => *i as f64,
                Some(other) => {
                    let mut shown = other.to_string();
                    if shown.len() > 80 {
                        shown = format!("a {} of {} bytes", other.type_str(), shown.len());
                    }
                    return Err(UnknownLaw::Value(LAW, key.to_owned(), shown, takes));
                }
                None => {
                    return default.ok_or_else(|| UnknownLaw::Param(LAW, key.to_owned(), takes));
                }
            };
            match v.is_finite() && v <= MAX_MAGNITUDE && ok(v) {
                true => Ok(v),
                false => Err(UnknownLaw::Value(LAW, key.to_owned(), format!("{v:?}"), takes)),
            }
        };
        Ok(Self {
            k: get("k", None, |x| x > 0.0)?,
            p: get("p", None, |x| x > 0.0)?,
            ki: get("ki", None, |x| x >= 0.0)?,
            integral_limit: get("integral_limit", Some(f64::MAX), |x| x > 0.0)?,
            model,
            int_sigma: DVec3::ZERO,
        })
    }

    /// The integral `∫σ` (K-weighted, as Basilisk keeps it).
    pub fn integral_state(&self) -> DVec3 {
        self.int_sigma
    }
}

impl Law for MrpPid {
    #[inline]
    fn step(&mut self, x: &RotorBodyState, reference: &ReferenceState, dt: f64) -> ControlOutput {
        let i = self.model.inertia;
        let br = x.r.transpose() * reference.r_d;
        let sigma = mrp(br);
        let omega_r = br * reference.omega_d;
        let omega_r_dot = br * reference.omega_d_dot;
        let d_omega = x.omega - omega_r;
        let z = if self.ki > 0.0 {
            let limit = self.integral_limit;
            let next = self.int_sigma + self.k * dt * sigma;
            self.int_sigma = next.clamp(DVec3::splat(-limit), DVec3::splat(limit));
            self.int_sigma + i * d_omega
        } else {
            DVec3::ZERO
        };
        let lr = self.k * sigma + self.p * d_omega + self.p * self.ki * z
            - (omega_r + self.ki * z).cross(i * x.omega)
            + i * (x.omega.cross(omega_r) - omega_r_dot);
        let tau = -lr;
        let u = (self.model.rotor_inertia * (x.omega + x.omega_r)).cross(x.omega) - tau;
        ControlOutput {
            rotor_torque: u,
            body_torque: tau,
            s: sigma,
            eta: -d_omega,
            psi: 0.0,
            xi_i: self.int_sigma,
            saturated: false,
        }
    }

    fn state(&self) -> LawState {
        LawState::of_vector(self.int_sigma)
    }

    fn restore(&mut self, state: &LawState) {
        self.int_sigma = state.vector();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rotorloop_common::so3::hat;

    /// The direction cosine matrix of frame 2 turned by `angle` about `axis` from frame 1
    /// (Schaub's `[C] = I − sin θ [ẽ] + (1 − cos θ) [ẽ]²`).
    fn dcm(axis: DVec3, angle: f64) -> DMat3 {
        let e = hat(axis.normalize());
        DMat3::IDENTITY - angle.sin() * e + (1.0 - angle.cos()) * e * e
    }

    fn law(k: f64, p: f64, ki: f64) -> MrpPid {
        let mut t = toml::Table::new();
        t.insert("k".into(), k.into());
        t.insert("p".into(), p.into());
        t.insert("ki".into(), ki.into());
        let model = BodyParams::new(
            DMat3::from_diagonal(DVec3::new(4.0, 5.0, 6.0)),
            DVec3::new(1.0, 1.0, 1.0),
        );
        MrpPid::from_params(&t, model).expect("params")
    }

    /// `σ = tan(θ/4) e` for a turn of θ about e, and the shadow set beyond half a turn
    /// (`|σ| ≤ 1`), for axes along each Sheppard branch.
    #[test]
    fn the_mrps_of_a_turn_are_tan_quarter_angle_along_its_axis() {
        for axis in [DVec3::X, DVec3::Y, DVec3::Z, DVec3::new(1.0, -2.0, 0.5)] {
            for angle in [1e-6, 0.3, 1.5, 3.0, 3.1] {
                let got = mrp(dcm(axis, angle));
                let want = axis.normalize() * (angle / 4.0).tan();
                assert!((got - want).length() < 1e-12, "{axis} {angle}: {got} vs {want}");
            }
            // 300° one way is 60° the other: the shadow set.
            let got = mrp(dcm(axis, 300f64.to_radians()));
            let want = -axis.normalize() * (60f64.to_radians() / 4.0).tan();
            assert!((got - want).length() < 1e-12, "{got} vs {want}");
            assert!(got.length() <= 1.0);
        }
    }

    /// The signs: a body turned +z from a resting reference gets a −z body torque, a body
    /// spinning +z gets −P·ω (without integral and gyroscopic terms, which vanish here).
    #[test]
    fn its_torques_restore_the_attitude_and_damp_the_rate() {
        let rest =
            ReferenceState { r_d: DMat3::IDENTITY, omega_d: DVec3::ZERO, omega_d_dot: DVec3::ZERO };
        // R = [NB]: the body turned by +0.2 rad about z; [BR] = Rᵀ.
        let turned = RotorBodyState {
            r: dcm(DVec3::Z, 0.2).transpose(),
            omega: DVec3::ZERO,
            omega_r: DVec3::ZERO,
            theta: DVec3::ZERO,
        };
        let out = law(2.0, 3.0, 0.0).step(&turned, &rest, 1e-3);
        let sigma_z = (0.2f64 / 4.0).tan();
        assert!(
            (out.body_torque - DVec3::new(0.0, 0.0, -2.0 * sigma_z)).length() < 1e-12,
            "{}",
            out.body_torque
        );
        let spinning =
            RotorBodyState { r: DMat3::IDENTITY, omega: DVec3::new(0.0, 0.0, 0.5), ..turned };
        let out = law(2.0, 3.0, 0.0).step(&spinning, &rest, 1e-3);
        // (IΩ)×Ω is zero for a spin about a principal axis.
        assert!(
            (out.body_torque - DVec3::new(0.0, 0.0, -1.5)).length() < 1e-12,
            "{}",
            out.body_torque
        );
    }

    /// The integral grows by K·dt·σ per tick and stops at the limit; a restored state
    /// continues it.
    #[test]
    fn the_integral_accumulates_k_dt_sigma_within_its_limit() {
        let rest =
            ReferenceState { r_d: DMat3::IDENTITY, omega_d: DVec3::ZERO, omega_d_dot: DVec3::ZERO };
        let x = RotorBodyState {
            r: dcm(DVec3::X, 0.4).transpose(),
            omega: DVec3::ZERO,
            omega_r: DVec3::ZERO,
            theta: DVec3::ZERO,
        };
        let mut l = law(2.0, 3.0, 0.1);
        for _ in 0..10 {
            l.step(&x, &rest, 0.01);
        }
        let want = 10.0 * 2.0 * 0.01 * (0.4f64 / 4.0).tan();
        assert!((l.integral_state().x - want).abs() < 1e-15);
        let mut limited = l;
        limited.integral_limit = 0.01;
        limited.step(&x, &rest, 0.01);
        assert_eq!(limited.integral_state().x, 0.01);
        let mut again = law(2.0, 3.0, 0.1);
        again.restore(&l.state());
        assert_eq!(again.integral_state(), l.integral_state());
    }

    /// Unknown keys, missing or bad gains are refused naming the key.
    #[test]
    fn bad_parameters_are_refused_naming_the_key() {
        let model = BodyParams::new(DMat3::IDENTITY, DVec3::ONE);
        let mut t = toml::Table::new();
        t.insert("k".into(), 1.0.into());
        t.insert("p".into(), 1.0.into());
        let e = MrpPid::from_params(&t, model).expect_err("no ki");
        assert!(e.to_string().contains("law_params.ki"), "{e}");
        t.insert("ki".into(), (-1.0).into());
        let e = MrpPid::from_params(&t, model).expect_err("ki < 0").to_string();
        assert!(
            e.starts_with("controller.law_params.ki = -1.0 is not allowed: mrp-pid takes"),
            "{e}"
        );
        // Capped as the common gains are (1e308 was accepted).
        t.insert("ki".into(), 1e308.into());
        let e = MrpPid::from_params(&t, model).expect_err("ki > 1e6").to_string();
        assert!(e.starts_with("controller.law_params.ki = 1e308 is not allowed"), "{e}");
        t.insert("ki".into(), "1".into());
        let e = MrpPid::from_params(&t, model).expect_err("a string").to_string();
        assert!(e.starts_with("controller.law_params.ki = \"1\" is not allowed"), "{e}");
        t.insert("ki".into(), 0.0.into());
        t.insert("gain".into(), 1.0.into());
        let e = MrpPid::from_params(&t, model).expect_err("unknown key");
        assert!(e.to_string().contains("law_params.gain"), "{e}");
    }
}
