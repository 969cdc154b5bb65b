//! `rotorloop gains`: the paper's Appendix A quantities next to the values the paper
//! prints, the linearised closed-loop poles per mode, and a plain verdict.
//!
//! Appendix A (spec, "Gain bounds"): `μ = 2(λ_min(I)+λ_max(I))/λ_min(I)`,
//! `λ = 2λ_max(I)/λ_min(I)²`, `κ ∈ (1/μ, 2/μ)`; sufficient conditions `k_p > 2κk_d²`,
//! `0 < k_I < k_d³(1−σ²)/μ` and
//! `k_p > (λk_I²/2k_d⁴)(1 + sqrt(1 + 4k_d³(k_I² + 4κ²k_d⁶)/(λk_I³)))`.
//! The paper defines σ through `μδ − 2k_I = −σk_I` with `δ = 2κk_I`, i.e.
//! `σ = 2 − 2μκ`. Every bound is evaluated at the κ that makes it weakest, so "not met"
//! means not met for any admissible κ.
//!
//! Linearised about `E = I`, mode `m` of `M = tr(P)I − P` has characteristic polynomial
//! `λ³ + k_dλ² + k_p mλ + k_I m` (Hurwitz iff `k_d k_p > k_I`).

use nalgebra::{Complex, Matrix3};
use rotorloop_common::scenario::Scenario;
use serde::Serialize;

/// What the paper prints for its `I` (section 5).
pub const PAPER_MU: f64 = 2.0048;
/// What the paper prints for its `I` (section 5).
pub const PAPER_LAMBDA: f64 = 1.42;

/// One linearised mode.
#[derive(Debug, Clone, Serialize)]
pub struct Mode {
    /// Eigenvalue `m` of `M = tr(P)I − P`.
    pub m: f64,
    /// Roots of `λ³ + k_dλ² + k_p mλ + k_I m`, as `[re, im]`.
    pub poles: Vec<[f64; 2]>,
    /// All real parts negative.
    pub hurwitz: bool,
}

/// The gain report.
#[derive(Debug, Clone, Serialize)]
pub struct GainReport {
    /// Scenario name.
    pub scenario: String,
    /// `k_p, k_d, k_I`.
    pub kp: f64,
    /// See `kp`.
    pub kd: f64,
    /// See `kp`.
    pub ki: f64,
    /// Principal moments of `I`, ascending.
    pub principal_moments: [f64; 3],
    /// `μ` from the formula.
    pub mu: f64,
    /// `λ` from the formula.
    pub lambda: f64,
    /// What the paper prints for `μ` and `λ`.
    pub paper_mu: f64,
    /// See `paper_mu`.
    pub paper_lambda: f64,
    /// `(1/μ, 2/μ)`.
    pub kappa_interval: [f64; 2],
    /// `inf_κ 2κk_d² = 2k_d²/μ`.
    pub kp_bound_1: f64,
    /// The second `k_p` bound at κ → 1/μ (where it is weakest).
    pub kp_bound_2: f64,
    /// `sup_κ k_d³(1−σ²)/μ` (σ → 0 at κ → 1/μ).
    pub ki_bound: f64,
    /// Whether each sufficient condition holds.
    pub kp_bound_1_met: bool,
    /// See `kp_bound_1_met`.
    pub kp_bound_2_met: bool,
    /// See `kp_bound_1_met`.
    pub ki_bound_met: bool,
    /// Linearised modes.
    pub modes: Vec<Mode>,
    /// One line.
    pub verdict: String,
    /// Remarks on the paper's text.
    pub notes: Vec<String>,
}

/// Roots of `x³ + a x² + b x + c` (eigenvalues of the companion matrix).
pub fn cubic_roots(a: f64, b: f64, c: f64) -> [Complex<f64>; 3] {
    let companion = Matrix3::new(-a, -b, -c, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0);
    let ev = companion.complex_eigenvalues();
    let mut roots = [ev[0], ev[1], ev[2]];
    roots.sort_by(|x, y| x.re.total_cmp(&y.re).then(x.im.total_cmp(&y.im)));
    roots
}

/// The report for a validated scenario.
pub fn analyse(s: &Scenario) -> GainReport {
    let g = s.gains;
    let [lmin, _, lmax] = s.plant_principal_moments;
    let mu = 2.0 * (lmin + lmax) / lmin;
    let lambda = 2.0 * lmax / (lmin * lmin);
    let kappa = 1.0 / mu; // infimum of the admissible interval: every bound is weakest here
    let kp_bound_1 = 2.0 * kappa * g.kd * g.kd;
    let kd3 = g.kd.powi(3);
    let kp_bound_2 = if g.ki > 0.0 {
        lambda * g.ki * g.ki / (2.0 * g.kd.powi(4))
            * (1.0
                + (1.0
                    + 4.0 * kd3 * (g.ki * g.ki + 4.0 * kappa * kappa * g.kd.powi(6))
                        / (lambda * g.ki.powi(3)))
                .sqrt())
    } else {
        f64::INFINITY
    };
    let sigma = 2.0 - 2.0 * mu * kappa;
    let ki_bound = kd3 * (1.0 - sigma * sigma) / mu;

    let pe = s.p_eigenvalues;
    let trace = pe.iter().sum::<f64>();
    let mut modes: Vec<Mode> = pe
        .iter()
        .map(|&p| {
            let m = trace - p;
            let roots = cubic_roots(g.kd, g.kp * m, g.ki * m);
            Mode {
                m,
                poles: roots.iter().map(|z| [z.re, z.im]).collect(),
                hurwitz: roots.iter().all(|z| z.re < 0.0),
            }
        })
        .collect();
    modes.sort_by(|a, b| a.m.total_cmp(&b.m));

    let (b1, b2, bi) = (g.kp > kp_bound_1, g.kp > kp_bound_2, g.ki > 0.0 && g.ki < ki_bound);
    let hurwitz = modes.iter().all(|m| m.hurwitz);
    let sufficient = b1 && b2 && bi;
    let verdict = format!(
        "{}; linearisation {}; {}",
        if sufficient { "sufficient bounds met" } else { "sufficient bound not met" },
        if hurwitz { "Hurwitz" } else { "NOT Hurwitz" },
        match (sufficient, hurwitz) {
            (true, true) => "almost-global convergence guaranteed by the paper's theorem",
            (false, true) => "expect convergence (the bounds are sufficient, not necessary)",
            (_, false) => "expect divergence near E = I",
        }
    );
    let mut notes = vec![format!(
        "paper prints μ = {PAPER_MU}, λ = {PAPER_LAMBDA}; the formulas give μ = {mu:.4}, λ = {lambda:.4}"
    )];
    notes.push(
        "σ = 2 − 2μκ is negative on the whole interval κ ∈ (1/μ, 2/μ) although the paper \
         assumes σ > 0; the k_I bound uses σ² and is evaluated at κ → 1/μ (σ → 0)"
            .to_owned(),
    );
    GainReport {
        scenario: s.file.name.clone(),
        kp: g.kp,
        kd: g.kd,
        ki: g.ki,
        principal_moments: s.plant_principal_moments,
        mu,
        lambda,
        paper_mu: PAPER_MU,
        paper_lambda: PAPER_LAMBDA,
        kappa_interval: [1.0 / mu, 2.0 / mu],
        kp_bound_1,
        kp_bound_2,
        ki_bound,
        kp_bound_1_met: b1,
        kp_bound_2_met: b2,
        ki_bound_met: bi,
        modes,
        verdict,
        notes,
    }
}

/// The report as text.
pub fn render(r: &GainReport) -> String {
    let yes = |b: bool| if b { "met" } else { "NOT met" };
    let GainReport { scenario, kp, kd, ki, mu, lambda, paper_mu, paper_lambda, .. } = r;
    let ([i1, i2, i3], [k0, k1]) = (r.principal_moments, r.kappa_interval);
    let (b1, b2, bi) = (r.kp_bound_1, r.kp_bound_2, r.ki_bound);
    let (met1, met2, meti) = (yes(r.kp_bound_1_met), yes(r.kp_bound_2_met), yes(r.ki_bound_met));
    let mut t = format!(
        "gains of {scenario}: k_p = {kp}, k_d = {kd}, k_I = {ki}\n\
         principal moments of I: {i1:.4}, {i2:.4}, {i3:.4}\n\n\
         {:<24} {:>12} {:>12}\n\
         {:<24} {mu:>12.4} {paper_mu:>12}\n\
         {:<24} {lambda:>12.4} {paper_lambda:>12}\n\
         {:<24} ({k0:.4}, {k1:.4})\n\n\
         sufficient conditions (each at its most permissive κ):\n\
         \x20 k_p > 2κ k_d²          : k_p = {kp} vs > {b1:.4}   {met1}\n\
         \x20 k_p > λk_I²/(2k_d⁴)(…) : k_p = {kp} vs > {b2:.4}   {met2}\n\
         \x20 0 < k_I < k_d³(1−σ²)/μ : k_I = {ki} vs < {bi:.4}   {meti}\n\n\
         linearised closed loop about E = I (λ³ + k_d λ² + k_p m λ + k_I m):\n",
        "quantity", "computed", "paper prints", "μ", "λ", "κ interval",
    );
    for m in &r.modes {
        let poles: Vec<String> =
            m.poles
                .iter()
                .map(|[re, im]| {
                    if im.abs() < 1e-12 { format!("{re:.4}") } else { format!("{re:.4}{im:+.4}i") }
                })
                .collect();
        t.push_str(&format!(
            "  mode m = {:.4}: poles {}  ({})\n",
            m.m,
            poles.join(", "),
            if m.hurwitz { "stable" } else { "UNSTABLE" }
        ));
    }
    t.push_str("\nnotes:\n");
    for n in &r.notes {
        t.push_str(&format!("  - {n}\n"));
    }
    t.push_str(&format!("\nverdict: {}\n", r.verdict));
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_gains_reproduce_the_spec_figures_and_verdict() {
        let s = Scenario::load("paper-zero").expect("builtin");
        let r = analyse(&s);
        assert!((r.mu - 6.849).abs() < 1e-3, "μ = {}", r.mu);
        assert!((r.lambda - 1.419).abs() < 1e-3, "λ = {}", r.lambda);
        assert!(!r.kp_bound_1_met, "k_p = 1 does not meet k_p > 2κk_d² for any κ");
        assert!(r.modes.iter().all(|m| m.hurwitz));
        assert!(r.verdict.contains("not met") && r.verdict.contains("Hurwitz"));
    }

    #[test]
    fn cubic_roots_satisfy_the_polynomial() {
        let (a, b, c) = (3.0, 2.1, 2.1);
        for z in cubic_roots(a, b, c) {
            let p = z * z * z + z * z * a + z * b + c;
            assert!(p.norm() < 1e-12, "{z}: {p}");
        }
    }

    #[test]
    fn hurwitz_iff_kd_kp_exceeds_ki() {
        for (kp, kd, ki, want) in
            [(1.0, 3.0, 1.0, true), (1.0, 1.0, 2.5, false), (2.0, 0.5, 0.9, true)]
        {
            let m = 2.0;
            let stable = cubic_roots(kd, kp * m, ki * m).iter().all(|z| z.re < 0.0);
            assert_eq!(stable, want, "kp={kp} kd={kd} ki={ki}");
        }
    }
}
