//! The published wire contract against the Rust types: `docs/wire.md`'s tables, the Python
//! module and the C header in the repository are exactly `rotorloop wire`'s output, and
//! Python's ctypes and a C compiler lay every sample out at Rust's sizes and offsets. A
//! field moved in any of the three fails here.

use std::path::Path;
use std::process::Command;

use rotorloop::export::wire::{Format, render, types};

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

fn read(path: &str) -> String {
    std::fs::read_to_string(Path::new(ROOT).join(path)).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// `(type, field) → offset` and `type → size` as Rust has them, one line each:
/// `StateSample.tick 0`, `StateSample 520`.
fn rust_layout() -> Vec<String> {
    let mut lines = Vec::new();
    for t in types() {
        lines.push(format!("{} {}", t.name, t.size));
        for f in t.fields {
            lines.push(format!("{}.{} {}", t.name, f.name, f.offset));
        }
    }
    lines
}

/// The committed files are the generator's output, so what they say is what Rust says.
#[test]
fn the_published_layouts_are_the_rust_layouts() {
    let generated = |f| render(f);
    assert!(
        read("python/rotorloop_wire.py") == generated(Format::Python),
        "python/rotorloop_wire.py differs from `rotorloop wire --format python`: regenerate it"
    );
    assert!(
        read("include/rotorloop_wire.h") == generated(Format::C),
        "include/rotorloop_wire.h differs from `rotorloop wire --format c`: regenerate it"
    );
    assert!(
        read("docs/wire.md").contains(&generated(Format::Markdown)),
        "docs/wire.md's tables differ from `rotorloop wire --format markdown`: paste them in"
    );
    // The JSON names every field with its offset.
    let j: serde_json::Value = serde_json::from_str(&generated(Format::Json)).expect("JSON");
    let state = &j["types"][1];
    assert_eq!(state["name"], "StateSample");
    assert_eq!(state["type_name"], "rotorloop::StateSample_v6");
    assert_eq!(state["fields"][0]["name"], "tick");
    assert_eq!(state["size"], 520);
}

/// Python's ctypes lays the module's Structures out at Rust's sizes and offsets, and
/// their type names are the Rust types'. Skipped with a message without `python3`.
#[test]
fn python_ctypes_agrees_with_rust_on_every_offset() {
    let script = r#"
import ctypes, sys
sys.path.insert(0, sys.argv[1])
import rotorloop_wire as w
for name in ["SendCost", "StateSample", "ReferenceSample", "TorqueSample"]:
    t = getattr(w, name)
    print(name, ctypes.sizeof(t))
    for f, _ in t._fields_:
        print(f"{name}.{f}", getattr(t, f).offset)
for name, t in w.TOPICS.items():
    print("topic", name, t.type_name())
"#;
    let out = match Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(Path::new(ROOT).join("python"))
        .output()
    {
        Ok(o) => o,
        Err(e) => {
            eprintln!("skipped: python3 cannot be run here ({e})");
            return;
        }
    };
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8_lossy(&out.stdout);
    let (topics, layout): (Vec<&str>, Vec<&str>) =
        text.lines().partition(|l| l.starts_with("topic "));
    assert_eq!(layout, rust_layout());
    let want: Vec<String> = types()
        .iter()
        .filter_map(|t| t.topic.zip(t.type_name).map(|(topic, n)| format!("topic {topic} {n}")))
        .collect();
    assert_eq!(topics, want);
}

/// A C compiler lays the header's structs out at Rust's sizes and offsets (the header's
/// own static asserts, and a program printing every `offsetof`). Skipped with a message
/// without `cc`.
#[test]
fn a_c_compiler_agrees_with_rust_on_every_offset() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut c =
        String::from("#include <stdio.h>\n#include \"rotorloop_wire.h\"\nint main(void) {\n");
    for t in types() {
        c.push_str(&format!("    printf(\"{} %zu\\n\", sizeof({}));\n", t.name, t.name));
        for f in t.fields {
            c.push_str(&format!(
                "    printf(\"{}.{} %zu\\n\", offsetof({}, {}));\n",
                t.name, f.name, t.name, f.name
            ));
        }
    }
    c.push_str("    return 0;\n}\n");
    let src = dir.path().join("layout.c");
    let exe = dir.path().join("layout");
    std::fs::write(&src, c).expect("write");
    let include = Path::new(ROOT).join("include");
    let built = match Command::new("cc")
        .args(["-std=c11", "-Wall", "-Wextra", "-Werror", "-I"])
        .arg(&include)
        .arg(&src)
        .arg("-o")
        .arg(&exe)
        .output()
    {
        Ok(o) => o,
        Err(e) => {
            eprintln!("skipped: no C compiler (cc) here ({e})");
            return;
        }
    };
    assert!(built.status.success(), "{}", String::from_utf8_lossy(&built.stderr));
    let out = Command::new(&exe).output().expect("run");
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(text.lines().collect::<Vec<_>>(), rust_layout());
}
