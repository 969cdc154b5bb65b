//! SO(3) and so(3) helpers on glam types: `hat`/`vee`, the exponential map, the inverse
//! of its right-trivialised differential (for Runge–Kutta–Munthe-Kaas), and the error
//! angle of a rotation. All functions are allocation-free and cheap enough for a tick.

use glam::{DMat3, DVec3};

/// `hat(w)`: the skew matrix with `hat(w) x = w × x`.
#[inline]
pub fn hat(w: DVec3) -> DMat3 {
    // glam matrices are column-major: these are the columns of [[0,-z,y],[z,0,-x],[-y,x,0]].
    DMat3::from_cols(
        DVec3::new(0.0, w.z, -w.y),
        DVec3::new(-w.z, 0.0, w.x),
        DVec3::new(w.y, -w.x, 0.0),
    )
}

/// `vee(A)`: the inverse of [`hat`], applied to the skew part of `A` (exact for skew `A`).
#[inline]
pub fn vee(a: DMat3) -> DVec3 {
    // a.col(j)[i] = A_ij
    DVec3::new(
        0.5 * (a.col(1).z - a.col(2).y),
        0.5 * (a.col(2).x - a.col(0).z),
        0.5 * (a.col(0).y - a.col(1).x),
    )
}

/// Element `(i, j)` of `m` (zero-based, row `i`, column `j`).
#[inline]
pub fn entry(m: &DMat3, i: usize, j: usize) -> f64 {
    m.col(j)[i]
}

/// A matrix from its rows.
#[inline]
pub fn from_rows(rows: [[f64; 3]; 3]) -> DMat3 {
    DMat3::from_cols_array_2d(&rows).transpose()
}

/// The rows of a matrix flattened row-major (`m11, m12, m13, m21, …`).
#[inline]
pub fn to_row_major(m: &DMat3) -> [f64; 9] {
    m.transpose().to_cols_array()
}

/// The exponential map `exp(hat(θ))` (Rodrigues' formula, with Taylor series near 0).
#[inline]
pub fn exp(theta: DVec3) -> DMat3 {
    let a2 = theta.length_squared();
    let (s, c) = if a2 < 1e-8 {
        // sin a / a and (1 - cos a) / a², to O(a^6): exact to rounding for a < 1e-4.
        (1.0 - a2 / 6.0 + a2 * a2 / 120.0, 0.5 - a2 / 24.0 + a2 * a2 / 720.0)
    } else {
        let a = a2.sqrt();
        let (sin, cos) = a.sin_cos();
        (sin / a, (1.0 - cos) / a2)
    };
    let k = hat(theta);
    DMat3::IDENTITY + k * s + (k * k) * c
}

/// `dexp⁻¹_θ(v)`: the inverse of the right-trivialised differential of `exp` on so(3),
/// in closed form: `v − ½ θ×v + c(|θ|) θ×(θ×v)` with `c(a) = (1 − (a/2)cot(a/2)) / a²`.
#[inline]
pub fn dexp_inv(theta: DVec3, v: DVec3) -> DVec3 {
    let a2 = theta.length_squared();
    let c = if a2 < 1e-6 {
        1.0 / 12.0 + a2 / 720.0 + a2 * a2 / 30240.0
    } else {
        let a = a2.sqrt();
        let half = 0.5 * a;
        (1.0 - half * half.cos() / half.sin()) / a2
    };
    let tv = theta.cross(v);
    v - 0.5 * tv + c * theta.cross(tv)
}

/// The rotation angle of `E` in radians, `acos((tr E − 1)/2)`, computed as
/// `atan2(|vee(E − Eᵀ)|, (tr E − 1)/2)`, which keeps full relative precision near 0 and π.
#[inline]
pub fn rotation_angle(e: &DMat3) -> f64 {
    let cos = 0.5 * (e.col(0).x + e.col(1).y + e.col(2).z - 1.0);
    let sin = vee(*e).length();
    sin.atan2(cos)
}

/// How far `R` is from SO(3): `(‖RᵀR − I‖_F, |det R − 1|)`.
pub fn orthonormality_error(r: &DMat3) -> (f64, f64) {
    let g = r.transpose() * *r - DMat3::IDENTITY;
    let fro =
        (g.col(0).length_squared() + g.col(1).length_squared() + g.col(2).length_squared()).sqrt();
    (fro, (r.determinant() - 1.0).abs())
}

/// A rotation by `angle` (rad) about the unit `axis`.
pub fn axis_angle(axis: DVec3, angle: f64) -> DMat3 {
    exp(axis.normalize() * angle)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: DMat3, b: DMat3, tol: f64) -> bool {
        (a - b).to_cols_array().iter().all(|d| d.abs() <= tol)
    }

    #[test]
    fn hat_is_the_cross_product_and_vee_inverts_it() {
        let w = DVec3::new(0.3, -1.2, 2.5);
        let x = DVec3::new(-0.7, 0.4, 1.1);
        assert!((hat(w) * x - w.cross(x)).length() < 1e-15);
        assert!((vee(hat(w)) - w).length() < 1e-15);
    }

    #[test]
    fn row_major_helpers_agree_with_entry() {
        let rows = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]];
        let m = from_rows(rows);
        assert_eq!(entry(&m, 0, 1), 2.0);
        assert_eq!(entry(&m, 2, 0), 7.0);
        assert_eq!(to_row_major(&m), [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]);
    }

    #[test]
    fn exp_is_a_rotation_and_matches_the_series_at_small_angles() {
        for theta in [
            DVec3::new(1e-9, -2e-9, 3e-10),
            DVec3::new(1e-5, 2e-5, -1e-5),
            DVec3::new(0.3, -1.0, 2.0),
            DVec3::new(3.1, 0.0, 0.0),
        ] {
            let r = exp(theta);
            let (o, d) = orthonormality_error(&r);
            assert!(o < 1e-14 && d < 1e-14, "{theta}: {o} {d}");
            assert!((rotation_angle(&r) - theta.length()).abs() < 1e-12);
            // exp(θ) θ = θ: the axis is fixed.
            assert!((r * theta - theta).length() < 1e-15);
        }
        // Matches a direct power series where both are accurate.
        let theta = DVec3::new(0.2, -0.1, 0.05);
        let k = hat(theta);
        let mut series = DMat3::IDENTITY;
        let mut term = DMat3::IDENTITY;
        for n in 1..20 {
            term = term * k * (1.0 / n as f64);
            series += term;
        }
        assert!(close(exp(theta), series, 1e-15));
    }

    #[test]
    fn dexp_inv_inverts_the_differential_of_exp() {
        // Right trivialisation: d/dt exp(θ + t v) = hat(w) exp(θ) with v = dexp_inv(θ, w).
        // Left trivialisation (used for R(t) = R0 exp(θ(t)), Ṙ = R hat(ω)):
        // d/dt exp(θ + t v) = exp(θ) hat(ω) with v = dexp_inv(−θ, ω).
        // Checked against central finite differences of `exp`.
        for theta in [DVec3::new(0.4, -0.3, 0.9), DVec3::new(1e-4, 2e-4, 0.0)] {
            let v = DVec3::new(-0.2, 0.5, 0.1);
            let h = 1e-6;
            let d = (exp(theta + v * h) - exp(theta - v * h)) * (0.5 / h);
            let w_right = vee(d * exp(theta).transpose());
            assert!((dexp_inv(theta, w_right) - v).length() < 1e-8, "{theta}");
            let w_left = vee(exp(theta).transpose() * d);
            assert!((dexp_inv(-theta, w_left) - v).length() < 1e-8, "{theta}");
        }
    }

    #[test]
    fn rotation_angle_is_accurate_near_zero_and_pi() {
        let axis = DVec3::new(1.0, 2.0, -0.5).normalize();
        for angle in [1e-12, 1e-6, 0.5, std::f64::consts::PI - 1e-7] {
            let got = rotation_angle(&axis_angle(axis, angle));
            assert!((got - angle).abs() <= 1e-12 * angle.max(1e-3), "{angle}: {got}");
        }
    }
}
