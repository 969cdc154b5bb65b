//! The code's shape, as the README's Architecture section promises it: every role's process shell
//! (`*/src/process/mod.rs`) is under 80 lines. No function is over 100 lines: clippy's
//! `too_many_lines` enforces that (workspace lints in `Cargo.toml`, the threshold in
//! `clippy.toml`), and a test here checks it stays switched on. No crate has an import
//! circle between its modules, and the root crate none between its rooms (`run`, `study`,
//! `pipeline`, …).

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

/// The modules of one crate that `path`'s code (comments and its `#[cfg(test)]` part left
/// out) names through `crate::`: each the longest known module prefix of the path.
fn imports(text: &str, modules: &[Vec<String>]) -> Vec<Vec<String>> {
    let code = text.split("#[cfg(test)]").next().unwrap_or_default();
    let mut found = Vec::new();
    for line in code.lines().filter(|l| !l.trim_start().starts_with("//")) {
        for (at, _) in line.match_indices("crate::") {
            let rest = &line[at + "crate::".len()..];
            let mut paths: Vec<Vec<String>> = Vec::new();
            if let Some(group) = rest.strip_prefix('{') {
                let group = group.split('}').next().unwrap_or_default();
                paths.extend(group.split(',').map(|p| path_of(p.trim())));
            } else {
                paths.push(path_of(rest));
            }
            for p in paths {
                if let Some(m) =
                    (1..=p.len()).rev().map(|k| &p[..k]).find(|m| modules.contains(&m.to_vec()))
                {
                    found.push(m.to_vec());
                }
            }
        }
    }
    found
}

fn path_of(s: &str) -> Vec<String> {
    s.split(|c: char| !(c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_' || c == ':'))
        .next()
        .unwrap_or_default()
        .split("::")
        .filter(|p| !p.is_empty())
        .map(str::to_string)
        .collect()
}

/// Every module of the crate under `src` with its file's text.
fn modules_of(src: &Path) -> Vec<(Vec<String>, String)> {
    let mut out = Vec::new();
    let mut dirs = vec![src.to_path_buf()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).expect("a source folder").flatten() {
            let path = entry.path();
            if path.is_dir() {
                if path.file_name().is_some_and(|n| n != "bin") {
                    dirs.push(path);
                }
                continue;
            }
            if path.extension().is_none_or(|e| e != "rs") {
                continue;
            }
            let rel = path.strip_prefix(src).expect("under src").with_extension("");
            let mut m: Vec<String> = rel.iter().map(|p| p.to_string_lossy().into_owned()).collect();
            if matches!(m.last().map(String::as_str), Some("mod" | "lib" | "main")) {
                m.pop();
            }
            out.push((m, std::fs::read_to_string(&path).expect("a source file")));
        }
    }
    out
}

/// A cycle of imports between the modules of one crate, if there is one.
fn import_cycle(src: &Path) -> Option<Vec<String>> {
    cycle_among(modules_of(src))
}

/// A cycle of imports between the crate's rooms (its top-level modules, each with
/// everything inside it), if there is one: `run` importing `study` while `study` imports
/// `run` is a circle even when no two files import each other.
fn room_cycle(src: &Path) -> Option<Vec<String>> {
    let mut rooms: Vec<(Vec<String>, String)> = Vec::new();
    for (m, text) in modules_of(src) {
        let room: Vec<String> = m.into_iter().take(1).collect();
        match rooms.iter_mut().find(|(r, _)| *r == room) {
            Some((_, all)) => {
                // Each file's test part stays out, as in `imports`.
                all.push_str(text.split("#[cfg(test)]").next().unwrap_or_default());
                all.push('\n');
            }
            None => {
                rooms.push((room, text.split("#[cfg(test)]").next().unwrap_or_default().into()))
            }
        }
    }
    cycle_among(rooms)
}

fn cycle_among(mods: Vec<(Vec<String>, String)>) -> Option<Vec<String>> {
    let names: Vec<Vec<String>> = mods.iter().map(|(m, _)| m.clone()).collect();
    let edges: Vec<Vec<usize>> = mods
        .iter()
        .map(|(m, text)| {
            let mut to: Vec<usize> = imports(text, &names)
                .iter()
                // A module's own ancestors and descendants are not an import circle.
                .filter(|t| !m.starts_with(t) && !t.starts_with(m))
                .filter_map(|t| names.iter().position(|n| n == t))
                .collect();
            to.dedup();
            to
        })
        .collect();
    // Depth-first search with colours: 1 on the stack, 2 done.
    fn visit(
        u: usize,
        edges: &[Vec<usize>],
        colour: &mut [u8],
        stack: &mut Vec<usize>,
    ) -> Option<Vec<usize>> {
        colour[u] = 1;
        stack.push(u);
        for &v in &edges[u] {
            if colour[v] == 1 {
                let from = stack.iter().position(|s| *s == v).expect("on the stack");
                return Some([&stack[from..], &[v]].concat());
            }
            if colour[v] == 0 {
                if let Some(c) = visit(v, edges, colour, stack) {
                    return Some(c);
                }
            }
        }
        stack.pop();
        colour[u] = 2;
        None
    }
    let mut colour = vec![0; mods.len()];
    (0..mods.len())
        .find_map(|u| {
            (colour[u] == 0).then(|| visit(u, &edges, &mut colour, &mut Vec::new())).flatten()
        })
        .map(|c| c.iter().map(|&i| format!("crate::{}", names[i].join("::"))).collect())
}

#[test]
fn no_crate_has_an_import_circle_between_its_modules() {
    for src in [
        "src",
        "common/src",
        "plant/src",
        "controller/src",
        "reference/src",
        "monitor/src",
        "link/src",
    ] {
        if let Some(cycle) = import_cycle(&root().join(src)) {
            panic!("{src}: an import circle: {}", cycle.join(" → "));
        }
    }
}

#[test]
fn the_rooms_of_the_root_crate_have_no_import_circle() {
    // The root crate's rooms (run, study, pipeline, sim, export, observe, baseline, cli):
    // the launcher calls the post-run pipeline, the bench calls the launcher, and nothing
    // beneath calls back up.
    if let Some(cycle) = room_cycle(&root().join("src")) {
        panic!("src: an import circle between rooms: {}", cycle.join(" → "));
    }
}

#[test]
fn the_layers_of_common_have_no_import_circle() {
    // common's top-level modules are layers (docs/architecture.md): the maths and the
    // scenario below the wire samples, the wire below IPC and the flight records, the role
    // harness on top. The wire's one import from IPC (the reference's lead) was such a
    // circle until the constant moved to the wire, where the contract states it.
    if let Some(cycle) = room_cycle(&root().join("common/src")) {
        panic!("common: an import circle between modules: {}", cycle.join(" → "));
    }
}

#[test]
fn the_room_check_finds_a_circle_that_no_two_files_make() {
    let dir = std::env::temp_dir().join(format!("rotorloop-rooms-{}", std::process::id()));
    for room in ["run", "study"] {
        std::fs::create_dir_all(dir.join(room)).expect("a temporary folder");
    }
    let write = |p: &str, t: &str| std::fs::write(dir.join(p), t).expect("write");
    write("lib.rs", "pub mod run;\npub mod study;\n");
    write("run/mod.rs", "pub mod launch;\npub mod sched;\n");
    write("run/launch.rs", "fn f() { crate::study::incidents::explain(); }\n");
    write("run/sched.rs", "pub const PERIOD_NS: u64 = 1;\n");
    write("study/mod.rs", "pub mod incidents;\n");
    write("study/incidents.rs", "fn g() -> u64 { crate::run::sched::PERIOD_NS }\n");
    assert_eq!(import_cycle(&dir), None, "no two files import each other");
    let cycle = room_cycle(&dir).expect("run → study → run");
    assert_eq!(cycle.len(), 3, "{cycle:?}");
    write("study/incidents.rs", "fn g() -> u64 { 1 }\n");
    assert_eq!(room_cycle(&dir), None, "study no longer imports run");
    std::fs::remove_dir_all(&dir).expect("remove");
}

#[test]
fn the_circle_check_finds_a_circle() {
    let dir = std::env::temp_dir().join(format!("rotorloop-circle-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("room")).expect("a temporary folder");
    let write = |p: &str, t: &str| std::fs::write(dir.join(p), t).expect("write");
    write("lib.rs", "pub mod a;\npub mod room;\n");
    write("a.rs", "use crate::room::b::B;\n// crate::nothing\n");
    write("room/mod.rs", "pub mod b;\n");
    write(
        "room/b.rs",
        "pub struct B;\nfn f() { crate::a::g(); }\n#[cfg(test)]\nmod t { use crate::a; }\n",
    );
    let cycle = import_cycle(&dir).expect("a → room::b → a");
    assert_eq!(cycle.len(), 3, "{cycle:?}");
    write("room/b.rs", "pub struct B;\n#[cfg(test)]\nmod t { use crate::a; }\n");
    assert_eq!(import_cycle(&dir), None, "a test module's import is not a circle");
    std::fs::remove_dir_all(&dir).expect("remove");
}

/// A role's name is written as a string only where it is parsed or written to a file
/// (docs/architecture.md): inside the code a role is a `Role` (`common::graph`), a
/// process of a run a `Member` (`run::member`). Counted in every crate's sources, their
/// tests and comments left out: at most 20, and each listed when over.
#[test]
fn role_names_are_strings_only_where_parsed_or_written() {
    let roles = ["\"plant\"", "\"reference\"", "\"controller\"", "\"monitor\""];
    let mut found = Vec::new();
    for krate in [".", "common", "plant", "controller", "reference", "monitor", "link", "capi"] {
        for (module, text) in modules_of(&root().join(krate).join("src")) {
            let code = text.split("#[cfg(test)]").next().unwrap_or_default();
            for line in code.lines().filter(|l| !l.trim_start().starts_with("//")) {
                for r in roles.iter().filter(|r| line.contains(*r)) {
                    found.push(format!("{krate}/{}: {r} in {}", module.join("/"), line.trim()));
                }
            }
        }
    }
    assert!(found.len() <= 20, "{} role-name literals:\n{}", found.len(), found.join("\n"));
}
