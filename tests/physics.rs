//! Physical invariants of the plant (spec, "The plant"): they must hold for every torque
//! history, so the tests drive the plant with seeded random piecewise-constant torques.

use crate::common::*;
use glam::DVec3;
use rotorloop_common::params::ReferenceState;
use rotorloop_common::scenario::Scenario;
use rotorloop_common::so3::orthonormality_error;
use rotorloop_monitor::metrics::Metrics;
use rotorloop_plant::{Body, BodyInput};

fn paper() -> Scenario {
    Scenario::load("paper-zero").expect("builtin scenario")
}

/// Drives the paper's plant for `ticks` ticks at `dt` with a random torque held per
/// tick, feeding the monitor's metrics; returns (max drift, max |energy residual|,
/// max orthonormality error, max det error, initial energy).
fn drive_random(seed: u64, ticks: u64, dt: f64, u_max: f64) -> (f64, f64, f64, f64, f64) {
    let s = paper();
    let mut rng = rng(seed);
    let mut body = Body::new(s.plant, s.plant_init);
    let mut metrics = Metrics::new(s.plant, &body.state());
    let dummy = ReferenceState {
        r_d: glam::DMat3::IDENTITY,
        omega_d: DVec3::ZERO,
        omega_d_dot: DVec3::ZERO,
    };
    let (mut drift, mut energy, mut ortho, mut det) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let mut held = DVec3::ZERO;
    for k in 0..=ticks {
        let u = from_na_v(&vec_in(&mut rng, u_max));
        let x = body.state();
        let row = metrics.observe(k, k as f64 * dt, &x, &dummy, u, DVec3::ZERO, held);
        held = u;
        drift = drift.max(row.h_drift_rel);
        energy = energy.max(row.energy_residual.abs());
        let (o, d) = orthonormality_error(&x.r);
        ortho = ortho.max(o);
        det = det.max(d);
        body.step(BodyInput { rotor_torque: u, body_torque: DVec3::ZERO }, dt);
    }
    (drift, energy, ortho, det, metrics.initial_energy())
}

/// Spatial momentum `h = RΠ`, computed from the reported `(R, Ω, Ω_r)` by the spec's
/// formula, stays constant under an arbitrary rotor-torque history: relative drift
/// below 1e-10 over 60 s at 1 kHz.
#[test]
fn spatial_momentum_is_conserved_under_arbitrary_torque_history() {
    let (drift, ..) = drive_random(11, 60_000, 1e-3, 5.0);
    assert!(drift < 1e-10, "relative momentum drift {drift:e}");
}

/// `Ṫ = u·Ω_r`: the kinetic energy changes only by rotor work, up to integrator
/// truncation. Shown two ways: the residual is tiny relative to the energy, and it
/// shrinks about 16× when dt halves (fourth order), so it is truncation, not a
/// modelling error.
#[test]
fn rotor_work_equals_energy_change() {
    let (_, e1, _, _, t0) = drive_random(12, 10_000, 1e-3, 2.0);
    assert!(e1 < 1e-8 * t0.max(1.0), "energy residual {e1:e} J vs T(0) = {t0}");
    // Same torque function of time at two step sizes: use a smooth torque.
    let residual_at = |n: u64| {
        let s = paper();
        let dt = 2.0 / n as f64;
        let mut body = Body::new(s.plant, s.plant_init);
        let mut m = Metrics::new(s.plant, &body.state());
        let dummy = ReferenceState {
            r_d: glam::DMat3::IDENTITY,
            omega_d: DVec3::ZERO,
            omega_d_dot: DVec3::ZERO,
        };
        let mut last = 0.0;
        for k in 0..=n {
            let u = DVec3::new(3.0, -2.0, 1.0); // held: work is exact, only truncation remains
            let row = m.observe(k, k as f64 * dt, &body.state(), &dummy, u, DVec3::ZERO, u);
            last = row.energy_residual;
            body.step(BodyInput { rotor_torque: u, body_torque: DVec3::ZERO }, dt);
        }
        last.abs()
    };
    let (a, b) = (residual_at(50), residual_at(100));
    assert!(
        a / b > 10.0,
        "residual {a:e} at dt=0.04, {b:e} at dt=0.02: not converging at high order"
    );
}

/// `R` stays in SO(3): `‖RᵀR − I‖` and `|det R − 1|` stay at rounding level over 60 s.
#[test]
fn attitude_stays_orthonormal_with_unit_determinant() {
    let (_, _, ortho, det, _) = drive_random(13, 60_000, 1e-3, 5.0);
    assert!(ortho < 1e-12, "‖RᵀR − I‖ = {ortho:e}");
    assert!(det < 1e-12, "|det R − 1| = {det:e}");
}

/// The plant's Lie-group integrator agrees with a plain RK4 integration of the spec's
/// equations (erratum form `Ω̇_r = K⁻¹u − Ω̇`), written independently in the test.
#[test]
fn plant_matches_direct_integration_of_the_spec_equations() {
    let s = paper();
    let mut rng = rng(14);
    let mut body = Body::new(s.plant, s.plant_init);
    let mut direct = DirectPlant {
        i: to_na(&s.plant.inertia),
        k: to_na_v(s.plant.rotor_inertia),
        r: to_na(&s.plant_init.r),
        w: to_na_v(s.plant_init.omega),
        wr: to_na_v(s.plant_init.omega_r),
        th: V3::zeros(),
    };
    let dt = 1e-3;
    for _ in 0..200 {
        // a torque held for 10 ticks (zero-order hold over 10 ms)
        let u = vec_in(&mut rng, 3.0);
        for _ in 0..10 {
            // the direct integrator takes 4 substeps per tick: its own error is negligible
            for _ in 0..4 {
                direct.step(&u, &V3::zeros(), dt / 4.0);
            }
            body.step(BodyInput { rotor_torque: from_na_v(&u), body_torque: DVec3::ZERO }, dt);
        }
    }
    let x = body.state();
    let err_r = (to_na(&x.r) - direct.r).amax();
    let err_w = (to_na_v(x.omega) - direct.w).amax();
    let err_wr = (to_na_v(x.omega_r) - direct.wr).amax();
    let err_th = (to_na_v(x.theta) - direct.th).amax();
    assert!(
        err_r < 1e-8 && err_w < 1e-8 && err_wr < 1e-8 && err_th < 1e-8,
        "after 2 s: |ΔR| {err_r:e}, |ΔΩ| {err_w:e}, |ΔΩ_r| {err_wr:e}, |ΔΘ| {err_th:e}"
    );
}

/// The gas-jet body follows `IΩ̇ = (IΩ)×Ω + τ` (spec, externally actuated body).
#[test]
fn gas_jet_body_matches_direct_integration_of_euler_equations() {
    let s = paper();
    let mut rng = rng(15);
    let params = s.plant.without_rotors();
    let mut body = Body::new(params, s.plant_init);
    let mut direct = DirectPlant {
        i: to_na(&s.plant.inertia),
        k: V3::zeros(),
        r: to_na(&s.plant_init.r),
        w: to_na_v(s.plant_init.omega),
        wr: V3::zeros(),
        th: V3::zeros(),
    };
    let dt = 1e-3;
    for _ in 0..200 {
        let tau = vec_in(&mut rng, 3.0);
        for _ in 0..10 {
            for _ in 0..4 {
                direct.step(&V3::zeros(), &tau, dt / 4.0);
            }
            body.step(BodyInput { rotor_torque: DVec3::ZERO, body_torque: from_na_v(&tau) }, dt);
        }
    }
    let x = body.state();
    let err = (to_na(&x.r) - direct.r).amax().max((to_na_v(x.omega) - direct.w).amax());
    assert!(err < 1e-8, "gas-jet body differs from Euler's equations by {err:e}");
    assert_eq!(x.omega_r, DVec3::ZERO);
}

/// Drives the paper's plant through the delayed zero-order hold: each tick's random torque
/// takes effect `delay` after its tick (a queue when longer than a tick), integrated
/// piecewise; returns (max drift, max |energy residual|, max orthonormality error).
fn drive_delayed(seed: u64, ticks: u64, dt: f64, delay: f64) -> (f64, f64, f64) {
    use rotorloop_plant::actuator::{ActuationDelay, DelayLine, integrate_tick};
    let s = paper();
    let mut rng = rng(seed);
    let mut body = Body::new(s.plant, s.plant_init);
    let mut metrics = Metrics::new(s.plant, &body.state());
    let mut line = DelayLine::new(ActuationDelay::Fixed(delay), dt);
    let dummy = ReferenceState {
        r_d: glam::DMat3::IDENTITY,
        omega_d: DVec3::ZERO,
        omega_d_dot: DVec3::ZERO,
    };
    let (mut drift, mut energy, mut ortho, mut work) = (0.0f64, 0.0f64, 0.0f64, 0.0);
    for k in 0..=ticks {
        let u = from_na_v(&vec_in(&mut rng, 5.0));
        let x = body.state();
        let row = metrics.observe_work(k, k as f64 * dt, &x, &dummy, u, DVec3::ZERO, work);
        drift = drift.max(row.h_drift_rel);
        energy = energy.max(row.energy_residual.abs());
        ortho = ortho.max(orthonormality_error(&x.r).0);
        line.arrive(k, BodyInput { rotor_torque: u, body_torque: DVec3::ZERO }, k, 0.0, 0, None);
        work = integrate_tick(&mut body, &mut line, k, &s.limits, DVec3::ZERO).work;
    }
    (drift, energy, ortho)
}

/// The invariants hold unchanged under a delayed zero-order hold (spec, "Actuation delay"):
/// spatial momentum is conserved by any internal torque history, the energy change equals
/// the rotor work summed over the pieces, and `R` stays on SO(3), for delays inside a
/// tick and longer than one (a queue).
#[test]
fn invariants_hold_when_torques_take_effect_inside_the_tick() {
    for delay in [3.7e-4, 2.5e-3, 0.05] {
        let (drift, energy, ortho) = drive_delayed(17, 20_000, 1e-3, delay);
        assert!(drift < 1e-10, "delay {delay}: relative momentum drift {drift:e}");
        assert!(energy < 1e-6, "delay {delay}: |energy − work| {energy:e} J");
        assert!(ortho < 1e-12, "delay {delay}: ‖RᵀR − I‖ {ortho:e}");
    }
}
