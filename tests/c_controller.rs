//! The C controller (`examples/c/controller.c`, the geometric PID against rotorloop's C
//! API `include/rotorloop.h`) under `rotorloop run --controller-cmd`: built here with
//! `make -C examples/c` against the `librotorloop_c.so` cargo built for these tests (the
//! C API crate is a dev-dependency, so `cargo test --workspace` alone builds it), its
//! lockstep traces are the built-in law's byte for byte (with and without actuator
//! limits), a `kill -9` of it is restarted and resumes bumplessly, and a real-time run
//! completes. Skipped with a message where `cc` or `make` is missing.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Mutex;
use std::time::Duration;

use crate::common::harness::{Harness, json, ok};

const LIMIT: Duration = Duration::from_secs(300);
const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// `examples/c/controller`, built once by `make` against this build's library, or `None`
/// (and a message) where `cc` or `make` is missing.
pub(crate) fn c_controller() -> Option<PathBuf> {
    static BUILT: Mutex<Option<PathBuf>> = Mutex::new(None);
    let mut built = BUILT.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(p) = built.as_ref() {
        return Some(p.clone());
    }
    for tool in ["cc", "make"] {
        if Command::new(tool).arg("--version").output().is_err() {
            eprintln!("skipped: {tool} is not installed here");
            return None;
        }
    }
    // The test binary lies in target/<profile>/deps/, beside the dev-dependency's cdylib.
    let exe = std::env::current_exe().expect("the test binary");
    let libdir = exe.parent().expect("its directory").to_path_buf();
    assert!(
        libdir.join("librotorloop_c.so").exists(),
        "{} has no librotorloop_c.so (rotorloop-capi is a dev-dependency)",
        libdir.display()
    );
    let dir = Path::new(ROOT).join("examples/c");
    let o = Command::new("make")
        .arg("-C")
        .arg(&dir)
        .arg(format!("LIBDIR={}", libdir.display()))
        // Always against this build's library: the binary may have been linked against
        // another (the bench links it against target/release).
        .arg("-B")
        .output()
        .expect("make");
    assert!(
        o.status.success(),
        "make -C examples/c: {}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    let exe = dir.join("controller");
    *built = Some(exe.clone());
    Some(exe)
}

/// `rotorloop run` of `scenario` for `duration` s in `mode` into `h/name`, with `extra`
/// arguments; the run must succeed.
fn run(
    h: &Harness,
    name: &str,
    scenario: &str,
    mode: &str,
    duration: &str,
    extra: &[&str],
) -> PathBuf {
    let out = h.path(name);
    let domain = format!("{}{name}", h.domain);
    let mut args = vec!["run", "--scenario", scenario, "--mode", mode];
    args.extend(["--duration", duration, "--quiet", "--no-mcap", "--domain", &domain]);
    args.extend(extra);
    args.extend(["--out", out.to_str().expect("utf8")]);
    ok(&h.rotorloop(&args, LIMIT));
    out
}

fn read(d: &Path) -> Vec<u8> {
    std::fs::read(d.join("trace.csv")).expect("trace")
}

/// Lockstep, the C law against the Rust law: the same `trace.csv`, byte for byte, on
/// the paper's sinusoid and on a scenario whose actuators saturate (anti-windup).
#[test]
fn the_c_controller_gives_the_built_in_trace_byte_for_byte() {
    let Some(c) = c_controller() else { return };
    let cmd = c.to_str().expect("utf8");
    let h = Harness::new("cclock");
    for (i, scenario) in ["paper-sinusoid", "saturation-antiwindup"].into_iter().enumerate() {
        let rust = run(&h, &format!("r{i}"), scenario, "lockstep", "4", &[]);
        let ext = run(&h, &format!("c{i}"), scenario, "lockstep", "4", &["--controller-cmd", cmd]);
        assert!(read(&rust) == read(&ext), "{scenario}: the C controller's trace differs");
        let s = json(&ext.join("summary.json"));
        assert_eq!(s["faults"].as_array().map(Vec::len), Some(0), "{}", s["faults"]);
    }
    h.assert_no_leftovers();
}

/// `kill -9` of the C controller mid-run (the fault schedule): the launcher restarts it,
/// it resumes from its state file, and the trace is the uninterrupted one byte for byte.
#[test]
fn a_killed_c_controller_is_restarted_and_resumes_bumplessly() {
    let Some(c) = c_controller() else { return };
    let cmd = c.to_str().expect("utf8");
    let h = Harness::new("cckill");
    // A fault's times are wall-clock seconds after tick 0, and an idle machine ran 30
    // simulated seconds of lockstep in under a second (the kill at 1 s never came): the
    // kill comes early in a run of 60.
    let calm = run(&h, "calm", "paper-sinusoid", "lockstep", "60", &["--controller-cmd", cmd]);
    let fault = "controller:kill@0.2:restart@0.4";
    let extra = ["--controller-cmd", cmd, "--fault", fault];
    let killed = run(&h, "kill", "paper-sinusoid", "lockstep", "60", &extra);
    let s = json(&killed.join("summary.json"));
    assert_eq!(s["faults"].as_array().map(Vec::len), Some(1), "{}", s["faults"]);
    assert!(read(&calm) == read(&killed), "the trace after the restart differs");
    h.assert_no_leftovers();
}

/// A real-time run with the C controller completes, its stamps fill the stage breakdown.
#[test]
fn the_c_controller_completes_a_real_time_run() {
    let Some(c) = c_controller() else { return };
    let h = Harness::new("ccrt");
    let extra = ["--controller-cmd", c.to_str().expect("utf8")];
    let out = run(&h, "rt", "paper-sinusoid", "realtime", "3", &extra);
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true, "{s}");
    let compute = &s["hops"]["controller_compute"];
    assert!(compute["count"].as_u64().is_some_and(|n| n > 2000), "{compute}");
    let law =
        s["stages"].as_array().and_then(|st| st.iter().find(|x| x["stage"] == "controller_law"));
    assert!(law.is_some_and(|l| l["p50"].as_f64().is_some_and(|p| p > 0.0)), "{law:?}");
    h.assert_no_leftovers();
}

/// A second run into the same `--out` starts its controller with an empty state
/// directory: the C controller (which resumes from `ROTORLOOP_STATE_DIR/pid.state` when
/// it finds one) does not take the first run's state as its own, and the second run's
/// trace is the first's byte for byte. With the directory kept, it resumed after the
/// first run's last tick and answered none of the second run's states.
#[test]
fn a_new_run_into_the_same_out_does_not_resume_the_last_runs_controller_state() {
    let Some(c) = c_controller() else { return };
    let cmd = c.to_str().expect("utf8");
    let h = Harness::new("ccstate");
    let first = run(&h, "same", "paper-sinusoid", "lockstep", "2", &["--controller-cmd", cmd]);
    let trace = read(&first);
    assert!(
        first.join("controller-state/pid.state").exists(),
        "the C controller keeps its state there"
    );
    let again = run(&h, "same", "paper-sinusoid", "lockstep", "2", &["--controller-cmd", cmd]);
    let s = json(&again.join("summary.json"));
    assert_eq!(s["faults"].as_array().map(Vec::len), Some(0), "{}", s["faults"]);
    assert!(read(&again) == trace, "the second run's trace differs");
    h.assert_no_leftovers();
}

/// The incidents of a run with an outside controller are costed: the C controller keeps
/// no flight record of its own, and the counterfactual takes its answers from the
/// plant's record of what it received (before, `law_reproduced` was [0, 0] and every
/// cost "not computed").
#[test]
fn the_incidents_of_a_run_with_an_outside_controller_are_costed() {
    let Some(c) = c_controller() else { return };
    let cmd = c.to_str().expect("utf8");
    let h = Harness::new("cccost");
    let extra = ["--controller-cmd", cmd, "--fault", "controller:kill@1:restart@1.2"];
    let out = run(&h, "rt", "paper-sinusoid", "realtime", "3", &extra);
    let s = json(&out.join("summary.json"));
    let reproduced = &s["incidents"]["law_reproduced"];
    let [same, computed] = [0, 1].map(|i| reproduced[i].as_u64().unwrap_or(0));
    assert!(computed > 1000 && same == computed, "{reproduced}");
    // The kill's incident has its cost.
    let fault = &s["faults"][0];
    assert!(fault["peak_deviation_deg"].as_f64().is_some_and(|p| p > 0.0), "{fault}");
    let md = std::fs::read_to_string(out.join("incidents.md")).expect("incidents.md");
    assert!(!md.contains("no record of the controller's answers"), "{md}");
    assert!(s["incidents"]["costed"].as_u64().is_some_and(|n| n > 0), "{}", s["incidents"]);
    h.assert_no_leftovers();
}

/// The thin C++ header (`include/rotorloop.hpp`) compiles with the C API's headers and
/// turns a refused call into a `rotorloop::error` carrying the status. Skipped with a
/// message without `c++`.
#[test]
fn the_cpp_header_compiles_and_throws_the_status_of_a_refusal() {
    if c_controller().is_none() {
        return;
    }
    if Command::new("c++").arg("--version").output().is_err() {
        eprintln!("skipped: c++ is not installed here");
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let src = dir.path().join("t.cpp");
    std::fs::write(
        &src,
        "#include \"rotorloop.hpp\"\nint main() {\n  try { rotorloop::controller c(\"no_underscores\"); }\n  \
         catch (const rotorloop::error &e) {\n    return e.status() == ROTORLOOP_ERR_ARGUMENT \
         && std::string(e.what()).find(\"no_underscores\") != std::string::npos ? 0 : 1;\n  }\n  \
         return 2;\n}\n",
    )
    .expect("write");
    let libdir = std::env::current_exe().expect("exe").parent().expect("dir").to_path_buf();
    let exe = dir.path().join("t");
    let o = Command::new("c++")
        .args(["-std=c++17", "-Wall", "-Wextra", "-Werror", "-I"])
        .arg(Path::new(ROOT).join("include"))
        .arg(&src)
        .arg(format!("-L{}", libdir.display()))
        .args(["-lrotorloop_c", &format!("-Wl,-rpath,{}", libdir.display()), "-o"])
        .arg(&exe)
        .output()
        .expect("c++");
    assert!(o.status.success(), "c++: {}", String::from_utf8_lossy(&o.stderr));
    let status = Command::new(&exe).status().expect("run");
    assert_eq!(status.code(), Some(0), "the refusal was not a rotorloop::error with its status");
}
