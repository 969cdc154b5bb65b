//! Every JSON message against its channel's own schema, with a JSON Schema validator
//! (`jsonschema`, not the writer's code): what Foxglove's panels trust a schema for.

use std::collections::BTreeMap;

/// The validators of the channels seen, by topic, and what was checked.
#[derive(Default)]
pub struct Schemas {
    validators: BTreeMap<String, jsonschema::Validator>,
    /// JSON messages validated, by topic.
    pub checked: BTreeMap<String, u64>,
}

/// 2⁶⁴−1 (`NO_TICK`) as JSON would write it: no message may carry it.
pub const NO_TICK_TEXT: &str = "18446744073709551615";

impl Schemas {
    /// Declares `topic`'s JSON schema (its text as the channel declared it).
    pub fn declare(&mut self, topic: &str, schema: &[u8]) {
        let v: serde_json::Value = serde_json::from_slice(schema)
            .unwrap_or_else(|e| panic!("{topic}: a schema that is not JSON: {e}"));
        let validator = jsonschema::validator_for(&v)
            .unwrap_or_else(|e| panic!("{topic}: not a valid JSON schema: {e}"));
        self.validators.insert(topic.to_owned(), validator);
    }

    /// Checks one JSON message of `topic` against its channel's schema, and that it carries
    /// no `NO_TICK`.
    pub fn check(&mut self, topic: &str, payload: &[u8]) {
        let text = std::str::from_utf8(payload).expect("JSON is UTF-8");
        assert!(!text.contains(NO_TICK_TEXT), "{topic} carries NO_TICK as a number: {text}");
        let v: serde_json::Value = serde_json::from_str(text).expect("JSON");
        let validator = self.validators.get(topic).unwrap_or_else(|| panic!("{topic}: no schema"));
        if let Err(e) = validator.validate(&v) {
            panic!("{topic}: a message its schema refuses: {e} (at {}): {text}", e.instance_path());
        }
        *self.checked.entry(topic.to_owned()).or_default() += 1;
    }
}
