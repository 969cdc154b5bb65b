//! The one rule for sizes in a scenario file, checked on the TOML before serde reads it:
//! a 3-vector is exactly three numbers, a 3×3 matrix exactly three rows of three numbers,
//! and a section is a table. serde alone reads `[f64; 3]` from the first three items of a
//! longer array, whatever follows them, and a struct from an array by position (`run =
//! [1, 2]` ran at 2 Hz, past the unknown-key check); both are refused here, naming the
//! key, what it holds and what is allowed.

use toml::{Table, Value};

use super::ScenarioError;

/// What a key of the file must hold.
#[derive(Debug, Clone, Copy)]
enum Shape {
    /// A table whose listed keys have these shapes (its other keys are serde's to check:
    /// unknown keys are refused there).
    Section(&'static [(&'static str, Shape)]),
    /// A table of any keys (`[controller.law_params]`: the law checks them).
    AnyTable,
    /// Three numbers.
    Vec3,
    /// Three rows of three numbers.
    Mat3,
}

use Shape::{AnyTable, Mat3, Section, Vec3};

const PLANT: &[(&str, Shape)] = &[
    ("inertia", Mat3),
    ("rotor_inertia", Vec3),
    ("attitude", Mat3),
    ("omega", Vec3),
    ("i_omega", Vec3),
    ("rotor_rates", Vec3),
    ("rotor_angles", Vec3),
    ("disturbance_torque", Vec3),
];
const TORQUE: &[(&str, Shape)] =
    &[("value", Vec3), ("amplitude", Vec3), ("frequency", Vec3), ("phase", Vec3)];
const REFERENCE: &[(&str, Shape)] = &[
    ("inertia", Mat3),
    ("rotor_inertia", Vec3),
    ("attitude", Mat3),
    ("omega", Vec3),
    ("i_omega", Vec3),
    ("torque", Section(TORQUE)),
];
const CONTROLLER: &[(&str, Shape)] = &[("p", Mat3), ("law_params", AnyTable)];
/// The file: its sections and, in them, every vector and matrix.
const FILE: &[(&str, Shape)] = &[
    ("plant", Section(PLANT)),
    ("reference", Section(REFERENCE)),
    ("controller", Section(CONTROLLER)),
    ("run", Section(&[])),
];

const VEC3: &str = "three numbers, e.g. [1.0, 2.0, 3.0]";
const MAT3: &str =
    "three rows of three numbers, e.g. [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]";

/// Checks every section, vector and matrix of a parsed file against the rule.
pub(super) fn check(file: &Table) -> Result<(), ScenarioError> {
    check_table("", file, FILE)
}

fn check_table(
    path: &str,
    table: &Table,
    keys: &[(&'static str, Shape)],
) -> Result<(), ScenarioError> {
    for (key, shape) in keys {
        let Some(value) = table.get(*key) else { continue };
        let field = if path.is_empty() { (*key).to_owned() } else { format!("{path}.{key}") };
        check_value(&field, value, *shape)?;
    }
    Ok(())
}

fn check_value(field: &str, value: &Value, shape: Shape) -> Result<(), ScenarioError> {
    let refuse = |allowed: &str, here: String| ScenarioError::Invalid {
        field: field.to_owned(),
        value: describe(value),
        allowed: format!("{allowed} (here {here})"),
    };
    match shape {
        Section(keys) => match value {
            Value::Table(t) => check_table(field, t, keys),
            other => Err(refuse(&table_allowed(field), a(other))),
        },
        AnyTable => match value {
            Value::Table(_) => Ok(()),
            other => Err(refuse(&table_allowed(field), a(other))),
        },
        Vec3 => numbers(value).map_err(|here| refuse(VEC3, here)),
        Mat3 => {
            let Value::Array(rows) = value else { return Err(refuse(MAT3, a(value))) };
            if rows.len() != 3 {
                return Err(refuse(MAT3, items(rows.len(), "row")));
            }
            for (i, row) in rows.iter().enumerate() {
                numbers(row).map_err(|here| refuse(MAT3, format!("row {}: {here}", i + 1)))?;
            }
            Ok(())
        }
    }
}

/// Whether `value` is three numbers; else what it is instead.
fn numbers(value: &Value) -> Result<(), String> {
    let Value::Array(v) = value else { return Err(a(value)) };
    if v.len() != 3 {
        return Err(items(v.len(), "item"));
    }
    match v.iter().position(|x| !matches!(x, Value::Integer(_) | Value::Float(_))) {
        Some(i) => Err(format!("item {} is {}", i + 1, a(&v[i]))),
        None => Ok(()),
    }
}

fn table_allowed(field: &str) -> String {
    format!("a table of named keys (a `[{field}]` section, or `{{ key = … }}`)")
}

fn items(n: usize, what: &str) -> String {
    format!("{n} {what}{}", if n == 1 { "" } else { "s" })
}

/// `a string`, `an array`, … (TOML's type names).
fn a(v: &Value) -> String {
    let t = v.type_str();
    let article = if t.starts_with(['a', 'e', 'i', 'o', 'u']) { "an" } else { "a" };
    format!("{article} {t}")
}

/// The value as TOML when short; else what it is and its size (a million-item array is not
/// echoed).
fn describe(v: &Value) -> String {
    const MAX: usize = 80;
    let text = v.to_string();
    if text.len() <= MAX {
        return text;
    }
    match v {
        Value::Array(x) => format!("{} of {}", a(v), items(x.len(), "item")),
        Value::Table(x) => format!("{} of {}", a(v), items(x.len(), "key")),
        _ => format!("{} of {} bytes", a(v), text.len()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn refusal(toml_text: &str) -> String {
        let t: Table = toml::from_str(toml_text).expect("TOML");
        check(&t).expect_err("refused").to_string()
    }

    /// A vector of another length, or with an item of another type, is refused naming the
    /// key, the value and what is allowed; a long one is not echoed.
    #[test]
    fn vectors_are_exactly_three_numbers() {
        let e = refusal("[plant]\nrotor_inertia = [5.0, 6.0, 7.0, \"ignored\", {x = 1}]");
        assert_eq!(
            e,
            "plant.rotor_inertia = [5.0, 6.0, 7.0, \"ignored\", { x = 1 }] is not allowed: \
             three numbers, e.g. [1.0, 2.0, 3.0] (here 5 items)"
        );
        let e = refusal("[reference.torque]\nvalue = [1, 2, \"3\"]");
        assert!(e.starts_with("reference.torque.value = "), "{e}");
        assert!(e.ends_with("(here item 3 is a string)"), "{e}");
        let big = format!("[plant]\nrotor_inertia = [{}]", vec!["1.0"; 100_000].join(","));
        let e = refusal(&big);
        assert!(e.starts_with("plant.rotor_inertia = an array of 100000 items is not"), "{e}");
        assert!(e.len() < 200, "{e}");
    }

    #[test]
    fn matrices_are_exactly_three_rows_of_three_numbers() {
        let four = "[[1.0,0,0,0],[0,1.0,0,0],[0,0,1.0,0],[0,0,0,1.0]]";
        let e = refusal(&format!("[plant]\ninertia = {four}"));
        assert!(e.starts_with("plant.inertia = "), "{e}");
        assert!(e.ends_with("(here 4 rows)"), "{e}");
        let e = refusal("[controller]\np = [[1.0,0,0],[0,1.0,0,0],[0,0,1.0]]");
        assert!(e.ends_with("(here row 2: 4 items)"), "{e}");
        let e = refusal("[reference]\nattitude = [1, 2, 3]");
        assert!(e.ends_with("(here row 1: an integer)"), "{e}");
    }

    /// A table written as an array is refused: serde would read it by position.
    #[test]
    fn sections_are_tables_never_arrays() {
        let e = refusal("run = [1, 2]");
        assert_eq!(
            e,
            "run = [1, 2] is not allowed: a table of named keys (a `[run]` section, or \
             `{ key = … }`) (here an array)"
        );
        let e = refusal("[reference]\ntorque = [\"constant\", [0.2, 0.1, 0.2]]");
        assert!(e.starts_with("reference.torque = "), "{e}");
        assert!(e.ends_with("(here an array)"), "{e}");
        let e = refusal("[controller]\nlaw_params = [1.0]");
        assert!(e.starts_with("controller.law_params = [1.0] is not allowed"), "{e}");
        let e = refusal("plant = 3");
        assert!(e.ends_with("(here an integer)"), "{e}");
    }
}
