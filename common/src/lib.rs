//! Shared by every rotorloop role: SO(3) helpers for the per-tick math, the parameter
//! types of a body with rotors and of the control law, scenario files, the wire samples,
//! the IPC helpers ([`ipc`]), the clock, signals and real-time set-up, and what every role process shares ([`role`]: arguments, start,
//! counting, ending).
//!
//! # Conventions (stated once, used everywhere)
//!
//! - `R ∈ SO(3)` maps body-frame components to inertial-frame components: `v_N = R v_B`.
//! - `Ω` is the body angular velocity in the body frame: `Ṙ = R hat(Ω)`.
//! - Rotor `i` spins about body axis `e_i`; `Ω_r` are rotor rates relative to the body.
//! - Matrices in files and traces are written row-major (`R11, R12, R13, R21, …`).
//!
//! # nalgebra and glam
//!
//! glam (`DMat3`, `DVec3`, f64) carries every number that changes per tick: it is small,
//! `Copy`, and has no generic machinery in the hot path. nalgebra does the set-up work
//! that glam cannot: eigenvalues, symmetry and positive-definiteness checks of the
//! scenario's matrices, and the roots of the closed-loop characteristic polynomials.
//! The conversion happens once, when a scenario is validated ([`scenario`]); nothing
//! inside a tick converts between them.

pub mod clock;
pub mod controller_json;
pub mod flight;
pub mod graph;
pub mod hgrm;
pub mod input;
pub mod ipc;
pub mod outdir;
pub mod output;
pub mod params;
pub mod prefetch;
pub mod private;
pub mod relay;
pub mod resume;
pub mod role;
pub mod rt;
pub mod scenario;
pub mod signals;
pub mod so3;
pub mod summary_json;
pub mod wire;
