//! Shared by the integration tests: seeded input generators and an independent
//! implementation of the spec's equations in nalgebra (written from
//! `shared/spec/dynamics-and-control.md`, not by calling the library).
#![allow(dead_code)]

pub mod harness;
pub mod old_layout;
pub mod schemas;

use nalgebra::{Matrix3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

pub type M3 = Matrix3<f64>;
pub type V3 = Vector3<f64>;

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

pub fn vec_in(rng: &mut ChaCha8Rng, m: f64) -> V3 {
    V3::new(rng.random_range(-m..m), rng.random_range(-m..m), rng.random_range(-m..m))
}

/// A random rotation (exponential of a random vector of norm < π).
pub fn rotation(rng: &mut ChaCha8Rng) -> M3 {
    let w = vec_in(rng, 1.8);
    *nalgebra::Rotation3::new(w).matrix()
}

pub fn hat(w: &V3) -> M3 {
    M3::new(0.0, -w.z, w.y, w.z, 0.0, -w.x, -w.y, w.x, 0.0)
}

pub fn vee(s: &M3) -> V3 {
    V3::new(s[(2, 1)], s[(0, 2)], s[(1, 0)])
}

pub fn to_na(m: &glam::DMat3) -> M3 {
    M3::from_fn(|i, j| m.col(j)[i])
}

pub fn to_na_v(v: glam::DVec3) -> V3 {
    V3::new(v.x, v.y, v.z)
}

pub fn from_na_v(v: &V3) -> glam::DVec3 {
    glam::DVec3::new(v.x, v.y, v.z)
}

pub fn from_na(m: &M3) -> glam::DMat3 {
    glam::DMat3::from_cols(
        glam::DVec3::new(m[(0, 0)], m[(1, 0)], m[(2, 0)]),
        glam::DVec3::new(m[(0, 1)], m[(1, 1)], m[(2, 1)]),
        glam::DVec3::new(m[(0, 2)], m[(1, 2)], m[(2, 2)]),
    )
}

/// The spec's plant in the plain form: state (R, Ω, Ω_r, Θ), classical RK4 on the
/// 18 numbers, R re-orthonormalised never (so its error shows).
#[derive(Clone, Copy, Debug)]
pub struct DirectPlant {
    pub i: M3,
    pub k: V3, // diagonal of K
    pub r: M3,
    pub w: V3,
    pub wr: V3,
    pub th: V3,
}

impl DirectPlant {
    /// Ṙ = R hat(Ω), Θ̇ = Ω_r, IΩ̇ = Π×Ω − u + τ, Ω̇_r = K⁻¹u − Ω̇ (spec, erratum form).
    fn deriv(&self, r: &M3, w: &V3, wr: &V3, u: &V3, tau: &V3) -> (M3, V3, V3, V3) {
        let kd = M3::from_diagonal(&self.k);
        let pi = (self.i + kd) * w + kd * wr;
        let i_inv = self.i.try_inverse().expect("SPD");
        let w_dot = i_inv * (pi.cross(w) - u + tau);
        let kinv_u = V3::new(u.x / self.k.x, u.y / self.k.y, u.z / self.k.z);
        let wr_dot = if self.k.iter().all(|k| *k > 0.0) { kinv_u - w_dot } else { V3::zeros() };
        (r * hat(w), w_dot, wr_dot, *wr)
    }

    pub fn step(&mut self, u: &V3, tau: &V3, dt: f64) {
        let (r0, w0, wr0, th0) = (self.r, self.w, self.wr, self.th);
        let (a_r, a_w, a_wr, a_th) = self.deriv(&r0, &w0, &wr0, u, tau);
        let (b_r, b_w, b_wr, b_th) = self.deriv(
            &(r0 + a_r * (dt / 2.0)),
            &(w0 + a_w * (dt / 2.0)),
            &(wr0 + a_wr * (dt / 2.0)),
            u,
            tau,
        );
        let (c_r, c_w, c_wr, c_th) = self.deriv(
            &(r0 + b_r * (dt / 2.0)),
            &(w0 + b_w * (dt / 2.0)),
            &(wr0 + b_wr * (dt / 2.0)),
            u,
            tau,
        );
        let (d_r, d_w, d_wr, d_th) =
            self.deriv(&(r0 + c_r * dt), &(w0 + c_w * dt), &(wr0 + c_wr * dt), u, tau);
        self.r = r0 + (a_r + (b_r + c_r) * 2.0 + d_r) * (dt / 6.0);
        self.w = w0 + (a_w + (b_w + c_w) * 2.0 + d_w) * (dt / 6.0);
        self.wr = wr0 + (a_wr + (b_wr + c_wr) * 2.0 + d_wr) * (dt / 6.0);
        self.th = th0 + (a_th + (b_th + c_th) * 2.0 + d_th) * (dt / 6.0);
    }
}

/// The spec's control law, re-derived in nalgebra: returns (u, τ, s).
#[allow(clippy::too_many_arguments)]
pub fn spec_law(
    i: &M3,
    k: &V3,
    p: &M3,
    (kp, kd, ki): (f64, f64, f64),
    r: &M3,
    w: &V3,
    wr: &V3,
    rd: &M3,
    wd: &V3,
    wd_dot: &V3,
    xi: &V3,
) -> (V3, V3, V3) {
    let e = rd * r.transpose();
    let eta = r * (wd - w);
    let s = vee(&(p * e - e.transpose() * p));
    let a = -s * kp - eta * kd - xi * ki;
    let w_star_dot = wd_dot + w.cross(wd) - r.transpose() * a;
    let tau = i * w_star_dot - (i * w).cross(w);
    let kd_m = M3::from_diagonal(k);
    let u = (kd_m * (w + wr)).cross(w) - tau;
    (u, tau, s)
}
