//! Scenario files: TOML, every field documented with its unit and default, validated
//! into the glam parameter types the algorithms run on.
//!
//! Validation refuses what would make a run meaningless (a non-SPD inertia, an `R(0)`
//! off SO(3), a negative gain, an unknown key…) with a [`ScenarioError`] naming the
//! field, the value and what is allowed. It warns, and still runs, where the paper
//! itself is unphysical or where the theory's premises are not met. This is the one
//! place where nalgebra meets glam: eigenvalues and SVDs here, glam from then on.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3};
use nalgebra::{Matrix3, SymmetricEigen};
use serde::{Deserialize, Serialize};

use crate::params::{ActuatorLimits, AntiWindup, BodyParams, Gains, RotorBodyState};
use crate::so3;

mod shape;

/// Scenarios that ship with rotorloop, by name: the paper's three reference torques, and
/// the extensions' demonstrations (a constant disturbance with PID and with PD;
/// saturated rotors with and without anti-windup).
pub const BUILTIN: [(&str, &str); 8] = [
    ("paper-zero", include_str!("../../scenarios/paper-zero.toml")),
    ("paper-constant", include_str!("../../scenarios/paper-constant.toml")),
    ("paper-sinusoid", include_str!("../../scenarios/paper-sinusoid.toml")),
    ("disturbance-pid", include_str!("../../scenarios/disturbance-pid.toml")),
    ("disturbance-pd", include_str!("../../scenarios/disturbance-pd.toml")),
    ("saturation-antiwindup", include_str!("../../scenarios/saturation-antiwindup.toml")),
    ("saturation-windup", include_str!("../../scenarios/saturation-windup.toml")),
    ("mrp-regulation", include_str!("../../scenarios/mrp-regulation.toml")),
];

/// Allowed tick rates (Hz).
pub const RATE_RANGE_HZ: (f64, f64) = (1.0, 100_000.0);
/// Allowed run durations (s).
pub const DURATION_RANGE_S: (f64, f64) = (1e-3, 86_400.0);
/// Tolerance on `‖RᵀR − I‖` and `|det R − 1|` for initial attitudes.
pub const ORTHONORMAL_TOL: f64 = 1e-6;
/// Allowed `controller.inertia_factor`.
pub const INERTIA_FACTOR_RANGE: (f64, f64) = (0.1, 10.0);
/// Largest magnitude accepted for any vector entry (rates, torques, momenta).
pub const MAX_MAGNITUDE: f64 = 1e6;
/// Largest scenario file read (bytes); the built-in ones are about 2 KiB.
pub const MAX_FILE_BYTES: u64 = 1 << 20;
/// Most characters of a value echoed in an error, and of the parser's message (which
/// lists the keys allowed): a 4 MB line is named by its line and column, not printed.
const MAX_ECHO: usize = 160;
const MAX_MESSAGE: usize = 600;

/// What went wrong with a scenario. Every message names the field and what is allowed.
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    /// The file could not be read (not a regular file, too large, not UTF-8, an I/O error).
    #[error("cannot read scenario file {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: crate::input::InputError,
    },
    /// The TOML did not parse or did not match the schema (includes unknown keys).
    #[error("scenario {origin}: {message}")]
    Parse {
        /// The file or built-in name.
        origin: String,
        /// The parser's message (line, column, what was expected).
        message: String,
    },
    /// Neither a built-in name nor an existing file.
    #[error(
        "unknown scenario `{name}`: not a built-in scenario (allowed: {allowed}) and no such file"
    )]
    Unknown {
        /// The name given.
        name: String,
        /// The built-in names.
        allowed: String,
    },
    /// A value out of its allowed set.
    #[error("{field} = {value} is not allowed: {allowed}")]
    Invalid {
        /// The field, as `section.key`.
        field: String,
        /// The value given.
        value: String,
        /// What is allowed.
        allowed: String,
    },
}

impl ScenarioError {
    fn invalid(field: &str, value: impl std::fmt::Debug, allowed: impl Into<String>) -> Self {
        Self::Invalid {
            field: field.to_owned(),
            value: capped(&format!("{value:?}")),
            allowed: allowed.into(),
        }
    }
}

/// `s`, or its first [`MAX_ECHO`] characters and how long it is.
fn capped(s: &str) -> String {
    capped_at(s, MAX_ECHO)
}

fn capped_at(s: &str, max: usize) -> String {
    match s.char_indices().nth(max) {
        None => s.to_owned(),
        Some((end, _)) => format!("{}… ({} bytes in all)", &s[..end], s.len()),
    }
}

/// A TOML error as a line, a column and the parser's message, with an excerpt of the line
/// around the column: never the whole line (toml's own rendering echoes it whole, with a
/// caret line as long).
fn parse_error(origin: &str, text: &str, e: &toml::de::Error) -> ScenarioError {
    let message = capped_at(e.message().trim_end(), MAX_MESSAGE);
    let Some(span) = e.span() else {
        return ScenarioError::Parse { origin: origin.to_owned(), message };
    };
    let mut at = span.start.min(text.len());
    while !text.is_char_boundary(at) {
        at -= 1;
    }
    let line_start = text[..at].rfind('\n').map_or(0, |i| i + 1);
    let line_end = text[at..].find('\n').map_or(text.len(), |i| at + i);
    let line = text[..at].matches('\n').count() + 1;
    let column = text[line_start..at].chars().count() + 1;
    // At most 40 characters either side of the column.
    let before: Vec<(usize, char)> = text[line_start..at].char_indices().collect();
    let from = before.len().checked_sub(40).map_or(line_start, |i| line_start + before[i].0);
    let to = text[at..line_end].char_indices().nth(40).map_or(line_end, |(i, _)| at + i);
    let (lead, tail) =
        (if from > line_start { "…" } else { "" }, if to < line_end { "…" } else { "" });
    let excerpt = format!("{lead}{}{tail}", &text[from..to]);
    let caret = " ".repeat(lead.chars().count() + text[from..at].chars().count());
    ScenarioError::Parse {
        origin: origin.to_owned(),
        message: format!("line {line}, column {column}: {message}\n  | {excerpt}\n  | {caret}^"),
    }
}

/// How torque reaches the body.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Actuation {
    /// Three internal rotors: the controller commands rotor torques `u`.
    #[default]
    Internal,
    /// Gas jets: the controller's body torque `τ` acts directly; no rotors.
    External,
}

impl std::fmt::Display for Actuation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Internal => "internal",
            Self::External => "external",
        })
    }
}

impl std::str::FromStr for Actuation {
    type Err = ScenarioError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "internal" => Ok(Self::Internal),
            "external" => Ok(Self::External),
            other => Err(ScenarioError::invalid("actuation", other, "`internal` or `external`")),
        }
    }
}

/// The reference body's rotor-torque profile `u_d(t)` (N m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TorqueProfile {
    /// `u_d = 0`.
    Zero,
    /// `u_d = value`.
    Constant(DVec3),
    /// `u_d,i = amplitude_i sin(frequency_i t + phase_i)` (frequency in rad/s).
    Sinusoid {
        /// `a_i` (N m).
        amplitude: DVec3,
        /// `ω_i` (rad/s).
        frequency: DVec3,
        /// `φ_i` (rad).
        phase: DVec3,
    },
}

impl TorqueProfile {
    /// `u_d(t)`.
    #[inline]
    pub fn at(&self, t: f64) -> DVec3 {
        match *self {
            Self::Zero => DVec3::ZERO,
            Self::Constant(u) => u,
            Self::Sinusoid { amplitude, frequency, phase } => DVec3::new(
                amplitude.x * (frequency.x * t + phase.x).sin(),
                amplitude.y * (frequency.y * t + phase.y).sin(),
                amplitude.z * (frequency.z * t + phase.z).sin(),
            ),
        }
    }
}

type Row3 = [f64; 3];
type Mat3Rows = [Row3; 3];

const IDENTITY_ROWS: Mat3Rows = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// A scenario file as written (TOML). Units: kg m², rad, rad/s, N m, s, Hz.
/// Unknown keys are refused, so a misspelt key never falls back to a default.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScenarioFile {
    /// Short name, used in reports. Default: the file name without extension.
    #[serde(default)]
    pub name: String,
    /// Free text.
    #[serde(default)]
    pub description: String,
    /// The controlled body.
    pub plant: BodyFile,
    /// The dummy body that generates `R_d, Ω_d, Ω̇_d`.
    pub reference: ReferenceFile,
    /// The control law.
    pub controller: ControllerFile,
    /// Tick rate, duration, actuation.
    #[serde(default)]
    pub run: RunFile,
}

/// A body with rotors and its initial state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BodyFile {
    /// `I` (kg m², rows): symmetric positive definite.
    pub inertia: Mat3Rows,
    /// Diagonal of `K` (kg m²): each > 0.
    pub rotor_inertia: Row3,
    /// `R(0)` (rows): orthonormal with det +1 to 1e-6 (then projected onto SO(3)).
    #[serde(default = "identity_rows")]
    pub attitude: Mat3Rows,
    /// `Ω(0)` (rad/s, body frame). Give exactly one of `omega` and `i_omega`; neither means 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub omega: Option<Row3>,
    /// `I Ω(0)` (N m s): the paper states initial rates this way.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub i_omega: Option<Row3>,
    /// `Ω_r(0)` (rad/s, relative to the body). Plant only; the reference's are set by
    /// momentum matching. Default 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotor_rates: Option<Row3>,
    /// `Θ(0)` (rad). Default 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotor_angles: Option<Row3>,
    /// Rotor torque limit `u_max` (N m, > 0): each `|u_i|` is clamped to it. Default:
    /// unlimited. Plant only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotor_torque_limit: Option<f64>,
    /// Rotor speed limit `Ω_max` (rad/s, > 0): torque that would spin a rotor beyond it is
    /// cut. Default: unlimited. Plant only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotor_rate_limit: Option<f64>,
    /// A constant external disturbance torque on the body (N m, body frame). Default 0.
    /// Plant only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub disturbance_torque: Option<Row3>,
}

/// The reference body: a [`BodyFile`] plus its torque profile.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReferenceFile {
    /// `I_d` (kg m², rows).
    pub inertia: Mat3Rows,
    /// Diagonal of `K_d` (kg m²).
    pub rotor_inertia: Row3,
    /// `R_d(0)` (rows). Default identity.
    #[serde(default = "identity_rows")]
    pub attitude: Mat3Rows,
    /// `Ω_d(0)` (rad/s). Exactly one of `omega`, `i_omega`; neither means 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub omega: Option<Row3>,
    /// `I_d Ω_d(0)` (N m s).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub i_omega: Option<Row3>,
    /// `u_d(t)`.
    pub torque: TorqueFile,
}

/// `profile = "zero" | "constant" | "sinusoid"` and that profile's fields.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TorqueFile {
    /// `zero`, `constant` or `sinusoid`.
    pub profile: String,
    /// `constant`: the torque (N m).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub value: Option<Row3>,
    /// `sinusoid`: amplitude per axis (N m).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub amplitude: Option<Row3>,
    /// `sinusoid`: angular frequency per axis (rad/s).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frequency: Option<Row3>,
    /// `sinusoid`: phase per axis (rad). Default 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase: Option<Row3>,
}

/// Gains and the navigation-function weight.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControllerFile {
    /// The law, by the name the controller crate gives it (`rotorloop_controller::law::LAWS`);
    /// left out: the controller's default law, the paper's. The controller checks the name
    /// before anything starts.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub law: Option<String>,
    /// The law's own parameters (`[controller.law_params]`), beyond the common gains
    /// below: read and checked by the law itself, so a new law needs nothing here.
    #[serde(default, skip_serializing_if = "toml::Table::is_empty")]
    pub law_params: toml::Table,
    /// `k_p` (> 0).
    pub kp: f64,
    /// `k_d` (> 0).
    pub kd: f64,
    /// `k_I` (≥ 0).
    pub ki: f64,
    /// `P` (rows): symmetric positive definite. Default `diag(0.9, 1.0, 1.1)`.
    #[serde(default = "default_p")]
    pub p: Mat3Rows,
    /// The controller's model of the body inertia is this factor times the plant's `I`
    /// (an inertia mismatch; `K` is known exactly). 0.1 to 10, default 1.
    #[serde(default = "default_inertia_factor")]
    pub inertia_factor: f64,
    /// `conditional` (default) or `none`: what `ξ_I` does while the actuators saturate.
    #[serde(default)]
    pub anti_windup: AntiWindup,
}

/// How the run is driven.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunFile {
    /// Simulated duration (s). Default 30.
    #[serde(default = "default_duration")]
    pub duration_s: f64,
    /// Tick rate (Hz). Default 1000.
    #[serde(default = "default_rate")]
    pub rate_hz: f64,
    /// `internal` (rotors) or `external` (gas jets). Default internal.
    #[serde(default)]
    pub actuation: Actuation,
}

impl Default for RunFile {
    fn default() -> Self {
        Self {
            duration_s: default_duration(),
            rate_hz: default_rate(),
            actuation: Actuation::Internal,
        }
    }
}

fn identity_rows() -> Mat3Rows {
    IDENTITY_ROWS
}
fn default_p() -> Mat3Rows {
    [[0.9, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.1]]
}
fn default_inertia_factor() -> f64 {
    1.0
}
fn default_duration() -> f64 {
    30.0
}
fn default_rate() -> f64 {
    1000.0
}

/// A validated scenario: everything the algorithms need, in glam types.
#[derive(Debug, Clone, PartialEq)]
pub struct Scenario {
    /// The file as run (after command-line overrides), for reports.
    pub file: ScenarioFile,
    /// Plant inertia parameters.
    pub plant: BodyParams,
    /// Plant initial state.
    pub plant_init: RotorBodyState,
    /// Reference body inertia parameters.
    pub reference: BodyParams,
    /// `R_d(0)`.
    pub reference_attitude: DMat3,
    /// `Ω_d(0)`.
    pub reference_omega: DVec3,
    /// `u_d(t)`.
    pub reference_torque: TorqueProfile,
    /// Control gains.
    pub gains: Gains,
    /// The rotor motors' limits (none in the paper's scenarios).
    pub limits: ActuatorLimits,
    /// Constant disturbance torque on the plant's body (N m, body frame).
    pub disturbance: DVec3,
    /// Anti-windup rule of the controller.
    pub anti_windup: AntiWindup,
    /// The control law's name as the file gives it (`None`: the controller's default law).
    /// The controller crate resolves it (`rotorloop_controller::law::AnyLaw::for_scenario`).
    pub law: Option<String>,
    /// The law's own parameters, as the file gives them (the law checks them).
    pub law_params: toml::Table,
    /// Eigenvalues of the plant's `I`, ascending (for the gain bounds).
    pub plant_principal_moments: [f64; 3],
    /// Eigenvalues of `P`, ascending.
    pub p_eigenvalues: [f64; 3],
    /// Things that are odd but allowed; printed before a run and kept in reports.
    pub warnings: Vec<String>,
}

impl Scenario {
    /// Loads a built-in scenario by name, or a TOML file by path.
    pub fn load(name_or_path: &str) -> Result<Self, ScenarioError> {
        Self::from_file(ScenarioFile::load(name_or_path)?)
    }

    /// Parses and validates TOML text; `origin` names it in messages.
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, ScenarioError> {
        Self::from_file(ScenarioFile::parse(text, origin)?)
    }

    /// Validates a parsed file.
    pub fn from_file(file: ScenarioFile) -> Result<Self, ScenarioError> {
        let mut warnings = Vec::new();
        let (plant, plant_moments) =
            body_params("plant", &file.plant.inertia, &file.plant.rotor_inertia, &mut warnings)?;
        let (reference, _) = body_params(
            "reference",
            &file.reference.inertia,
            &file.reference.rotor_inertia,
            &mut warnings,
        )?;

        let r0 = rotation("plant.attitude", &file.plant.attitude)?;
        let omega0 = rate_pair("plant", file.plant.omega, file.plant.i_omega, &plant.inertia_inv)?;
        let omega_r0 = finite_vec("plant.rotor_rates", file.plant.rotor_rates.unwrap_or_default())?;
        let theta0 = finite_vec("plant.rotor_angles", file.plant.rotor_angles.unwrap_or_default())?;
        let rd0 = rotation("reference.attitude", &file.reference.attitude)?;
        let omega_d0 = rate_pair(
            "reference",
            file.reference.omega,
            file.reference.i_omega,
            &reference.inertia_inv,
        )?;
        let reference_torque = torque_profile(&file.reference.torque)?;

        let c = &file.controller;
        let (p, p_eig) = controller_gains(c, &mut warnings)?;
        in_range("controller.inertia_factor", c.inertia_factor, INERTIA_FACTOR_RANGE)?;
        let (limits, disturbance) = actuators(&file, omega_r0, &mut warnings)?;

        let run = &file.run;
        in_range("run.rate_hz", run.rate_hz, RATE_RANGE_HZ)?;
        in_range("run.duration_s", run.duration_s, DURATION_RANGE_S)?;

        Ok(Self {
            plant,
            plant_init: RotorBodyState { r: r0, omega: omega0, omega_r: omega_r0, theta: theta0 },
            reference,
            reference_attitude: rd0,
            reference_omega: omega_d0,
            reference_torque,
            gains: Gains { kp: c.kp, kd: c.kd, ki: c.ki, p },
            limits,
            disturbance,
            anti_windup: c.anti_windup,
            law: c.law.clone(),
            law_params: c.law_params.clone(),
            plant_principal_moments: plant_moments,
            p_eigenvalues: p_eig,
            warnings,
            file,
        })
    }

    /// Tick period (s).
    pub fn dt(&self) -> f64 {
        1.0 / self.file.run.rate_hz
    }

    /// Number of plant steps in the run: `round(duration · rate)`, at least 1.
    pub fn ticks(&self) -> u64 {
        ((self.file.run.duration_s * self.file.run.rate_hz).round() as u64).max(1)
    }

    /// The plant's inertia parameters for an actuation: the gas-jet body is the same
    /// body without its rotors.
    pub fn plant_params(&self, actuation: Actuation) -> BodyParams {
        match actuation {
            Actuation::Internal => self.plant,
            Actuation::External => self.plant.without_rotors(),
        }
    }

    /// The controller's model of the plant for an actuation: the plant's parameters with
    /// `I` scaled by `controller.inertia_factor`.
    pub fn controller_params(&self, actuation: Actuation) -> BodyParams {
        let p = self.plant_params(actuation);
        BodyParams::new(p.inertia * self.file.controller.inertia_factor, p.rotor_inertia)
    }

    /// The actuator limits in effect for an actuation (gas jets have no rotors to limit).
    pub fn limits_for(&self, actuation: Actuation) -> ActuatorLimits {
        match actuation {
            Actuation::Internal => self.limits,
            Actuation::External => ActuatorLimits::default(),
        }
    }

    /// The actuation of this run.
    pub fn actuation(&self) -> Actuation {
        self.file.run.actuation
    }

    /// A copy with the run settings replaced, re-validated.
    pub fn with_run(&self, run: RunFile) -> Result<Self, ScenarioError> {
        let mut file = self.file.clone();
        file.run = run;
        Self::from_file(file)
    }
}

impl ScenarioFile {
    /// Reads a built-in scenario by name, or a TOML file by path.
    pub fn load(name_or_path: &str) -> Result<Self, ScenarioError> {
        if let Some((_, text)) = BUILTIN.iter().find(|(n, _)| *n == name_or_path) {
            return Self::parse(text, name_or_path);
        }
        let path = Path::new(name_or_path);
        let text = crate::input::read_text(path, MAX_FILE_BYTES).map_err(|e| match e {
            crate::input::InputError::Missing => ScenarioError::Unknown {
                name: capped(name_or_path),
                allowed: BUILTIN.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", ")
                    + ", or the path of a .toml file",
            },
            source => ScenarioError::Io { path: path.to_owned(), source },
        })?;
        let mut file = Self::parse(&text, &path.display().to_string())?;
        if file.name.is_empty() {
            file.name =
                path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        }
        Ok(file)
    }

    /// Parses TOML text; `origin` names it in messages. Checks the schema only: the
    /// sizes and sections first (`scenario::shape`), then the keys and types.
    pub fn parse(text: &str, origin: &str) -> Result<Self, ScenarioError> {
        let table: toml::Table = toml::from_str(text).map_err(|e| parse_error(origin, text, &e))?;
        shape::check(&table)?;
        let mut file: Self = toml::from_str(text).map_err(|e| parse_error(origin, text, &e))?;
        if file.name.is_empty() {
            file.name = origin.to_owned();
        }
        Ok(file)
    }

    /// Deserializes a scenario kept in another format (`launch.json` keeps the one a run
    /// ran) under the same rule for sizes and sections as a TOML file (`scenario::shape`): serde
    /// alone reads a longer array's first three items, and a struct from an array. For
    /// `#[serde(deserialize_with = "ScenarioFile::checked")]`.
    pub fn checked<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let value = toml::Value::deserialize(d)?;
        let toml::Value::Table(table) = &value else {
            return Err(D::Error::custom(format!(
                "a scenario is a table of sections, not {}",
                value.type_str()
            )));
        };
        shape::check(table).map_err(D::Error::custom)?;
        Self::deserialize(value).map_err(D::Error::custom)
    }

    /// The file as TOML text.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_else(|e| format!("# cannot serialise scenario: {e}\n"))
    }
}

fn fmt_rows(m: &Mat3Rows) -> String {
    let mut s = String::from("[");
    for (i, r) in m.iter().enumerate() {
        let _ = write!(s, "{}[{}, {}, {}]", if i > 0 { ", " } else { "" }, r[0], r[1], r[2]);
    }
    s.push(']');
    s
}

fn finite_mat(field: &str, m: &Mat3Rows) -> Result<Matrix3<f64>, ScenarioError> {
    if m.iter().flatten().any(|v| !v.is_finite() || v.abs() > MAX_MAGNITUDE) {
        return Err(ScenarioError::Invalid {
            field: field.to_owned(),
            value: fmt_rows(m),
            allowed: "finite entries of magnitude ≤ 1e6".into(),
        });
    }
    Ok(Matrix3::from_fn(|i, j| m[i][j]))
}

fn finite_vec(field: &str, v: Row3) -> Result<DVec3, ScenarioError> {
    if v.iter().any(|x| !x.is_finite() || x.abs() > MAX_MAGNITUDE) {
        return Err(ScenarioError::invalid(field, v, "three finite numbers of magnitude ≤ 1e6"));
    }
    Ok(DVec3::from_array(v))
}

fn to_glam(m: &Matrix3<f64>) -> DMat3 {
    so3::from_rows([
        [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
        [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
        [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
    ])
}

/// A symmetric positive definite matrix and its ascending eigenvalues.
fn spd(field: &str, rows: &Mat3Rows) -> Result<(DMat3, [f64; 3]), ScenarioError> {
    let m = finite_mat(field, rows)?;
    let scale = m.amax().max(f64::MIN_POSITIVE);
    if (m - m.transpose()).amax() > 1e-9 * scale {
        return Err(ScenarioError::Invalid {
            field: field.to_owned(),
            value: fmt_rows(rows),
            allowed: "a symmetric positive definite matrix (this one is not symmetric)".into(),
        });
    }
    let mut eig: Vec<f64> = SymmetricEigen::new(m).eigenvalues.iter().copied().collect();
    eig.sort_by(f64::total_cmp);
    if eig[0] <= 1e-12 * scale {
        return Err(ScenarioError::Invalid {
            field: field.to_owned(),
            value: fmt_rows(rows),
            allowed: format!(
                "a symmetric positive definite matrix (eigenvalues here: {:.6}, {:.6}, {:.6})",
                eig[0], eig[1], eig[2]
            ),
        });
    }
    Ok((to_glam(&m), [eig[0], eig[1], eig[2]]))
}

/// The body of section `body` (`plant`, `reference`) and its principal moments; a warning
/// where they violate the triangle inequality.
fn body_params(
    body: &str,
    inertia: &Mat3Rows,
    rotor: &Row3,
    warnings: &mut Vec<String>,
) -> Result<(BodyParams, [f64; 3]), ScenarioError> {
    let (i, m) = spd(&format!("{body}.inertia"), inertia)?;
    if rotor.iter().any(|k| !k.is_finite() || *k <= 0.0 || *k > MAX_MAGNITUDE) {
        return Err(ScenarioError::invalid(
            &format!("{body}.rotor_inertia"),
            rotor,
            "the diagonal of K: three finite numbers > 0 and ≤ 1e6 (K must be positive diagonal)",
        ));
    }
    if m[0] + m[1] < m[2] {
        warnings.push(format!(
            "{body}.inertia: principal moments {:.4}, {:.4}, {:.4} violate the triangle inequality \
             ({:.4} + {:.4} < {:.4}): no physical rigid body has this inertia; running it anyway",
            m[0], m[1], m[2], m[0], m[1], m[2]
        ));
    }
    Ok((BodyParams::new(i, DVec3::from_array(*rotor)), m))
}

/// An attitude within [`ORTHONORMAL_TOL`] of SO(3), projected onto it (polar/SVD).
fn rotation(field: &str, rows: &Mat3Rows) -> Result<DMat3, ScenarioError> {
    let m = finite_mat(field, rows)?;
    let ortho = (m.transpose() * m - Matrix3::identity()).norm();
    let det = m.determinant();
    if ortho > ORTHONORMAL_TOL || (det - 1.0).abs() > ORTHONORMAL_TOL {
        return Err(ScenarioError::Invalid {
            field: field.to_owned(),
            value: fmt_rows(rows),
            allowed: format!(
                "a rotation matrix: orthonormal with det +1 to within 1e-6 \
                 (here ‖RᵀR − I‖ = {ortho:.3e}, det = {det:.9})"
            ),
        });
    }
    if ortho <= 4.0 * f64::EPSILON && (det - 1.0).abs() <= 4.0 * f64::EPSILON {
        return Ok(to_glam(&m)); // already a rotation to rounding: keep the user's digits
    }
    let svd = m.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(ScenarioError::invalid(field, rows, "a rotation matrix (its SVD failed)"));
    };
    Ok(to_glam(&(u * v_t)))
}

fn rate_pair(
    body: &str,
    omega: Option<Row3>,
    i_omega: Option<Row3>,
    inertia_inv: &DMat3,
) -> Result<DVec3, ScenarioError> {
    match (omega, i_omega) {
        (Some(_), Some(_)) => Err(ScenarioError::invalid(
            &format!("{body}.omega / {body}.i_omega"),
            "both given",
            "exactly one of them (or neither, for a body at rest)",
        )),
        (Some(w), None) => finite_vec(&format!("{body}.omega"), w),
        (None, Some(iw)) => Ok(*inertia_inv * finite_vec(&format!("{body}.i_omega"), iw)?),
        (None, None) => Ok(DVec3::ZERO),
    }
}

fn torque_profile(t: &TorqueFile) -> Result<TorqueProfile, ScenarioError> {
    let field = "reference.torque";
    let unexpected = |name: &str, present: bool| -> Result<(), ScenarioError> {
        if present {
            Err(ScenarioError::invalid(
                &format!("{field}.{name}"),
                "given",
                format!("only with the profiles that use it, not with `{}`", t.profile),
            ))
        } else {
            Ok(())
        }
    };
    let required = |name: &str, v: Option<Row3>| -> Result<DVec3, ScenarioError> {
        match v {
            Some(v) => finite_vec(&format!("{field}.{name}"), v),
            None => Err(ScenarioError::invalid(
                &format!("{field}.{name}"),
                "missing",
                format!("required for profile `{}`: three numbers", t.profile),
            )),
        }
    };
    match t.profile.as_str() {
        "zero" => {
            unexpected("value", t.value.is_some())?;
            unexpected("amplitude", t.amplitude.is_some())?;
            unexpected("frequency", t.frequency.is_some())?;
            unexpected("phase", t.phase.is_some())?;
            Ok(TorqueProfile::Zero)
        }
        "constant" => {
            unexpected("amplitude", t.amplitude.is_some())?;
            unexpected("frequency", t.frequency.is_some())?;
            unexpected("phase", t.phase.is_some())?;
            Ok(TorqueProfile::Constant(required("value", t.value)?))
        }
        "sinusoid" => {
            unexpected("value", t.value.is_some())?;
            Ok(TorqueProfile::Sinusoid {
                amplitude: required("amplitude", t.amplitude)?,
                frequency: required("frequency", t.frequency)?,
                phase: finite_vec(&format!("{field}.phase"), t.phase.unwrap_or_default())?,
            })
        }
        other => Err(ScenarioError::invalid(
            &format!("{field}.profile"),
            other,
            "`zero`, `constant` or `sinusoid`",
        )),
    }
}

fn in_range(field: &str, v: f64, (lo, hi): (f64, f64)) -> Result<(), ScenarioError> {
    if !(v.is_finite() && v >= lo && v <= hi) {
        return Err(ScenarioError::invalid(field, v, format!("a finite number from {lo} to {hi}")));
    }
    Ok(())
}

/// Checks the gains of the law and `P` (symmetric positive definite), and warns about
/// repeated eigenvalues of `P` and a linearisation that is not Hurwitz.
fn controller_gains(
    c: &ControllerFile,
    warnings: &mut Vec<String>,
) -> Result<(DMat3, [f64; 3]), ScenarioError> {
    for (field, v, allow_zero) in [
        ("controller.kp", c.kp, false),
        ("controller.kd", c.kd, false),
        ("controller.ki", c.ki, true),
    ] {
        let ok = v.is_finite() && v <= MAX_MAGNITUDE && if allow_zero { v >= 0.0 } else { v > 0.0 };
        if !ok {
            let allowed = if allow_zero {
                "a finite number ≥ 0 and ≤ 1e6 (0 switches the integral term off)"
            } else {
                "a finite number > 0 and ≤ 1e6"
            };
            return Err(ScenarioError::invalid(field, v, allowed));
        }
    }
    let (p, p_eig) = spd("controller.p", &c.p)?;
    let gap = (p_eig[1] - p_eig[0]).min(p_eig[2] - p_eig[1]);
    if gap <= 1e-9 * p_eig[2] {
        warnings.push(format!(
            "controller.p: repeated eigenvalues {:?}: ψ is then not a Morse function and its \
             critical set at π is not isolated; running it anyway",
            p_eig
        ));
    }
    if c.kd * c.kp <= c.ki {
        warnings.push(format!(
            "controller: k_d k_p = {} ≤ k_I = {}: the linearised closed loop is not Hurwitz; \
             expect no convergence",
            c.kd * c.kp,
            c.ki
        ));
    }
    Ok((p, p_eig))
}

/// Checks the actuator limits (and the initial rotor rates against them) and the
/// disturbance torque; warns when limits are set for a body without rotors.
fn actuators(
    file: &ScenarioFile,
    omega_r0: DVec3,
    warnings: &mut Vec<String>,
) -> Result<(ActuatorLimits, DVec3), ScenarioError> {
    let positive = |field: &str, v: Option<f64>| match v {
        Some(x) if !(x.is_finite() && x > 0.0 && x <= MAX_MAGNITUDE) => {
            Err(ScenarioError::invalid(
                field,
                x,
                "a finite number > 0 and ≤ 1e6, or no entry (unlimited)",
            ))
        }
        _ => Ok(v),
    };
    let limits = ActuatorLimits {
        rotor_torque: positive("plant.rotor_torque_limit", file.plant.rotor_torque_limit)?,
        rotor_rate: positive("plant.rotor_rate_limit", file.plant.rotor_rate_limit)?,
    };
    if let Some(w) = limits.rotor_rate {
        if omega_r0.abs().max_element() > w {
            return Err(ScenarioError::invalid(
                "plant.rotor_rates",
                omega_r0.to_array(),
                format!("each |Ω_r,i| ≤ plant.rotor_rate_limit = {w}"),
            ));
        }
    }
    let disturbance =
        finite_vec("plant.disturbance_torque", file.plant.disturbance_torque.unwrap_or_default())?;
    if limits.any() && file.run.actuation == Actuation::External {
        warnings.push(
            "plant.rotor_torque_limit / rotor_rate_limit limit the rotors; with \
             run.actuation = external there are none, so they have no effect"
                .to_owned(),
        );
    }
    Ok((limits, disturbance))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_scenarios_load_and_match_the_spec_table() {
        for (name, _) in BUILTIN {
            let s = Scenario::load(name).expect(name);
            assert_eq!(s.file.name, name);
            if !name.starts_with("paper-") {
                continue;
            }
            // The paper's runs have none of the extensions.
            assert_eq!(s.limits, ActuatorLimits::default());
            assert_eq!(s.disturbance, DVec3::ZERO);
            assert_eq!(s.file.controller.inertia_factor, 1.0);
            assert_eq!(s.gains.kp, 1.0);
            assert_eq!(s.gains.kd, 3.0);
            assert_eq!(s.gains.ki, 1.0);
            // The paper's I violates the triangle inequality: a warning, not an error.
            assert!(s.warnings.iter().any(|w| w.contains("triangle")), "{:?}", s.warnings);
            let m = s.plant_principal_moments;
            assert!((m[0] - 3.42).abs() < 0.01 && (m[2] - 8.28).abs() < 0.01, "{m:?}");
            // Ω(0) = I⁻¹ (1, 2.2, 5.1)
            let iw = s.plant.inertia * s.plant_init.omega;
            assert!((iw - DVec3::new(1.0, 2.2, 5.1)).length() < 1e-12);
        }
    }

    #[test]
    fn the_law_is_named_in_the_controller_section_and_left_out_when_it_is_the_default() {
        let text = BUILTIN.iter().find(|(n, _)| *n == "paper-zero").expect("built-in").1;
        let plain = Scenario::from_toml(text, "test").expect("valid");
        assert_eq!(plain.law, None);
        let named = text.replace("[controller]\n", "[controller]\nlaw = \"geometric-pid\"\n");
        assert_ne!(named, text, "the file has a [controller] section");
        let named = Scenario::from_toml(&named, "test").expect("valid");
        assert_eq!((named.law.as_deref(), &named.gains), (Some("geometric-pid"), &plain.gains));
        // Written out, a law left out stays out: reports of today's files are unchanged.
        assert!(!toml::to_string(&plain.file).expect("toml").contains("law"));
    }

    /// A parse error names its line and column and shows a bounded excerpt of the line: a
    /// 4 MB line is not echoed (it was, whole, with a caret line as long).
    #[test]
    fn a_parse_error_names_line_and_column_with_a_bounded_excerpt() {
        let text = BUILTIN[0].1.replace("kp = 1.0", &format!("kp = 1.0{}", "9x".repeat(2 << 20)));
        let e = Scenario::from_toml(&text, "long").expect_err("not a number").to_string();
        assert!(e.starts_with("scenario long: line "), "{}", &e[..200.min(e.len())]);
        assert!(e.contains(", column "), "{}", &e[..200.min(e.len())]);
        assert!(e.len() < 1000, "{} bytes: {}", e.len(), &e[..300]);
    }

    /// A byte that is not UTF-8 is named by its line and column; a FIFO is refused, not
    /// waited on; a file larger than any scenario is refused by its size.
    #[test]
    fn files_that_are_not_scenario_text_are_refused_naming_why() {
        let dir = std::env::temp_dir().join(format!("rl-scenario-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let bad = dir.join("bad.toml");
        std::fs::write(&bad, b"name = \"x\"\n\n  kp = \"\xfe\"\n").expect("write");
        let e = Scenario::load(bad.to_str().expect("utf-8")).expect_err("not UTF-8").to_string();
        assert!(e.contains("line 3, column 9: byte 0xfe is not UTF-8"), "{e}");
        let fifo = dir.join("fifo.toml");
        let c = std::ffi::CString::new(fifo.as_os_str().as_encoded_bytes()).expect("path");
        // SAFETY: a valid path for the call.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0, "mkfifo");
        let e = Scenario::load(fifo.to_str().expect("utf-8")).expect_err("a FIFO").to_string();
        assert!(e.contains("a FIFO, not a regular file"), "{e}");
        let big = dir.join("big.toml");
        std::fs::write(&big, vec![b'#'; MAX_FILE_BYTES as usize + 1]).expect("write");
        let e = Scenario::load(big.to_str().expect("utf-8")).expect_err("too big").to_string();
        assert!(e.contains("more than the 1048576 bytes"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The one rule for sizes holds for the whole file (`shape`): a 3-vector with extra
    /// items and a table written as an array were read without a word.
    #[test]
    fn oversize_vectors_and_sections_as_arrays_are_refused() {
        let text = BUILTIN[0].1;
        let extra = "rotor_inertia = [5.0, 6.0, 7.0, \"ignored\", {x = 1}, ";
        let long = text.replacen("rotor_inertia = [", extra, 1);
        let e = Scenario::from_toml(&long, "t").expect_err("5 items").to_string();
        assert!(e.starts_with("plant.rotor_inertia = ") && e.contains("(here 8 items)"), "{e}");
        // `run = [1, 2]` ran at 2 Hz for 1 s.
        let head = text.split("[run]").next().expect("a [run] section");
        let e = Scenario::from_toml(&format!("run = [1, 2]\n{head}"), "t").expect_err("array");
        assert!(e.to_string().starts_with("run = [1, 2] is not allowed: a table"), "{e}");
    }

    /// A scenario kept as JSON (`launch.json`) is read under the same rule: serde_json
    /// read `"run": [1, 2]` by position and a 5-item vector's first three.
    #[test]
    fn a_scenario_kept_as_json_is_checked_as_a_file_is() {
        #[derive(Debug, Deserialize)]
        struct Kept {
            #[serde(deserialize_with = "ScenarioFile::checked")]
            #[allow(dead_code)]
            scenario: ScenarioFile,
        }
        let file = ScenarioFile::load("paper-zero").expect("built-in");
        let mut j = serde_json::json!({ "scenario": file });
        serde_json::from_value::<Kept>(j.clone()).expect("as written");
        j["scenario"]["run"] = serde_json::json!([1, 2]);
        let e = serde_json::from_value::<Kept>(j.clone()).expect_err("array").to_string();
        assert!(e.starts_with("run = [1, 2] is not allowed: a table"), "{e}");
        j["scenario"]["run"] = serde_json::json!({"rate_hz": 2.0});
        j["scenario"]["plant"]["rotor_inertia"] = serde_json::json!([5.0, 6.0, 7.0, "x"]);
        let e = serde_json::from_value::<Kept>(j).expect_err("4 items").to_string();
        assert!(e.starts_with("plant.rotor_inertia = [5.0, 6.0, 7.0, \"x\"] is not"), "{e}");
    }

    #[test]
    fn the_paper_sinusoid_is_sin_cos_sin() {
        let s = Scenario::load("paper-sinusoid").expect("builtin");
        for t in [0.0, 0.7, 3.0, 11.5] {
            let u = s.reference_torque.at(t);
            let want = DVec3::new(f64::sin(t), f64::cos(t), f64::sin(t));
            assert!((u - want).length() < 1e-15, "{t}");
        }
    }
}
