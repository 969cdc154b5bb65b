//! The topics of `run.mcap` and of the live view (`rotorloop foxglove`), in one place: each
//! JSON topic's name, its schema's name and its JSON schema, and the JSON of the samples as
//! both write them. One name has one schema everywhere: the file ([`super::mcap`]) and the
//! live server declare their channels from here, and a test validates every message of a
//! run with kills against its channel's schema with a JSON Schema validator.
//!
//! JSON has no NaN and JavaScript no exact integer above 2⁵³: a NaN is `null`, and a tick
//! field that holds [`NO_TICK`] ("no torque sample", 2⁶⁴−1) is `null` (never the number).

use rotorloop_common::wire::{
    NO_TICK, ReferenceSample, SendCost, StateSample, TorqueSample, WireField,
};
use serde_json::{Value, json};

/// A JSON topic: its name, its schema's name and its JSON schema.
#[derive(Debug, Clone, Copy)]
pub struct JsonTopic {
    /// The topic (`/rotorloop/...`).
    pub topic: &'static str,
    /// The schema's name (`rotorloop.…`).
    pub schema_name: &'static str,
    schema: fn() -> Value,
}

impl JsonTopic {
    /// Its JSON schema (draft 2020-12).
    pub fn schema(&self) -> Value {
        (self.schema)()
    }

    /// Its JSON schema as the bytes a channel declares.
    pub fn schema_bytes(&self) -> Vec<u8> {
        serde_json::to_vec(&self.schema()).unwrap_or_default()
    }
}

/// Every field of the plant's state sample.
pub const STATE: JsonTopic =
    JsonTopic { topic: "/rotorloop/state", schema_name: "rotorloop.StateSample", schema: state };
/// Every field of the controller's answer.
pub const TORQUE: JsonTopic =
    JsonTopic { topic: "/rotorloop/torque", schema_name: "rotorloop.TorqueSample", schema: torque };
/// Every field of the reference sample.
pub const REFERENCE: JsonTopic = JsonTopic {
    topic: "/rotorloop/reference",
    schema_name: "rotorloop.ReferenceSample",
    schema: reference,
};
/// The tracking error per tick.
pub const TRACKING: JsonTopic =
    JsonTopic { topic: "/rotorloop/tracking", schema_name: "rotorloop.Tracking", schema: tracking };
/// The latency per tick.
pub const LATENCY: JsonTopic =
    JsonTopic { topic: "/rotorloop/latency", schema_name: "rotorloop.Latency", schema: latency };
/// One message per incident.
pub const INCIDENTS: JsonTopic = JsonTopic {
    topic: "/rotorloop/incidents",
    schema_name: "rotorloop.Incident",
    schema: incident,
};
/// One message per window of ticks (a tenth of a second of the loop's time): the
/// extremes of its ticks, in `run.mcap` only (the live view has every tick).
pub const WINDOW: JsonTopic =
    JsonTopic { topic: "/rotorloop/window", schema_name: "rotorloop.Window", schema: window };
/// Every JSON topic.
pub const JSON_TOPICS: [JsonTopic; 7] =
    [STATE, TORQUE, REFERENCE, TRACKING, LATENCY, INCIDENTS, WINDOW];

/// The per-tick hops and stages of [`LATENCY`] (ns, `null` where a stamp is missing), in
/// its order; [`WINDOW`] has each one's largest as `NAME_max`.
pub const LATENCY_HOPS: [&str; 9] = [
    "state_transport_ns",
    "controller_compute_ns",
    "validate_ns",
    "pair_ns",
    "law_ns",
    "publish_prep_ns",
    "tick_lateness_ns",
    "state_prep_ns",
    "reference_lead_ns",
];

/// The tracking columns whose largest [`WINDOW`] has, as `NAME_max`.
pub const WINDOW_TRACKING: [&str; 2] = ["err_deg", "werr"];

/// The log (`foxglove.Log`, protobuf).
pub const LOG: &str = "/rotorloop/log";
/// The attitudes (`foxglove.FrameTransform`, protobuf).
pub const TF: &str = "/tf";

/// The u64 fields of the samples that hold a tick or [`NO_TICK`]: `null` for [`NO_TICK`].
pub const TICK_OR_NONE: &[&str] = &["applied_torque_tick", "effect_ticks", "prev_tick"];

/// `trace.csv`'s columns on `/rotorloop/tracking`, each a number or `null`.
pub const TRACKING_COLUMNS: &[&str] =
    &["t", "err_deg", "werr", "h_drift_rel", "energy_residual", "delay_s", "u1", "u2", "u3"];

/// A number, `null` where it is NaN or infinite.
const NUMBER: &str = r#"{"type": ["number", "null"]}"#;

fn number() -> Value {
    serde_json::from_str(NUMBER).unwrap_or_default()
}

fn integer_or_null(description: &str) -> Value {
    json!({"type": ["integer", "null"], "description": description})
}

fn object(properties: serde_json::Map<String, Value>) -> Value {
    let required: Vec<&String> = properties.keys().collect();
    json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "type": "object",
        "properties": properties,
        "required": required,
        "additionalProperties": false,
    })
}

/// The schema of one wire field: `u64` an integer (a tick field an integer or `null`),
/// `f64` a number or `null`, arrays of them with their length, the send cost an object.
fn field_schema(f: &WireField) -> Value {
    let doc = f.doc.split_whitespace().collect::<Vec<_>>().join(" ");
    let tick = TICK_OR_NONE.contains(&f.name);
    let scalar = |ty: &str| match ty {
        "u64" if tick => integer_or_null("a tick; null: none (NO_TICK)"),
        "u64" => json!({"type": "integer", "minimum": 0}),
        _ => number(),
    };
    let mut s = match f.ty {
        "u64" | "f64" => scalar(f.ty),
        "SendCost" => sample_schema(SendCost::FIELDS),
        t => {
            let n = f.size / 8;
            let item = scalar(if t.starts_with("[u64") { "u64" } else { "f64" });
            json!({"type": "array", "items": item, "minItems": n, "maxItems": n})
        }
    };
    s["description"] = Value::String(doc);
    s
}

fn sample_schema(fields: &[WireField]) -> Value {
    object(fields.iter().map(|f| (f.name.to_owned(), field_schema(f))).collect())
}

fn state() -> Value {
    sample_schema(StateSample::FIELDS)
}

fn torque() -> Value {
    sample_schema(TorqueSample::FIELDS)
}

fn reference() -> Value {
    sample_schema(ReferenceSample::FIELDS)
}

fn tracking() -> Value {
    let mut p: serde_json::Map<String, Value> =
        TRACKING_COLUMNS.iter().map(|c| ((*c).to_owned(), number())).collect();
    p.insert("tick".into(), json!({"type": "integer", "minimum": 0}));
    p.insert(
        "in_incident".into(),
        json!({"type": ["integer", "null"], "enum": [0, 1, null],
               "description": "1: the tick is in an incident's window; null: not known"}),
    );
    object(p)
}

fn latency() -> Value {
    let hop = || integer_or_null("ns; null: a stamp is missing (a tick nobody answered)");
    let mut p = serde_json::Map::new();
    p.insert("tick".into(), json!({"type": "integer", "minimum": 0}));
    p.insert("t_s".into(), number());
    for h in LATENCY_HOPS {
        p.insert(h.into(), hop());
    }
    for n in ["state_send_ns", "misses", "torque_in_force_recv_ns"] {
        p.insert(n.into(), json!({"type": "integer", "minimum": 0}));
    }
    p.insert("safe_mode".into(), json!({"type": "boolean"}));
    p.insert("torque_in_force_tick".into(), integer_or_null("null: no torque in force"));
    object(p)
}

fn window() -> Value {
    let count = |d: &str| json!({"type": "integer", "minimum": 0, "description": d});
    let mut p = serde_json::Map::new();
    p.insert("first_tick".into(), count("the window's first tick"));
    p.insert("last_tick".into(), count("its last tick"));
    p.insert("t_s".into(), number());
    p.insert("ticks".into(), count("the ticks of it with a state recorded"));
    p.insert("answered".into(), count("those the controller answered"));
    p.insert("misses".into(), count("ticks without a fresh torque in time, in the window"));
    p.insert("safe_mode_ticks".into(), count("ticks in safe mode"));
    p.insert("in_incident_ticks".into(), count("ticks in an incident's window"));
    for c in WINDOW_TRACKING {
        let mut n = number();
        n["description"] = Value::String(format!("the largest {c} (trace.csv's column)"));
        p.insert(format!("{c}_max"), n);
    }
    for h in LATENCY_HOPS {
        let d = format!("the largest {h} of the window; null: none had both stamps");
        p.insert(format!("{h}_max"), integer_or_null(&d));
    }
    object(p)
}

fn incident() -> Value {
    let text = |d: &str| json!({"type": ["string", "null"], "description": d});
    let mut p = serde_json::Map::new();
    for n in ["start_tick", "end_tick", "misses"] {
        p.insert(n.into(), json!({"type": "integer", "minimum": 0}));
    }
    p.insert("start_s".into(), number());
    p.insert("duration_s".into(), number());
    p.insert("kind".into(), json!({"type": "string"}));
    p.insert("cause_role".into(), text("the process that held the loop up; null: live"));
    p.insert("cause_stage".into(), text("the stage, or what was done; null: live"));
    p.insert("evidence".into(), text("the stamps and kernel figures; null: live"));
    p.insert("flags".into(), json!({"type": "string"}));
    p.insert(
        "peak_deviation_deg".into(),
        json!({"type": ["number", "null"],
               "description": "against the loop without it (deg); null: not computed, or live"}),
    );
    p.insert(
        "recovery_s".into(),
        json!({"type": ["number", "null"],
               "description": "until below 10 % of the peak (s); null: not within the run, \
                               not computed, or live"}),
    );
    p.insert(
        "analysed".into(),
        json!({"type": "boolean",
               "description": "true: rotorloop explain's analysis after the run \
                               (incidents.csv); false: a window the live view saw"}),
    );
    object(p)
}

/// `v` with every [`TICK_OR_NONE`] field that holds [`NO_TICK`] made `null`.
fn ticks_or_null(mut v: Value) -> Value {
    for name in TICK_OR_NONE {
        match v.get_mut(*name) {
            Some(Value::Array(a)) => a.iter_mut().for_each(none_if_no_tick),
            Some(x) => none_if_no_tick(x),
            None => {}
        }
    }
    v
}

fn none_if_no_tick(v: &mut Value) {
    if v.as_u64() == Some(NO_TICK) {
        *v = Value::Null;
    }
}

/// A state sample as JSON ([`STATE`]).
pub fn state_json(s: &StateSample) -> Value {
    ticks_or_null(serde_json::to_value(s).unwrap_or_default())
}

/// A torque sample as JSON ([`TORQUE`]).
pub fn torque_json(t: &TorqueSample) -> Value {
    ticks_or_null(serde_json::to_value(t).unwrap_or_default())
}

/// A reference sample as JSON ([`REFERENCE`]).
pub fn reference_json(r: &ReferenceSample) -> Value {
    serde_json::to_value(r).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A state with no torque in force, and effect slots unused, writes `null` for those
    /// ticks, never 2⁶⁴−1; a tick that is there stays a number.
    fn rest() -> rotorloop_common::params::RotorBodyState {
        use glam::{DMat3, DVec3};
        rotorloop_common::params::RotorBodyState {
            r: DMat3::IDENTITY,
            omega: DVec3::ZERO,
            omega_r: DVec3::ZERO,
            theta: DVec3::ZERO,
        }
    }

    #[test]
    fn no_tick_is_null() {
        let mut s = StateSample::of(5, 0.005, &rest());
        s.effect_ticks[0] = 4;
        let v = state_json(&s);
        assert_eq!(v["applied_torque_tick"], Value::Null);
        assert_eq!(v["effect_ticks"][0], 4);
        assert_eq!(v["effect_ticks"][1], Value::Null);
        assert!(!v.to_string().contains(&NO_TICK.to_string()));
        let t = TorqueSample { prev_tick: NO_TICK, ..TorqueSample::default() };
        assert_eq!(torque_json(&t)["prev_tick"], Value::Null);
    }

    /// Every field of each sample is in its schema, and nothing else: the schema is made
    /// from the same field table as the sample.
    #[test]
    fn each_sample_schema_names_every_field() {
        let s = StateSample::of(0, 0.0, &rest());
        for (v, topic) in [(state_json(&s), STATE), (torque_json(&TorqueSample::default()), TORQUE)]
        {
            let schema = topic.schema();
            let props = schema["properties"].as_object().expect("properties");
            let fields = v.as_object().expect("an object");
            assert_eq!(props.keys().collect::<Vec<_>>(), fields.keys().collect::<Vec<_>>());
        }
    }
}
