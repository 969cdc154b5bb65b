//! `OUT/controller.json` (`$ROTORLOOP_CONTROLLER_JSON`): what a controller of the user's
//! own needs of the law, resolved from the scenario as run (docs/wire.md). Written by the
//! launcher from [`ControllerJson`]; its key table in docs/wire.md is [`KEYS`], which a
//! unit test holds to the type's serialized keys, and its layout carries
//! [`CONTROLLER_JSON_VERSION`], raised whenever a key is renamed, removed or changes
//! meaning (a key added keeps it).

use serde::{Deserialize, Serialize};

/// The layout version of `controller.json` (its `layout_version` key).
pub const CONTROLLER_JSON_VERSION: u32 = 1;

/// The whole file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControllerJson {
    /// [`CONTROLLER_JSON_VERSION`].
    pub layout_version: u32,
    /// The law's name (`geometric-pid`, `mrp-pid`).
    pub law: String,
    /// `internal` (rotor torque `u`) or `external` (body torque `τ`).
    pub actuation: String,
    /// The tick, `1/rate_hz` (s).
    pub dt_s: f64,
    /// The rate (Hz).
    pub rate_hz: f64,
    /// Ticks in the run.
    pub ticks: u64,
    /// The gains.
    pub gains: JsonGains,
    /// The controller's model of the body.
    pub model: JsonModel,
    /// The actuator limits the law knows of.
    pub limits: JsonLimits,
    /// `conditional` or `none`.
    pub anti_windup: String,
    /// The scenario's `[controller.law_params]` (the `mrp-pid` law's `k`, `p`, `ki`, …).
    pub law_params: serde_json::Map<String, serde_json::Value>,
}

/// `gains`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JsonGains {
    /// `k_p`.
    pub kp: f64,
    /// `k_d`.
    pub kd: f64,
    /// `k_i`.
    pub ki: f64,
    /// `P`, rows.
    pub p: [[f64; 3]; 3],
}

/// `model`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JsonModel {
    /// `I`, rows (kg m²).
    pub inertia: [[f64; 3]; 3],
    /// `K`'s diagonal (kg m²).
    pub rotor_inertia: [f64; 3],
}

/// `limits`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JsonLimits {
    /// `u_max` (N m), or null.
    pub rotor_torque_nm: Option<f64>,
    /// `Ω_max` (rad/s), or null.
    pub rotor_rate_rad_s: Option<f64>,
}

/// Every key of the file, as docs/wire.md's table: (key path, JSON type, meaning).
pub const KEYS: &[(&str, &str, &str)] = &[
    (
        "layout_version",
        "integer",
        "this file's layout version (now 1); raised when a key is renamed, removed or changes meaning",
    ),
    ("law", "string", "the law: `geometric-pid` or `mrp-pid`"),
    (
        "actuation",
        "string",
        "`internal` (answer with the rotor torque `u`) or `external` (the body torque `τ`)",
    ),
    ("dt_s", "number", "the tick `dt = 1/rate_hz` (s): the integral's step"),
    ("rate_hz", "number", "the loop rate (Hz)"),
    (
        "ticks",
        "integer",
        "the run's last tick: states are published for ticks 0 to `ticks` inclusive (`ticks` + 1 states), and the one of tick `ticks` has `FLAG_LAST`",
    ),
    ("gains.kp", "number", "`k_p`"),
    ("gains.kd", "number", "`k_d`"),
    ("gains.ki", "number", "`k_i`"),
    ("gains.p", "3×3 numbers, rows", "`P` (the attitude error's weight)"),
    (
        "model.inertia",
        "3×3 numbers, rows",
        "the controller's model of `I`, the body's inertia without the rotors' spin inertia (kg m²)",
    ),
    (
        "model.rotor_inertia",
        "3 numbers",
        "the controller's model of `K`, the rotors' spin inertia (diagonal, kg m²)",
    ),
    (
        "limits.rotor_torque_nm",
        "number or null",
        "`u_max`: each `|u_i|` is clamped to it by the plant; null: no limit",
    ),
    (
        "limits.rotor_rate_rad_s",
        "number or null",
        "`Ω_max`: torque that would spin a rotor at or past it is cut by the plant; null: no limit",
    ),
    (
        "anti_windup",
        "string",
        "`conditional` (hold `ξ_I` on a tick whose `u` the limits change unless the step shrinks it) or `none`; matters only with limits",
    ),
    (
        "law_params",
        "object",
        "the scenario's `[controller.law_params]` as given (empty for `geometric-pid`)",
    ),
];

/// [`KEYS`] as a markdown table.
pub fn keys_markdown() -> String {
    let mut md = String::from("| key | type | meaning |\n|---|---|---|\n");
    for (k, t, m) in KEYS {
        md.push_str(&format!("| `{k}` | {t} | {} |\n", m.replace('|', "\\|")));
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every leaf key path of a JSON object (objects other than `law_params` descended).
    fn paths(v: &serde_json::Value, prefix: &str, out: &mut Vec<String>) {
        if let serde_json::Value::Object(m) = v {
            for (k, x) in m {
                let p = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                if x.is_object() && k != "law_params" {
                    paths(x, &p, out);
                } else {
                    out.push(p);
                }
            }
        }
    }

    #[test]
    fn the_key_table_names_every_key_of_the_type_and_no_other() {
        let j = ControllerJson {
            layout_version: CONTROLLER_JSON_VERSION,
            law: "geometric-pid".into(),
            actuation: "internal".into(),
            dt_s: 1e-3,
            rate_hz: 1e3,
            ticks: 1,
            gains: JsonGains { kp: 1.0, kd: 1.0, ki: 1.0, p: [[0.0; 3]; 3] },
            model: JsonModel { inertia: [[0.0; 3]; 3], rotor_inertia: [0.0; 3] },
            limits: JsonLimits { rotor_torque_nm: None, rotor_rate_rad_s: Some(1.0) },
            anti_windup: "conditional".into(),
            law_params: serde_json::Map::new(),
        };
        let v = serde_json::to_value(&j).expect("serializes");
        let mut got = Vec::new();
        paths(&v, "", &mut got);
        got.sort();
        let mut want: Vec<String> = KEYS.iter().map(|(k, _, _)| (*k).to_owned()).collect();
        want.sort();
        assert_eq!(got, want);
        let back: ControllerJson = serde_json::from_value(v).expect("reads back");
        assert_eq!(back, j);
    }
}
