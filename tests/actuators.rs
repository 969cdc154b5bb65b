//! Actuator limits, a constant disturbance and an inertia mismatch (scenario options, off
//! in the paper's runs): the paper's remark on the integral term, anti-windup under
//! saturation, and the invariants that still hold with an external torque.

use std::time::Duration;

use crate::common::harness::{Harness, assert_same_trace, json, ok};
use crate::common::{M3, V3, to_na};
use glam::DVec3;
use rotorloop::sim::closed_loop::ClosedLoop;
use rotorloop_common::scenario::{Actuation, Scenario};
use rotorloop_monitor::metrics::TraceRow;

fn scenario(name: &str) -> Scenario {
    Scenario::load(name).expect("builtin")
}

/// Every row of a closed-loop run of `s`.
fn rows(s: &Scenario) -> (Vec<TraceRow>, ClosedLoop) {
    let mut lp = ClosedLoop::new(s, Actuation::Internal, None).expect("the default law");
    let rows = (0..=s.ticks()).map(|_| lp.tick()).collect();
    (rows, lp)
}

fn err_between(rows: &[TraceRow], from_s: f64) -> (f64, f64) {
    rows.iter()
        .filter(|r| r.t >= from_s)
        .fold((f64::INFINITY, 0.0), |(lo, hi), r| (lo.min(r.err_deg), hi.max(r.err_deg)))
}

fn mat(rows9: &[f64; 9]) -> M3 {
    M3::from_row_slice(rows9)
}

/// `s = vee(PE − EᵀP)` of a row, from its `R` and `R_d`.
fn s_of(row: &TraceRow, p: &M3) -> V3 {
    let e = mat(&row.r_d) * mat(&row.r).transpose();
    crate::common::vee(&(p * e - e.transpose() * p))
}

/// The paper's remark: with a constant disturbance torque the PID law drives the error to
/// zero, while the same gains with `k_I = 0` settle at the offset where `k_p s` balances
/// the disturbance: `−k_p s = R I⁻¹ τ_d` at rest (from `η̇ = a − R I⁻¹ τ_d`).
#[test]
fn pid_rejects_a_constant_disturbance_that_leaves_pd_with_a_steady_error() {
    let pid = scenario("disturbance-pid");
    let pd = scenario("disturbance-pd");
    assert_eq!(pd.gains.ki, 0.0);
    assert_ne!(pid.disturbance, DVec3::ZERO);
    assert_eq!(pid.disturbance, pd.disturbance);

    let (pid_rows, _) = rows(&pid);
    let (lo, hi) = err_between(&pid_rows, 50.0);
    assert!(hi < 1e-3, "PID: error over the last 10 s {lo}..{hi}°, want < 0.001°");

    let (pd_rows, _) = rows(&pd);
    let (lo, hi) = err_between(&pd_rows, 50.0);
    assert!(lo > 1.0, "PD: the disturbance should leave a steady error, got {lo}°");
    assert!(hi - lo < 1e-3 * hi, "PD: error not steady over the last 10 s: {lo}..{hi}°");
    let last = pd_rows.last().expect("rows");
    let p = to_na(&pd.gains.p);
    let i_inv = to_na(&pd.plant.inertia_inv);
    let tau_d = V3::new(pd.disturbance.x, pd.disturbance.y, pd.disturbance.z);
    let want = -(mat(&last.r) * i_inv * tau_d) / pd.gains.kp;
    let got = s_of(last, &p);
    assert!(
        (got - want).norm() < 1e-4 * want.norm(),
        "PD steady state: s = {got:?}, theory −R I⁻¹ τ_d / k_p = {want:?}"
    );
}

/// With weak, speed-limited rotors a 170° slew saturates for a long stretch. Conditional
/// integration converges; the law without anti-windup winds up and does not.
#[test]
fn saturated_slew_converges_with_anti_windup_and_winds_up_without() {
    let aw = scenario("saturation-antiwindup");
    let u_max = aw.limits.rotor_torque.expect("u_max");
    let w_max = aw.limits.rotor_rate.expect("Ω_max");
    let (aw_rows, aw_loop) = rows(&aw);
    assert!(aw_rows[0].err_deg > 169.9, "starts {}° away", aw_rows[0].err_deg);
    let saturated = aw_loop.saturated_ticks() as f64 / aw.ticks() as f64;
    assert!(saturated > 0.05, "the limits should bind for a while: {saturated}");
    assert!(aw_rows.iter().any(|r| DVec3::from_array(r.u).abs().max_element() > 2.0 * u_max));
    let (_, hi) = err_between(&aw_rows, 100.0);
    assert!(hi < 0.01, "with anti-windup: error over the last 20 s up to {hi}°");
    // The speed limiter holds the rotors at Ω_max, give or take what body motion adds.
    let w_seen = aw_rows.iter().flat_map(|r| r.omega_r).fold(0.0f64, |m, w| m.max(w.abs()));
    assert!(w_seen <= 1.01 * w_max, "|Ω_r| reached {w_seen} with Ω_max = {w_max}");
    assert!(w_seen >= 0.99 * w_max, "the speed limit never bound ({w_seen})");
    // Energy still balances against the work of the torque actually delivered.
    let e_max = aw_rows.iter().map(|r| r.energy_residual.abs()).fold(0.0, f64::max);
    assert!(e_max < 1e-8 * aw_loop.metrics().initial_energy().max(1.0), "energy residual {e_max}");

    let wu = scenario("saturation-windup");
    let (wu_rows, _) = rows(&wu);
    let (lo, _) = err_between(&wu_rows, 100.0);
    assert!(lo > 10.0, "without anti-windup the loop should still be far off, got {lo}°");
}

/// With a disturbance, momentum changes by exactly its impulse and energy by the rotor
/// work plus the disturbance's work: the plant integrates `ḣ = R τ_d` (the metrics check
/// it against trapezoidal integrals, hence the second-order tolerances).
#[test]
fn a_disturbance_changes_momentum_by_its_impulse_and_energy_by_its_work() {
    let s = scenario("disturbance-pid");
    let (rows, lp) = rows(&s);
    let h0 = DVec3::from_array(rows[0].h).length();
    let h_end = DVec3::from_array(rows.last().expect("rows").h);
    assert!((h_end - DVec3::from_array(rows[0].h)).length() > 0.5 * h0, "h should change");
    let drift = rows.iter().map(|r| r.h_drift_rel).fold(0.0, f64::max);
    assert!(drift < 1e-7, "‖h − h(0) − ∫Rτ_d‖/‖h(0)‖ reached {drift}");
    let e = rows.iter().map(|r| r.energy_residual.abs()).fold(0.0, f64::max);
    assert!(e < 1e-6 * lp.metrics().initial_energy(), "energy residual {e} J");
}

/// An inertia mismatch changes only the controller's model: the trajectory differs from
/// the exact-model run, and the PID loop still converges (factors 0.7 and 1.5).
#[test]
fn inertia_mismatch_changes_the_law_not_the_plant_and_pid_still_converges() {
    let exact = scenario("disturbance-pid");
    let (exact_rows, _) = rows(&exact);
    for factor in [0.7, 1.5] {
        let mut file = exact.file.clone();
        file.controller.inertia_factor = factor;
        let s = Scenario::from_file(file).expect("valid");
        assert_eq!(s.plant, exact.plant);
        assert_eq!(s.controller_params(Actuation::Internal).inertia, exact.plant.inertia * factor);
        let (r, _) = rows(&s);
        let at = 5000;
        assert!(
            (r[at].err_deg - exact_rows[at].err_deg).abs() > 0.01,
            "factor {factor}: no effect at t = 5 s"
        );
        let (_, hi) = err_between(&r, 55.0);
        assert!(hi < 0.01, "factor {factor}: error over the last 5 s up to {hi}°");
    }
}

/// The four processes apply the same limits and disturbance as the in-process simulator:
/// lockstep traces are byte-identical and the plant's saturation count equals the
/// simulator's.
#[test]
fn four_processes_apply_the_same_limits_and_disturbance_as_the_simulator() {
    let h = Harness::new("actuators");
    let limit = Duration::from_secs(120);
    for scenario in ["saturation-antiwindup", "disturbance-pid"] {
        let out = h.path(scenario);
        let sim = h.path(&format!("sim-{scenario}"));
        let common = ["--scenario", scenario, "--duration", "4"];
        ok(&h.rotorloop(
            &[
                &["run"][..],
                &common,
                &["--domain", &h.domain, "--out", out.to_str().expect("present")],
            ]
            .concat(),
            limit,
        ));
        ok(&h.rotorloop(
            &[&["sim"][..], &common, &["--no-figures", "--out", sim.to_str().expect("present")]]
                .concat(),
            limit,
        ));
        let read = |d: &std::path::Path| std::fs::read(d.join("trace.csv")).expect("trace");
        assert_same_trace(scenario, &read(&out), &read(&sim));
        let (run, sim) = (json(&out.join("summary.json")), json(&sim.join("summary.json")));
        assert_eq!(run["saturated_ticks"], sim["saturated_ticks"], "{scenario}");
        if scenario.starts_with("saturation") {
            assert!(run["saturated_fraction"].as_f64().expect("fraction") > 0.1);
        }
    }
    h.assert_no_leftovers();
}
