//! The code's shape, as `docs/architecture.md` promises it: every role's process shell
//! (`*/src/process/mod.rs`) is under 80 lines. No function is over 100 lines: clippy's
//! `too_many_lines` enforces that (workspace lints in `Cargo.toml`, the threshold in
//! `clippy.toml`), and the last test here checks it stays switched on.

use std::path::Path;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn process_shells_stay_under_80_lines() {
    for role in ["plant", "controller", "reference", "monitor"] {
        let path = root().join(role).join("src/process/mod.rs");
        let lines = std::fs::read_to_string(&path).expect("a source file").lines().count();
        assert!(lines < 80, "{} has {lines} lines; a shell stays under 80", path.display());
    }
}

#[test]
fn clippy_refuses_functions_over_100_lines() {
    let clippy = std::fs::read_to_string(root().join("clippy.toml")).expect("clippy.toml");
    assert!(
        clippy.lines().any(|l| l.replace(' ', "") == "too-many-lines-threshold=100"),
        "clippy.toml sets too-many-lines-threshold = 100:\n{clippy}"
    );
    let manifest = std::fs::read_to_string(root().join("Cargo.toml")).expect("Cargo.toml");
    let lints = manifest.split("[workspace.lints.clippy]").nth(1).expect("clippy lints");
    let lints = lints.split("\n[").next().unwrap_or_default();
    assert!(
        lints.lines().any(|l| l.replace(' ', "") == "too_many_lines=\"warn\""),
        "[workspace.lints.clippy] has too_many_lines = \"warn\" (CI denies warnings):\n{lints}"
    );
}
