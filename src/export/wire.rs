//! `rotorloop wire --format F`: the wire contract of the three samples (and the send cost
//! they carry), rendered from the Rust types' own field tables
//! ([`rotorloop_common::wire`]'s `FIELDS`): JSON for tools, the tables of `docs/wire.md`,
//! the Python module `python/rotorloop_wire.py` (ctypes) and the C header
//! `include/rotorloop_wire.h`. The files in the repository are this output; a test
//! compares them, and checks every offset with Python's ctypes and a C compiler.

use std::fmt::Write as _;

use rotorloop_common::graph::Topic;
use rotorloop_common::wire::{
    FLAG_LAST, FLAG_REALTIME, FLAG_SAFE_MODE, FLAG_SATURATED, LAYOUT_VERSION, MAX_EFFECTS, NO_TICK,
    ReferenceSample, SendCost, StateSample, TORQUE_SKIPPED, TorqueSample, WireField,
};

/// What `rotorloop wire` renders.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// Every type: name, iceoryx2 type name, size, fields with offset, size, type, doc.
    Json,
    /// The field tables of docs/wire.md.
    Markdown,
    /// `python/rotorloop_wire.py`: ctypes Structures.
    Python,
    /// `include/rotorloop_wire.h`: C structs with static asserts of every offset.
    C,
}

/// `rotorloop wire` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct WireArgs {
    /// What to print.
    #[arg(long, value_enum, default_value = "markdown")]
    pub format: Format,
}

/// One sample type of the contract.
#[derive(Debug, Clone, Copy)]
pub struct WireType {
    /// Its Rust (and Python, and C) name.
    pub name: &'static str,
    /// Its iceoryx2 type name (`None`: not sent alone, only inside the samples).
    pub type_name: Option<&'static str>,
    /// The topic it is published on.
    pub topic: Option<&'static str>,
    /// Its size (bytes).
    pub size: usize,
    /// What its doc comment says.
    pub doc: &'static str,
    /// Its fields.
    pub fields: &'static [WireField],
}

/// The iceoryx2 type name of `T`.
fn type_name<T: iceoryx2::prelude::ZeroCopySend>() -> &'static str {
    // SAFETY: type_name only returns the static name.
    unsafe { <T as iceoryx2::prelude::ZeroCopySend>::type_name() }
}

/// The contract's types, the nested one first (C and Python need it declared first).
pub fn types() -> [WireType; 4] {
    // A sample type sent on `topic` (`None`: only inside the samples).
    macro_rules! wire_type {
        ($t:ident, $topic:expr) => {
            WireType {
                name: stringify!($t),
                type_name: $topic.map(|_: Topic| type_name::<$t>()),
                topic: $topic.map(Topic::name),
                size: size_of::<$t>(),
                doc: $t::DOC,
                fields: $t::FIELDS,
            }
        };
    }
    [
        wire_type!(SendCost, None),
        wire_type!(StateSample, Some(Topic::State)),
        wire_type!(ReferenceSample, Some(Topic::Reference)),
        wire_type!(TorqueSample, Some(Topic::Torque)),
    ]
}

/// The constants a sample's fields refer to: name, value, doc.
pub fn constants() -> Vec<(&'static str, u64, &'static str)> {
    vec![
        ("LAYOUT_VERSION", u64::from(LAYOUT_VERSION), "the layout version in every type name"),
        (
            "MAX_EFFECTS",
            MAX_EFFECTS as u64,
            "length of StateSample.effect_ticks and effect_offsets_s",
        ),
        ("NO_TICK", NO_TICK, "\"no torque sample\" in a tick field"),
        ("FLAG_LAST", FLAG_LAST, "StateSample.flags: the run's last tick"),
        ("FLAG_REALTIME", FLAG_REALTIME, "StateSample.flags: the plant runs on a real-time grid"),
        ("FLAG_SAFE_MODE", FLAG_SAFE_MODE, "StateSample.flags: safe mode (rotors coast)"),
        ("FLAG_SATURATED", FLAG_SATURATED, "StateSample.flags: the held torque was limited"),
        (
            "TORQUE_SKIPPED",
            TORQUE_SKIPPED,
            "TorqueSample.flags: not computed (the state was rejected, or no reference to track)",
        ),
    ]
}

/// A field's element type and count: (`u64` or `f64` or a nested type, count; 1 for a
/// scalar).
fn element(f: &WireField) -> (&'static str, usize) {
    let scalar = |t: &'static str| (t, 1);
    match f.ty {
        "u64" | "f64" => scalar(f.ty),
        t if t.starts_with("[u64;") => ("u64", f.size / 8),
        t if t.starts_with("[f64;") => ("f64", f.size / 8),
        t => scalar(t),
    }
}

/// A doc comment on one line (markdown kept).
fn one_line(doc: &str) -> String {
    doc.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// Renders the contract in `format`.
pub fn render(format: Format) -> String {
    match format {
        Format::Json => json(),
        Format::Markdown => markdown(),
        Format::Python => python(),
        Format::C => c_header(),
    }
}

fn json() -> String {
    let types: Vec<serde_json::Value> = types()
        .iter()
        .map(|t| {
            serde_json::json!({
                "name": t.name,
                "type_name": t.type_name,
                "topic": t.topic,
                "size": t.size,
                "fields": t.fields.iter().map(|f| {
                    let (elem, count) = element(f);
                    serde_json::json!({
                        "name": f.name, "offset": f.offset, "size": f.size, "type": f.ty,
                        "element": elem, "count": count, "doc": one_line(f.doc),
                    })
                }).collect::<Vec<_>>(),
            })
        })
        .collect();
    let constants: serde_json::Map<String, serde_json::Value> =
        constants().into_iter().map(|(n, v, _)| (n.to_owned(), v.into())).collect();
    serde_json::to_string_pretty(&serde_json::json!({ "types": types, "constants": constants }))
        .unwrap_or_default()
        + "\n"
}

fn markdown() -> String {
    let mut md = String::new();
    for t in types() {
        let named = t.type_name.map_or(String::new(), |n| format!(", iceoryx2 type name `{n}`"));
        let topic = t.topic.map_or(String::new(), |n| format!(", topic `{n}`"));
        let _ = writeln!(md, "### `{}` ({} bytes{named}{topic})\n", t.name, t.size);
        let _ = writeln!(md, "{}\n", one_line(t.doc));
        md.push_str("| offset | field | type | meaning |\n|---|---|---|---|\n");
        for f in t.fields {
            let _ = writeln!(
                md,
                "| {} | `{}` | `{}` | {} |",
                f.offset,
                f.name,
                f.ty,
                one_line(f.doc).replace('|', "\\|")
            );
        }
        md.push('\n');
    }
    md.push_str("### Constants\n\n| name | value | meaning |\n|---|---|---|\n");
    for (n, v, d) in constants() {
        let _ = writeln!(md, "| `{n}` | {v} | {d} |");
    }
    let _ = writeln!(
        md,
        "\n### `controller.json` (`$ROTORLOOP_CONTROLLER_JSON`, `layout_version` {})\n",
        rotorloop_common::controller_json::CONTROLLER_JSON_VERSION
    );
    md.push_str(&rotorloop_common::controller_json::keys_markdown());
    let _ = writeln!(
        md,
        "\n### `summary.json` (`OUT/summary.json` of `rotorloop run`, `layout_version` {})\n\n\
         Every key of the report, its type and unit, and whether it is always there. `<name>` \
         stands for each key of a map, `[]` for each element of an array. Raised like \
         `controller.json`'s when a key is renamed, removed or changes meaning or unit; \
         `summary_json::check` holds a real file to this table (a key added is a row of \
         `common/src/summary_json.rs`).\n",
        rotorloop_common::summary_json::SUMMARY_JSON_VERSION
    );
    md.push_str(&rotorloop_common::summary_json::keys_markdown());
    md
}

const GENERATED: &str = "Generated by `rotorloop wire --format";

fn python() -> String {
    let mut py = format!(
        "\"\"\"rotorloop's wire samples as ctypes Structures, for iceoryx2's Python binding.\n\n\
         {GENERATED} python` from the Rust types: do not edit; the\n\
         layout test compares this file with that output and every offset with Rust's.\n\
         docs/wire.md says what each field means and how to take part in a loop.\n\"\"\"\n\n\
         import ctypes\n\n"
    );
    for (n, v, d) in constants() {
        let _ = writeln!(py, "{n} = {v}  # {d}");
    }
    py.push_str(
        "\n\ndef service_name(domain: str, topic: str) -> str:\n    \
         \"\"\"The iceoryx2 service (publish-subscribe and event) of `topic` in `domain`.\"\"\"\n    \
         return f\"rotorloop/{domain}/{topic}\"\n",
    );
    for t in types() {
        let _ = write!(
            py,
            "\n\nclass {}(ctypes.Structure):\n    \"\"\"{}\"\"\"\n\n",
            t.name,
            one_line(t.doc)
        );
        py.push_str("    _fields_ = [\n");
        for f in t.fields {
            let ty = match element(f) {
                ("u64", 1) => "ctypes.c_uint64".to_owned(),
                ("f64", 1) => "ctypes.c_double".to_owned(),
                ("u64", n) => format!("ctypes.c_uint64 * {n}"),
                ("f64", n) => format!("ctypes.c_double * {n}"),
                (nested, _) => nested.to_owned(),
            };
            let _ = writeln!(py, "        (\"{}\", {ty}),", f.name);
        }
        py.push_str("    ]\n");
        if let Some(n) = t.type_name {
            let _ = write!(
                py,
                "\n    @staticmethod\n    def type_name() -> str:\n        \
                 \"\"\"The iceoryx2 type name: it carries the layout version.\"\"\"\n        \
                 return \"{n}\"\n"
            );
        }
    }
    let topics: Vec<String> = types()
        .iter()
        .filter_map(|t| t.topic.map(|topic| format!("\"{topic}\": {}", t.name)))
        .collect();
    let _ = writeln!(py, "\n\nTOPICS = {{{}}}", topics.join(", "));
    py
}

fn c_header() -> String {
    let mut h = format!(
        "/* rotorloop's wire samples as C structs.\n *\n * {GENERATED} c` from the Rust types: \
         do not edit; the layout\n * test compares this file with that output and compiles \
         it. docs/wire.md says\n * what each field means and how to take part in a loop. \
         */\n#ifndef ROTORLOOP_WIRE_H\n#define ROTORLOOP_WIRE_H\n\n#include <stddef.h>\n\
         #include <stdint.h>\n\n/* C11's _Static_assert is C++'s static_assert: the header \
         compiles as either. */\n#ifdef __cplusplus\n#define ROTORLOOP_STATIC_ASSERT \
         static_assert\n#else\n#define ROTORLOOP_STATIC_ASSERT _Static_assert\n#endif\n\n"
    );
    for (n, v, d) in constants() {
        let _ = writeln!(h, "#define ROTORLOOP_{n} UINT64_C({v}) /* {d} */");
    }
    for t in types() {
        let _ = write!(h, "\n/* {} */\ntypedef struct {} {{\n", one_line(t.doc), t.name);
        for f in t.fields {
            let decl = match element(f) {
                ("u64", 1) => format!("uint64_t {}", f.name),
                ("f64", 1) => format!("double {}", f.name),
                ("u64", n) => format!("uint64_t {}[{n}]", f.name),
                ("f64", n) => format!("double {}[{n}]", f.name),
                (nested, _) => format!("{nested} {}", f.name),
            };
            let _ = writeln!(h, "    {decl}; /* {} */", one_line(f.doc).replace("*/", "* /"));
        }
        let _ = writeln!(h, "}} {};", t.name);
        if let Some(n) = t.type_name {
            let _ = writeln!(h, "#define ROTORLOOP_{}_TYPE_NAME \"{n}\"", t.name.to_uppercase());
        }
        let _ = writeln!(
            h,
            "ROTORLOOP_STATIC_ASSERT(sizeof({}) == {}, \"{} size\");",
            t.name, t.size, t.name
        );
        for f in t.fields {
            let _ = writeln!(
                h,
                "ROTORLOOP_STATIC_ASSERT(offsetof({}, {}) == {}, \"{}.{} offset\");",
                t.name, f.name, f.offset, t.name, f.name
            );
        }
    }
    h.push_str("\n#endif /* ROTORLOOP_WIRE_H */\n");
    h
}

/// `rotorloop wire`: prints the contract.
pub fn run(a: &WireArgs) -> anyhow::Result<()> {
    print!("{}", render(a.format));
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each type's fields follow one another without a gap and fill it exactly: a field
    /// left out of a table, or padding a C compiler would place elsewhere, shows here.
    #[test]
    fn the_fields_tile_each_sample() {
        for t in types() {
            let mut end = 0;
            for f in t.fields {
                assert_eq!(f.offset, end, "{}.{} starts at {} not {end}", t.name, f.name, f.offset);
                end += f.size;
            }
            assert_eq!(end, t.size, "{} fields end at {end}, the type is {}", t.name, t.size);
        }
    }

    /// Every field is a u64, an f64, an array of them, or the nested send cost: what C
    /// and Python can declare with the same layout.
    #[test]
    fn every_field_has_a_c_and_python_type() {
        for t in types() {
            for f in t.fields {
                let (elem, count) = element(f);
                let ok = matches!(elem, "u64" | "f64") || (elem == "SendCost" && count == 1);
                assert!(ok, "{}.{}: {}", t.name, f.name, f.ty);
            }
        }
    }
}
