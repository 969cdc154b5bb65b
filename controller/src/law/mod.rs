//! The control laws, behind one interface: [`Law`]. A law is built in one place
//! ([`AnyLaw::for_scenario`]) for the `controller` process and the in-process loop alike,
//! so the lockstep run and the simulator run the same law with the same state.
//!
//! Adding a law touches this folder only: a module here with its struct and its
//! `impl Law`, a row of [`LAWS`] (the name a scenario file's `[controller] law` gives it),
//! and a variant of [`AnyLaw`] with its arms. The scenario file carries the name as text;
//! [`AnyLaw::for_scenario`] resolves it, and the launcher and the simulator call it before
//! anything starts, so an unknown name is refused naming the allowed ones.
//!
//! - [`geometric_pid`]: the paper's geometric PID almost-global tracking law.
//! - [`mrp_pid`]: Basilisk's MRP feedback law (`mrpFeedback`), mapped to the rotors.

pub mod geometric_pid;
pub mod mrp_pid;

use glam::DVec3;
use rotorloop_common::params::{ReferenceState, RotorBodyState};
use rotorloop_common::scenario::{Actuation, Scenario};

use geometric_pid::GeometricPid;
use mrp_pid::MrpPid;

/// Everything the law computes in one tick.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ControlOutput {
    /// Rotor torque `u = K(Ω+Ω_r)×Ω − τ` (N m).
    pub rotor_torque: DVec3,
    /// Body torque `τ = IΩ̇* − (IΩ)×Ω` (N m): what a gas-jet body would apply.
    pub body_torque: DVec3,
    /// `s = vee(PE − EᵀP)`, the gradient of ψ.
    pub s: DVec3,
    /// `η = R(Ω_d − Ω)`, the error velocity.
    pub eta: DVec3,
    /// `ψ(E) = tr(P(I − E))`.
    pub psi: f64,
    /// The integral state used at this tick, `ξ_I,k`.
    pub xi_i: DVec3,
    /// Whether the actuator limits change `u` at this tick (set by [`GeometricPid::step`]).
    pub saturated: bool,
}

/// A law's internal state, as a restarted controller takes it over (bumpless restart):
/// fixed-size, so it fits a resume slot. The geometric PID uses the first three numbers
/// (`ξ_I`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LawState(pub [f64; LawState::LEN]);

impl LawState {
    /// Numbers a law may keep.
    pub const LEN: usize = 8;

    /// The state of a law whose whole state is one vector (the PID's `ξ_I`).
    pub fn of_vector(v: DVec3) -> Self {
        let mut s = [0.0; Self::LEN];
        s[..3].copy_from_slice(&v.to_array());
        Self(s)
    }

    /// The first three numbers as a vector.
    pub fn vector(&self) -> DVec3 {
        DVec3::new(self.0[0], self.0[1], self.0[2])
    }
}

/// A control law: one tick's torques from the state and the reference at that tick.
pub trait Law {
    /// Computes the tick's torques from the state and reference at tick `k`, then
    /// advances the law's internal state over the tick.
    fn step(&mut self, x: &RotorBodyState, reference: &ReferenceState, dt: f64) -> ControlOutput;

    /// The internal state a restarted controller continues from.
    fn state(&self) -> LawState;

    /// Continues from `state` (bumpless restart).
    fn restore(&mut self, state: &LawState);
}

/// Every law a scenario file can name in `[controller] law`, with a line of help. The
/// first is the default (a file that names no law runs it).
pub const LAWS: &[(&str, &str)] = &[
    ("geometric-pid", "the paper's geometric PID almost-global tracking law"),
    ("mrp-pid", "Basilisk's MRP feedback law (mrpFeedback), through the same rotor relation"),
];

/// A scenario names a law that does not exist, or gives it a parameter it does not take.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum UnknownLaw {
    /// `[controller] law` names no law of [`LAWS`].
    Name(String),
    /// `[controller.law_params]` has a key the law does not take: (law, key, what it takes).
    Param(&'static str, String, &'static str),
    /// A key of `[controller.law_params]` holds a value the law does not take: (law, key,
    /// the value as written, what it takes).
    Value(&'static str, String, String, &'static str),
}

impl std::fmt::Display for UnknownLaw {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Name(name) => {
                let allowed: Vec<&str> = LAWS.iter().map(|(n, _)| *n).collect();
                write!(
                    f,
                    "controller.law: no law is named {name:?}; allowed: {} (default {})",
                    allowed.join(", "),
                    LAWS[0].0
                )
            }
            Self::Param(law, key, takes) => {
                write!(f, "controller.law_params.{key}: {law} takes {takes}")
            }
            Self::Value(law, key, value, takes) => {
                write!(
                    f,
                    "controller.law_params.{key} = {value} is not allowed: {law} takes {takes}"
                )
            }
        }
    }
}

impl std::error::Error for UnknownLaw {}

impl From<UnknownLaw> for rotorloop_common::role::UsageError {
    fn from(e: UnknownLaw) -> Self {
        Self(e.to_string())
    }
}

/// Every law, as one type: what the controller and the in-process loop hold. An enum,
/// not a `Box<dyn Law>`: no allocation, and the tick's call is a match.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum AnyLaw {
    /// The paper's law.
    GeometricPid(GeometricPid),
    /// Basilisk's MRP feedback law.
    MrpPid(MrpPid),
}

impl AnyLaw {
    /// The law `scenario` names ([`LAWS`]; none named: the first), with its gains, the
    /// controller's body model for `actuation`, and the actuator limits it knows of;
    /// internal state zero.
    pub fn for_scenario(scenario: &Scenario, actuation: Actuation) -> Result<Self, UnknownLaw> {
        match scenario.law.as_deref().unwrap_or(LAWS[0].0) {
            "geometric-pid" => {
                no_params("geometric-pid", &scenario.law_params)?;
                Ok(Self::GeometricPid(
                    GeometricPid::new(scenario.gains, scenario.controller_params(actuation))
                        .with_limits(scenario.limits_for(actuation), scenario.anti_windup),
                ))
            }
            "mrp-pid" => Ok(Self::MrpPid(MrpPid::from_params(
                &scenario.law_params,
                scenario.controller_params(actuation),
            )?)),
            other => Err(UnknownLaw::Name(other.to_string())),
        }
    }
}

/// A law that takes only the common gains refuses every key of `[controller.law_params]`.
fn no_params(law: &'static str, params: &toml::Table) -> Result<(), UnknownLaw> {
    match params.keys().next() {
        Some(key) => Err(UnknownLaw::Param(law, key.clone(), "no parameters of its own")),
        None => Ok(()),
    }
}

impl Law for AnyLaw {
    #[inline]
    fn step(&mut self, x: &RotorBodyState, reference: &ReferenceState, dt: f64) -> ControlOutput {
        match self {
            Self::GeometricPid(l) => l.step(x, reference, dt),
            Self::MrpPid(l) => l.step(x, reference, dt),
        }
    }

    fn state(&self) -> LawState {
        match self {
            Self::GeometricPid(l) => l.state(),
            Self::MrpPid(l) => l.state(),
        }
    }

    fn restore(&mut self, state: &LawState) {
        match self {
            Self::GeometricPid(l) => l.restore(state),
            Self::MrpPid(l) => l.restore(state),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scenario_names_the_law_and_a_restored_law_continues_bit_for_bit() {
        let s = Scenario::load("paper-sinusoid").expect("built-in");
        assert_eq!(s.law, None, "the default law");
        let a = s.actuation();
        let mut law = AnyLaw::for_scenario(&s, a).expect("the default law");
        let AnyLaw::GeometricPid(pid) = law else { panic!("the default law is the geometric PID") };
        assert_eq!(pid.gains(), &s.gains);
        let (x, dt) = (s.plant_init, s.dt());
        let rd = ReferenceState {
            r_d: s.reference_attitude,
            omega_d: s.reference_omega,
            omega_d_dot: DVec3::ZERO,
        };
        for _ in 0..3 {
            law.step(&x, &rd, dt);
        }
        assert_ne!(law.state(), LawState::default(), "ξ_I moved");
        let mut restarted = AnyLaw::for_scenario(&s, a).expect("the default law");
        restarted.restore(&law.state());
        assert_eq!(restarted.step(&x, &rd, dt), law.step(&x, &rd, dt));
        assert_eq!(restarted.state(), law.state());
    }

    #[test]
    fn every_law_of_the_table_is_built_by_its_name_and_an_unknown_name_is_refused_naming_them() {
        let mut s = Scenario::load("paper-zero").expect("built-in");
        for (name, _) in LAWS {
            s.law = Some(name.to_string());
            s.law_params.clear();
            if *name == "mrp-pid" {
                for key in ["k", "p", "ki"] {
                    s.law_params.insert(key.into(), toml::Value::Float(1.0));
                }
            }
            assert!(AnyLaw::for_scenario(&s, s.actuation()).is_ok(), "{name}");
        }
        s.law = None;
        s.law_params.clear();
        s.law_params.insert("gain".into(), toml::Value::Float(1.0));
        let e = AnyLaw::for_scenario(&s, s.actuation()).expect_err("no such parameter");
        assert!(e.to_string().starts_with("controller.law_params.gain: "), "{e}");
        s.law = Some("bang-bang".into());
        let e = AnyLaw::for_scenario(&s, s.actuation()).expect_err("no such law").to_string();
        assert!(e.contains("controller.law") && e.contains("bang-bang"), "{e}");
        assert!(LAWS.iter().all(|(n, _)| e.contains(n)), "{e}");
    }
}
