//! The files `rotorloop sim`, `paper`, `gains` and `montecarlo` promise, checked for
//! presence and form.

use std::path::Path;
use std::process::Command;

fn rotorloop(args: &[&str]) -> String {
    let o =
        Command::new(env!("CARGO_BIN_EXE_rotorloop")).args(args).output().expect("run rotorloop");
    assert!(o.status.success(), "{args:?} failed: {}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// A PNG's width and height from its IHDR chunk, after checking the signature.
fn png_size(path: &Path) -> (u32, u32) {
    let b = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert_eq!(&b[..8], b"\x89PNG\r\n\x1a\n", "{} is not a PNG", path.display());
    assert_eq!(&b[12..16], b"IHDR");
    let be = |i: usize| u32::from_be_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
    (be(16), be(20))
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).expect("read json")).expect("valid json")
}

const CONTRACT_COLUMNS: &str = "t,R11,R12,R13,R21,R22,R23,R31,R32,R33,\
Rd11,Rd12,Rd13,Rd21,Rd22,Rd23,Rd31,Rd32,Rd33,W1,W2,W3,Wd1,Wd2,Wd3,Wr1,Wr2,Wr3,\
u1,u2,u3,tau1,tau2,tau3,err_deg,werr,h1,h2,h3";

#[test]
fn sim_writes_trace_summary_and_figures() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("run");
    let stdout = rotorloop(&[
        "sim",
        "--scenario",
        "paper-sinusoid",
        "--duration",
        "2",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    assert!(stdout.contains("attitude error") && stdout.contains("ticks/s"), "{stdout}");

    let trace = std::fs::read_to_string(out.join("trace.csv")).expect("trace");
    let mut lines = trace.lines();
    let header = lines.next().expect("header");
    assert!(header.starts_with(CONTRACT_COLUMNS), "{header}");
    let ncol = header.split(',').count();
    let rows: Vec<&str> = lines.collect();
    assert_eq!(rows.len(), 2001, "ticks 0..=2000");
    for r in &rows {
        assert_eq!(r.split(',').count(), ncol);
        for v in r.split(',') {
            assert!(v.parse::<f64>().is_ok(), "not a number: {v}");
        }
    }

    let s = json(&out.join("summary.json"));
    for key in [
        "ticks",
        "err_deg_final",
        "momentum_drift_rel_max",
        "wall_seconds",
        "ticks_per_second",
        "scenario",
        "effort",
        "energy_residual_max_abs",
    ] {
        assert!(s.get(key).is_some(), "summary.json lacks {key}: {s}");
    }
    assert_eq!(s["ticks"], 2000);
    assert_eq!(s["scenario"]["reference"]["torque"]["profile"], "sinusoid");
    assert_eq!(s["scenario"]["run"]["duration_s"], 2.0);
    for f in [
        "attitude_entries.png",
        "attitude_error.png",
        "control_effort.png",
        "rotor_rates.png",
        "momentum_drift.png",
        "energy_residual.png",
    ] {
        let (w, h) = png_size(&out.join(f));
        assert!(w >= 800 && h >= 500, "{f}: {w}x{h}");
    }
}

#[test]
fn sim_open_loop_external_and_trace_every() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("ol");
    rotorloop(&[
        "sim",
        "--scenario",
        "paper-zero",
        "--duration",
        "1",
        "--open-loop",
        "0.1,-0.2,0.3",
        "--trace-every",
        "10",
        "--no-figures",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    let trace = std::fs::read_to_string(out.join("trace.csv")).expect("trace");
    assert_eq!(trace.lines().count(), 1 + 101, "header + ticks 0,10,…,1000");
    let s = json(&out.join("summary.json"));
    assert_eq!(s["open_loop"], serde_json::json!([0.1, -0.2, 0.3]));
    assert!(s["effort"].is_null());
    // u column holds the open-loop torque
    let row: Vec<f64> =
        trace.lines().nth(1).expect("row").split(',').map(|v| v.parse().expect("f64")).collect();
    assert_eq!(&row[28..31], &[0.1, -0.2, 0.3]);

    let ext = dir.path().join("ext");
    rotorloop(&[
        "sim",
        "--scenario",
        "paper-constant",
        "--duration",
        "1",
        "--actuation",
        "external",
        "--no-figures",
        "--out",
        ext.to_str().expect("utf8"),
    ]);
    let s = json(&ext.join("summary.json"));
    assert_eq!(s["actuation"], "external");
    assert!(s["energy_residual_max_abs"].is_null(), "no rotor work for a gas-jet body");
}

#[test]
fn gains_reports_appendix_a_and_a_verdict() {
    let text = rotorloop(&["gains", "--scenario", "paper-zero"]);
    for needle in [
        "6.849",
        "2.0048",
        "1.419",
        "1.42",
        "NOT met",
        "verdict: sufficient bound not met; linearisation Hurwitz; expect convergence",
        "mode m = 1.9000",
    ] {
        assert!(text.contains(needle), "missing `{needle}` in:\n{text}");
    }
    let j: serde_json::Value =
        serde_json::from_str(&rotorloop(&["gains", "--json"])).expect("json");
    assert_eq!(j["modes"].as_array().expect("modes").len(), 3);
}

#[test]
fn montecarlo_writes_runs_summary_and_histograms() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("mc");
    rotorloop(&[
        "montecarlo",
        "--runs",
        "6",
        "--seed",
        "3",
        "--duration",
        "2",
        "--out",
        out.to_str().expect("utf8"),
    ]);
    let csv = std::fs::read_to_string(out.join("runs.csv")).expect("runs.csv");
    assert_eq!(csv.lines().count(), 7);
    let s = json(&out.join("summary.json"));
    assert_eq!(s["runs"], 6);
    assert!(s["fraction_converged"].is_number() && s["worst_final_err_deg"].is_number());
    png_size(&out.join("final_error_histogram.png"));
    png_size(&out.join("initial_error_histogram.png"));
}

/// `paper` runs each scenario through the four processes (report, latency files) and in
/// process (effort comparison), and writes one report.
#[test]
fn paper_runs_the_three_scenarios_and_writes_a_report() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("paper");
    rotorloop(&["paper", "--duration", "1", "--out", out.to_str().expect("utf8")]);
    let report = std::fs::read_to_string(out.join("report.md")).expect("report");
    for name in ["paper-zero", "paper-constant", "paper-sinusoid"] {
        assert!(report.contains(name));
        let run = json(&out.join(name).join("summary.json"));
        assert_eq!(run["mode"], "realtime");
        assert_eq!(run["completed"], true);
        assert!(out.join(name).join("sense_to_actuate.hgrm").exists());
        assert!(out.join(name).join("sim").join("summary.json").exists());
        png_size(&out.join(name).join("sim").join("control_effort.png"));
    }
    assert!(report.contains("verdict") && report.contains("sense-to-actuate"));
    // Each run's worst incident, or that it had none, is named.
    assert!(report.contains("### The worst incident of each run"), "{report}");
    for name in ["paper-zero", "paper-constant", "paper-sinusoid"] {
        assert!(report.contains(&format!("- **{name}**")), "{name}: {report}");
    }
}

/// `rotorloop doctor --json` names every item it promises (CPUs, scheduling, timers and
/// idle, memory, interference), each with what it is here and what it means; the text
/// form says the same items. Whether SCHED_FIFO works is what the kernel said to a child.
#[test]
fn doctor_names_what_this_machine_allows_a_loop() {
    let text = rotorloop(&["doctor", "--json", "--rate", "2000"]);
    let j: serde_json::Value = serde_json::from_str(&text).expect("json");
    assert_eq!(j["rate_hz"].as_f64(), Some(2000.0));
    let items = j["items"].as_array().expect("items");
    let names: Vec<&str> = items.iter().filter_map(|i| i["name"].as_str()).collect();
    for want in [
        "cpus",
        "smt",
        "numa",
        "isolated",
        "nohz_full",
        "rcu_nocbs",
        "sched_fifo",
        "rt_throttling",
        "preemption",
        "clocksource",
        "cpuidle",
        "cpu_dma_latency",
        "governor",
        "mlockall",
        "thp",
        "swap",
        "shm",
        "irqbalance",
        "irq_affinity",
        "steal",
    ] {
        assert!(names.contains(&want), "doctor lacks {want}: {names:?}");
    }
    for i in items {
        assert!(!i["value"].as_str().unwrap_or_default().is_empty(), "{i}");
        assert!(!i["meaning"].as_str().unwrap_or_default().is_empty(), "{i}");
    }
    let fifo = items.iter().find(|i| i["name"] == "sched_fifo").expect("sched_fifo");
    let value = fifo["value"].as_str().unwrap_or_default();
    assert!(
        value.starts_with("SCHED_FIFO available")
            || value.starts_with("SCHED_FIFO not available ("),
        "{value}"
    );
    let text = rotorloop(&["doctor"]);
    assert!(text.contains("sched_fifo: ") && text.contains("irq_affinity: "), "{text}");
}
