//! `rotorloop run --controller-cmd`: a controller of the user's own under the launcher.
//! The rotorloop binary itself as the command gives the built-in trace byte for byte;
//! `examples/python/controller.py` (numpy, iceoryx2's Python binding, installed by
//! these tests into `target/pyvenv` from `python/requirements.txt`) tracks the Rust law's
//! lockstep trace, completes a real-time run, and resumes bumplessly after a `kill -9`.
//! The Python tests skip with a message where `python3` is missing.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Mutex;
use std::time::Duration;

use crate::common::harness::{Harness, ROTORLOOP, json, ok};

const LIMIT: Duration = Duration::from_secs(300);
const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The Python of `target/pyvenv` with `python/requirements.txt` installed (made once, by
/// the first test that needs it), or `None` (and a message) where `python3` is missing.
pub(crate) fn python() -> Option<PathBuf> {
    static VENV: Mutex<Option<PathBuf>> = Mutex::new(None);
    let mut made = VENV.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(p) = made.as_ref() {
        return Some(p.clone());
    }
    if Command::new("python3").arg("--version").output().is_err() {
        eprintln!("skipped: python3 is not installed here");
        return None;
    }
    let venv = Path::new(ROOT).join("target/pyvenv");
    let py = venv.join("bin/python");
    let requirements = Path::new(ROOT).join("python/requirements.txt");
    let stamp = venv.join("requirements.txt");
    let current = std::fs::read(&stamp).ok() == std::fs::read(&requirements).ok();
    if !(py.exists() && current) {
        let made_venv = Command::new("python3").args(["-m", "venv"]).arg(&venv).output();
        let o = made_venv.expect("python3 -m venv");
        assert!(o.status.success(), "python3 -m venv: {}", String::from_utf8_lossy(&o.stderr));
        let o = Command::new(&py)
            .args(["-m", "pip", "install", "-q", "--disable-pip-version-check", "-r"])
            .arg(&requirements)
            .output()
            .expect("pip");
        assert!(
            o.status.success(),
            "pip install -r python/requirements.txt: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        std::fs::copy(&requirements, &stamp).expect("stamp");
    }
    *made = Some(py.clone());
    Some(py)
}

/// `rotorloop run` of `paper-sinusoid` for `duration` s in `mode` into `h/name`, with
/// `extra` arguments; the run must succeed.
fn run(h: &Harness, name: &str, mode: &str, duration: &str, extra: &[&str]) -> PathBuf {
    let out = h.path(name);
    let domain = format!("{}{name}", h.domain);
    let mut args = vec!["run", "--scenario", "paper-sinusoid", "--mode", mode];
    args.extend(["--duration", duration, "--quiet", "--no-mcap", "--domain", &domain]);
    args.extend(extra);
    args.extend(["--out", out.to_str().expect("utf8")]);
    ok(&h.rotorloop(&args, LIMIT));
    out
}

/// The controller command of the Python example with `py`.
fn python_controller(py: &Path) -> String {
    format!("{} {}/examples/python/controller.py", py.display(), ROOT)
}

/// `trace.csv` as its header and rows of numbers.
fn trace(dir: &Path) -> (Vec<String>, Vec<Vec<f64>>) {
    let text = std::fs::read_to_string(dir.join("trace.csv")).expect("trace.csv");
    let mut lines = text.lines();
    let header = lines.next().expect("header").split(',').map(str::to_owned).collect();
    let rows =
        lines.map(|l| l.split(',').map(|v| v.parse().unwrap_or(f64::NAN)).collect()).collect();
    (header, rows)
}

/// The rotorloop binary itself as the command: the launcher's part of `--controller-cmd`
/// (arguments, environment, supervision) changes nothing, byte for byte.
#[test]
fn the_built_in_controller_as_a_command_gives_the_same_trace() {
    let h = Harness::new("ccself");
    let builtin = run(&h, "b", "lockstep", "3", &[]);
    let cmd = format!("{ROTORLOOP} role controller");
    let external = run(&h, "e", "lockstep", "3", &["--controller-cmd", &cmd]);
    let read = |d: &Path| std::fs::read(d.join("trace.csv")).expect("trace");
    assert!(read(&builtin) == read(&external), "the traces differ");
    let c = json(&external.join("controller.json"));
    assert_eq!(c["gains"]["kd"], 3.0);
    assert_eq!(c["ticks"], 3000);
    assert!(external.join("scenario.toml").exists());
    h.assert_no_leftovers();
}

/// A command that cannot be started is a usage error naming it, before anything runs.
#[test]
fn a_controller_command_that_cannot_start_is_refused() {
    let h = Harness::new("ccbad");
    let out = h.path("run");
    let o = h.rotorloop(
        &["run", "--scenario", "paper-zero", "--mode", "lockstep", "--domain", &h.domain]
            .into_iter()
            .chain(["--controller-cmd", "no-such-ctl --x", "--out", out.to_str().expect("utf8")])
            .collect::<Vec<_>>(),
        LIMIT,
    );
    assert_eq!(o.status.code(), Some(2), "{o:?}");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--controller-cmd") && err.contains("no-such-ctl"), "{err}");
    assert!(!out.join("summary.json").exists());
}

/// The Python law against the Rust law in lockstep, row by row: the attitude (the angle
/// of `R_py R_rustᵀ`) and every other column relative to `max(1, |rust|)`, within 1e-9.
#[test]
fn the_python_controller_tracks_the_rust_law_in_lockstep() {
    let Some(py) = python() else { return };
    let h = Harness::new("ccpy");
    let rust = run(&h, "rust", "lockstep", "10", &[]);
    let python = run(&h, "py", "lockstep", "10", &["--controller-cmd", &python_controller(&py)]);
    let ((hr, r), (hp, p)) = (trace(&rust), trace(&python));
    assert_eq!(hr, hp);
    assert_eq!(r.len(), p.len(), "rows");
    let r11 = hr.iter().position(|c| c == "R11").expect("R11");
    let mut worst = (0.0f64, String::new());
    for (a, b) in r.iter().zip(&p) {
        let ra = glam::DMat3::from_cols_array(&a[r11..r11 + 9].try_into().expect("9")).transpose();
        let rb = glam::DMat3::from_cols_array(&b[r11..r11 + 9].try_into().expect("9")).transpose();
        // The angle of E = R_py R_rustᵀ from its skew part (acos of its trace would
        // read 1e-16 of round-off as 1e-8 rad near zero).
        let e = rb * ra.transpose();
        let skew = glam::DVec3::new(
            e.col(1).z - e.col(2).y,
            e.col(2).x - e.col(0).z,
            e.col(0).y - e.col(1).x,
        ) * 0.5;
        let angle = skew.length().min(1.0).asin();
        if angle > worst.0 {
            worst = (angle, format!("attitude at t = {}", a[0]));
        }
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            // Both NaN: a column with no value on that row (delay_s of the last row).
            if hr[i] == "delay_s" || (x.is_nan() && y.is_nan()) {
                continue;
            }
            let d = (x - y).abs() / x.abs().max(1.0);
            if d > worst.0 || d.is_nan() {
                worst = (d, format!("{} at t = {}: {x} vs {y}", hr[i], a[0]));
            }
        }
    }
    eprintln!("python vs rust, lockstep 10 s: worst {:.3e} ({})", worst.0, worst.1);
    assert!(worst.0 < 1e-9, "{:e}: {}", worst.0, worst.1);
}

/// A real-time run with the Python controller completes with its histograms, and its
/// compute shows in the stage breakdown.
#[test]
fn the_python_controller_completes_a_real_time_run() {
    let Some(py) = python() else { return };
    let h = Harness::new("ccpyrt");
    let out = run(&h, "rt", "realtime", "4", &["--controller-cmd", &python_controller(&py)]);
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true, "{s}");
    assert_eq!(s["faults"].as_array().map(Vec::len), Some(0));
    // How many states the slow controller answers is the machine's business (under a busy
    // loop per core, 2 557 of 4 001 once): every tick with a fresh torque had an answer,
    // and no state was both answered and skipped.
    let compute = &s["hops"]["controller_compute"];
    let n = |v: &serde_json::Value| v.as_u64().unwrap_or_else(|| panic!("a count: {s}"));
    let (answers, ticks) = (n(&compute["count"]), n(&s["ticks"]));
    let (misses, skipped) = (n(&s["misses"]), n(&s["states_skipped_by_controller"]));
    assert!(answers > 0 && answers >= ticks - misses, "{answers} answers, {misses} misses: {s}");
    assert!(answers + skipped <= ticks + 1, "{answers} answers, {skipped} skipped: {s}");
    let law =
        s["stages"].as_array().and_then(|st| st.iter().find(|x| x["stage"] == "controller_law"));
    assert!(law.is_some_and(|l| l["p50"].as_f64().is_some_and(|p| p > 0.0)), "{law:?}");
    assert!(out.join("controller_compute.hgrm").exists());
    h.assert_no_leftovers();
}

/// `kill -9` of the Python controller in the middle of a lockstep run, by the fault
/// schedule and by hand: the launcher restarts it, it resumes from its state file, and
/// the trace is the uninterrupted one byte for byte (bumpless: no step in the law's
/// integral).
#[test]
fn a_killed_python_controller_resumes_bumplessly() {
    let Some(py) = python() else { return };
    let h = Harness::new("ccpykill");
    let cmd = python_controller(&py);
    let calm = run(&h, "calm", "lockstep", "20", &["--controller-cmd", &cmd]);
    let fault = "controller:kill@1:restart@1.3";
    let killed = run(&h, "kill", "lockstep", "20", &["--controller-cmd", &cmd, "--fault", fault]);
    let s = json(&killed.join("summary.json"));
    assert_eq!(s["faults"].as_array().map(Vec::len), Some(1), "{}", s["faults"]);
    let read = |d: &Path| std::fs::read(d.join("trace.csv")).expect("trace");
    assert!(read(&calm) == read(&killed), "the trace after the restart differs");
    // By hand: `kill -9` of the Python process itself while the loop runs.
    let out = h.path("hand");
    let domain = format!("{}hand", h.domain);
    let child = crate::common::harness::group(&mut Command::new(ROTORLOOP))
        .args(["run", "--scenario", "paper-sinusoid", "--mode", "lockstep", "--duration", "20"])
        .args(["--quiet", "--no-mcap", "--domain", &domain, "--controller-cmd", &cmd, "--out"])
        .arg(&out)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("spawn");
    let pid = python_pid(&domain);
    std::thread::sleep(Duration::from_millis(800));
    // SAFETY: signals a process this test found by its command line.
    unsafe { libc::kill(pid as libc::pid_t, libc::SIGKILL) };
    ok(&crate::common::harness::wait_output(child, LIMIT));
    let s = json(&out.join("summary.json"));
    assert_eq!(s["faults"].as_array().map(Vec::len), Some(1), "{}", s["faults"]);
    assert!(read(&calm) == read(&out), "the trace after a by-hand kill differs");
    h.assert_no_leftovers();
}

/// The pid of the Python controller of `domain`, once it runs.
fn python_pid(domain: &str) -> u32 {
    let until = std::time::Instant::now() + LIMIT;
    loop {
        for e in std::fs::read_dir("/proc").expect("/proc").flatten() {
            let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else { continue };
            let Ok(cmdline) = std::fs::read(e.path().join("cmdline")) else { continue };
            let args: Vec<&[u8]> = cmdline.split(|b| *b == 0).collect();
            let ours = args.windows(2).any(|w| w[0] == b"--domain" && w[1] == domain.as_bytes());
            // The launcher's own command line names the script too, inside one argument.
            let script = args.get(1).is_some_and(|a| a.ends_with(b"controller.py"));
            if ours && script {
                return pid;
            }
        }
        assert!(std::time::Instant::now() < until, "no Python controller in {domain}");
        std::thread::sleep(Duration::from_millis(20));
    }
}
