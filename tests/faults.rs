//! Fault injection: SIGKILL any role mid-run, restart it, and the loop recovers with
//! nothing lost. In lockstep the recovered run is checked against the simulator bit for
//! bit, which is the strongest statement of "nothing lost" there is.

mod common;

use std::time::Duration;

use common::harness::{Harness, TimingRow, assert_same_trace, json, ok, timing_rows};
use rotorloop_common::wire::FLAG_SAFE_MODE;

const LIMIT: Duration = Duration::from_secs(180);

/// A lockstep run of 60 s of simulated time with the given faults; returns the report dir.
fn lockstep_with_faults(h: &Harness, faults: &[&str], env: &[(&str, &str)]) -> std::path::PathBuf {
    let out = h.path("run");
    let mut cmd = std::process::Command::new(common::harness::ROTORLOOP);
    common::harness::group(&mut cmd);
    cmd.args(["run", "--scenario", "paper-sinusoid", "--duration", "60", "--mode", "lockstep"])
        .args(["--domain", &h.domain, "--out"])
        .arg(&out)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped());
    for f in faults {
        cmd.args(["--fault", f]);
    }
    for (k, v) in env {
        cmd.env(k, v);
    }
    ok(&common::harness::wait_output(cmd.spawn().expect("spawn"), LIMIT));
    out
}

fn sim_trace(h: &Harness) -> Vec<u8> {
    let out = h.path("sim");
    ok(&h.rotorloop(
        &[
            "sim",
            "--scenario",
            "paper-sinusoid",
            "--duration",
            "60",
            "--no-figures",
            "--out",
            out.to_str().expect("utf8"),
        ],
        LIMIT,
    ));
    std::fs::read(out.join("trace.csv")).expect("sim trace")
}

/// Each fault happened mid-run (it has a kill tick before the last tick).
fn assert_faults_mid_run(out: &std::path::Path, n: usize) -> serde_json::Value {
    let s = json(&out.join("summary.json"));
    let faults = s["faults"].as_array().expect("faults list");
    assert_eq!(faults.len(), n, "{faults:?}");
    for f in faults {
        let k = f["kill_tick"].as_u64().expect("kill tick");
        assert!(k < 60_000, "the fault came after the run: {f}");
    }
    assert_eq!(s["completed"], true);
    s
}

fn lockstep_role_killed_and_restarted_continues_bit_for_bit(role: &str) {
    let h = Harness::new(&format!("kill-{role}"));
    let out = lockstep_with_faults(&h, &[&format!("{role}:kill@0.6:restart@0.9")], &[]);
    assert_faults_mid_run(&out, 1);
    assert_same_trace(role, &std::fs::read(out.join("trace.csv")).expect("trace"), &sim_trace(&h));
    h.assert_no_leftovers();
}

/// A killed and restarted controller resumes bumplessly: it takes `ξ_I` from the last
/// torque sample it published, and the lockstep trace equals the simulator's.
#[test]
fn controller_killed_and_restarted_resumes_bumplessly() {
    lockstep_role_killed_and_restarted_continues_bit_for_bit("controller");
}

/// A restarted reference continues its trajectory from its last published sample, as
/// if it had never died (not from t = 0).
#[test]
fn reference_killed_and_restarted_continues_the_trajectory() {
    lockstep_role_killed_and_restarted_continues_bit_for_bit("reference");
}

/// A restarted plant resumes from its last published state at the same tick index: the
/// trace continues without a jump.
#[test]
fn plant_killed_and_restarted_resumes_at_the_same_tick() {
    lockstep_role_killed_and_restarted_continues_bit_for_bit("plant");
}

/// A killed monitor does not disturb the loop; the restarted one appends to the same
/// report, the data lost is exactly its downtime (reported as a gap), every row it wrote
/// equals the simulator's (but the energy residual, re-anchored after the gap), and the
/// interval logs written before the kill remain readable.
#[test]
fn monitor_killed_and_restarted_reports_exactly_its_gap() {
    let h = Harness::new("kill-monitor");
    let out = lockstep_with_faults(&h, &["monitor:kill@0.3:restart@0.6"], &[]);
    let s = assert_faults_mid_run(&out, 1);
    let gaps = s["monitor_gaps"].as_array().expect("gaps");
    assert_eq!(gaps.len(), 1, "{gaps:?}");
    let (g0, g1) = (gaps[0][0].as_u64().expect("g0"), gaps[0][1].as_u64().expect("g1"));
    assert!(g1 >= g0);
    assert_eq!(s["rows_lost"].as_u64(), Some(g1 - g0 + 1));
    assert_eq!(s["trace_rows"].as_u64(), Some(60_001 - (g1 - g0 + 1)));
    assert_eq!(s["monitor_restarts"], 1);
    assert_eq!(s["misses"], 0);
    // Rows: exactly the ticks outside the gap, each equal to the simulator's row.
    let run =
        String::from_utf8(std::fs::read(out.join("trace.csv")).expect("trace")).expect("utf8");
    let sim = String::from_utf8(sim_trace(&h)).expect("utf8");
    let header: Vec<&str> = sim.lines().next().expect("header").split(',').collect();
    let residual = header.iter().position(|c| *c == "energy_residual").expect("column");
    let tick_col = header.iter().position(|c| *c == "tick").expect("column");
    let err_col = header.iter().position(|c| *c == "err_deg").expect("column");
    let sim_rows: Vec<&str> = sim.lines().skip(1).collect();
    let mut expected_tick = 0u64;
    let (mut err_sq, mut rows) = (0.0f64, 0u64);
    for line in run.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let tick: u64 = f[tick_col].parse().expect("tick");
        let err: f64 = f[err_col].parse().expect("err_deg");
        (err_sq, rows) = (err_sq + err * err, rows + 1);
        if expected_tick == g0 {
            expected_tick = g1 + 1;
        }
        assert_eq!(tick, expected_tick, "rows out of order or missing outside the gap");
        let want: Vec<&str> = sim_rows[tick as usize].split(',').collect();
        for (i, (a, b)) in f.iter().zip(&want).enumerate() {
            if i != residual {
                assert_eq!(a, b, "tick {tick}, column {}", header[i]);
            }
        }
        expected_tick += 1;
    }
    assert_eq!(expected_tick, 60_001);
    // The RMS error is over the rows written, carried across the restart in the slot.
    let rms = (err_sq / rows as f64).sqrt();
    let reported = s["err_deg_rms"].as_f64().expect("err_deg_rms");
    assert!((reported - rms).abs() <= 1e-9 * rms, "err_deg_rms {reported} != {rms} of the trace");
    // Interval logs: one header, then interval lines from both monitor lives.
    let log = std::fs::read_to_string(out.join("sense_to_actuate.hlog")).expect("hlog");
    assert!(log.lines().filter(|l| l.starts_with("#[StartTime")).count() == 1, "{log}");
    assert!(log.lines().filter(|l| !l.starts_with('#') && !l.starts_with('"')).count() >= 1);
    h.assert_no_leftovers();
}

/// The same role killed and restarted five times in one run.
#[test]
fn the_same_role_killed_five_times_in_one_run() {
    let h = Harness::new("kill-5x");
    let faults: Vec<String> = (0..5)
        .map(|i| {
            format!(
                "controller:kill@{:.2}:restart@{:.2}",
                0.5 + 0.3 * i as f64,
                0.65 + 0.3 * i as f64
            )
        })
        .collect();
    let refs: Vec<&str> = faults.iter().map(String::as_str).collect();
    let out = lockstep_with_faults(&h, &refs, &[]);
    assert_faults_mid_run(&out, 5);
    assert_same_trace(
        "5 kills",
        &std::fs::read(out.join("trace.csv")).expect("trace"),
        &sim_trace(&h),
    );
    h.assert_no_leftovers();
}

/// Two roles killed at once, restarted together.
#[test]
fn two_roles_killed_at_once() {
    let h = Harness::new("kill-2");
    let out = lockstep_with_faults(
        &h,
        &["controller:kill@0.3:restart@0.6", "reference:kill@0.3:restart@0.6"],
        &[],
    );
    assert_faults_mid_run(&out, 2);
    assert_same_trace(
        "2 roles",
        &std::fs::read(out.join("trace.csv")).expect("trace"),
        &sim_trace(&h),
    );
    h.assert_no_leftovers();
}

/// A controller killed while it holds a loaned sample (test hook) is restarted fine:
/// iceoryx2 reclaims the loan, the restart cleans up its dead predecessor.
#[test]
fn controller_killed_while_holding_a_loan_restarts() {
    let h = Harness::new("kill-loan");
    let out = lockstep_with_faults(
        &h,
        &["controller:kill@0.8:restart@1.0"],
        &[("ROTORLOOP_TEST_STALL_WITH_LOAN_AT", "500")],
    );
    let s = assert_faults_mid_run(&out, 1);
    assert_eq!(s["faults"][0]["kill_tick"], 500, "the controller stalled at tick 500");
    assert_same_trace(
        "loan",
        &std::fs::read(out.join("trace.csv")).expect("trace"),
        &sim_trace(&h),
    );
    h.assert_no_leftovers();
}

/// Real time: with the controller gone the plant keeps its tick grid, holds the last
/// torque for `--hold-ticks`, then enters safe mode; the restarted controller resumes
/// control.
#[test]
fn realtime_controller_loss_holds_then_safe_mode_then_recovers() {
    let h = Harness::new("rt-kill");
    let out = h.path("rt");
    ok(&h.rotorloop(
        &[
            "run",
            "--scenario",
            "paper-zero",
            "--duration",
            "4",
            "--mode",
            "realtime",
            "--hold-ticks",
            "40",
            "--fault",
            "controller:kill@1.0:restart@2.0",
            "--domain",
            &h.domain,
            "--out",
            out.to_str().expect("utf8"),
        ],
        LIMIT,
    ));
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    assert_eq!(s["trace_rows"], 4001, "the plant kept its grid: every tick published");
    let f = &s["faults"][0];
    let without = f["ticks_without_fresh_torque"].as_u64().expect("ticks");
    assert!(without > 40, "{f}");
    assert!(f["ticks_to_first_fresh_torque"].as_u64().is_some(), "control never resumed: {f}");
    // Every tick from the kill to the first fresh torque after safe mode is, in this order:
    // held (a torque from before the kill, at most --hold-ticks of them, and the one in
    // flight), in safe mode (or coasting), then, on a loaded machine, late answers of the restarted
    // controller (newer than the kill, but not from the tick before: its first answers
    // can miss their own tick's wait, and safe mode ends on arrival). Seen loaded: 1003
    // safe-mode ticks of 1048 without a fresh torque.
    let kill = f["kill_tick"].as_u64().expect("kill tick") as i64;
    let rows = timing_rows(&out);
    let fresh = |r: &TimingRow| r.tick > 0 && r.applied == r.tick - 1;
    let safe = |r: &TimingRow| r.flags & FLAG_SAFE_MODE != 0;
    let first_safe = rows.iter().find(|r| r.tick > kill && safe(r)).expect("no safe mode").tick;
    let first_fresh = rows.iter().find(|r| r.tick > first_safe && fresh(r)).expect("no fresh").tick;
    let class: Vec<u8> = rows
        .iter()
        .filter(|r| r.tick > kill && r.tick <= first_fresh && !fresh(r))
        .map(|r| match (safe(r), r.applied) {
            // Safe mode, or no torque at all in the tick (applied -1: the rotors coast,
            // as on the tick where safe mode has ended and the first answer is late).
            (true, _) | (false, ..0) => 1,
            (false, a) if a <= kill => 0,
            (false, _) => 2,
        })
        .collect();
    assert_eq!(class.len() as u64, without, "the report's count is this window");
    assert!(class.is_sorted(), "held, then safe mode, then late answers: {class:?}");
    let held = class.iter().filter(|x| **x == 0).count();
    assert!(held <= 41, "held {held} ticks with --hold-ticks 40");
    let in_safe_mode =
        rows.iter().filter(|r| r.tick > kill && r.tick < first_fresh && safe(r)).count();
    assert!(in_safe_mode > 0);
    let safe_total = s["safe_mode_ticks"].as_u64().expect("safe") as usize;
    assert!(safe_total >= in_safe_mode, "summary {safe_total} < {in_safe_mode} safe-mode ticks");
    assert!(out.join("faults.png").exists());
    h.assert_no_leftovers();
}

/// Killing and restarting by hand works as well: `kill -9` the controller of a run
/// started by hand and start it again with its original command line.
#[test]
fn controller_killed_by_hand_and_restarted_with_its_command_line() {
    let mut h = Harness::new("by-hand");
    let out = h.path("mon");
    let base: Vec<String> =
        ["--domain", &h.domain, "--scenario", "paper-sinusoid", "--duration", "60"]
            .iter()
            .map(|s| s.to_string())
            .collect();
    let with = |extra: &[&str]| {
        base.iter().cloned().chain(extra.iter().map(|s| s.to_string())).collect::<Vec<_>>()
    };
    h.spawn(env!("CARGO_BIN_EXE_monitor"), &with(&["--out", out.to_str().expect("utf8")]));
    h.spawn(env!("CARGO_BIN_EXE_reference"), &base);
    let c = h.spawn(env!("CARGO_BIN_EXE_controller"), &base);
    h.spawn(env!("CARGO_BIN_EXE_plant"), &with(&["--subscribers", "3"]));
    std::thread::sleep(Duration::from_millis(300));
    h.child(c).kill().expect("kill -9");
    h.child(c).wait().expect("reap");
    std::thread::sleep(Duration::from_millis(300));
    h.spawn(env!("CARGO_BIN_EXE_controller"), &base);
    let statuses = h.wait_all(LIMIT);
    for (i, st) in statuses.iter().enumerate() {
        if i != c {
            assert!(st.success(), "process {i}: {st}");
        }
    }
    let trace = std::fs::read(out.join("trace.csv")).expect("trace");
    assert_same_trace("by hand", &trace, &sim_trace(&h));
    ok(&h.rotorloop(&["clean", "--domain", &h.domain], LIMIT));
    h.assert_no_leftovers();
}

/// Soak (not in CI: `cargo test --release --test faults -- --ignored`): random kills of
/// random roles for several minutes in real time; prints the recovery statistics.
#[test]
#[ignore]
fn soak_random_kills_of_random_roles() {
    let h = Harness::new("soak");
    let out = h.path("soak");
    let roles = ["plant", "reference", "controller", "monitor"];
    let mut faults = Vec::new();
    let mut t = 2.0;
    let mut x = 12345u64;
    while t < 170.0 {
        x = x.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let role = roles[(x >> 33) as usize % roles.len()];
        let down = 0.2 + ((x >> 13) % 1000) as f64 / 1000.0;
        faults.push(format!("{role}:kill@{t:.2}:restart@{:.2}", t + down));
        t += down + 2.0 + ((x >> 23) % 3000) as f64 / 1000.0;
    }
    let mut args: Vec<String> = [
        "run",
        "--scenario",
        "paper-zero",
        "--duration",
        "180",
        "--mode",
        "realtime",
        "--domain",
        &h.domain,
        "--out",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    args.push(out.to_string_lossy().into_owned());
    for f in &faults {
        args.push("--fault".into());
        args.push(f.clone());
    }
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    ok(&h.rotorloop(&refs, Duration::from_secs(600)));
    let s = json(&out.join("summary.json"));
    let fs = s["faults"].as_array().expect("faults");
    let recovered = fs
        .iter()
        .filter(|f| f["ticks_to_first_fresh_torque"].is_u64() || f["role"] == "monitor")
        .count();
    eprintln!(
        "soak: {} faults, {} recovered, misses {}, safe-mode ticks {}, monitor gaps {}",
        fs.len(),
        recovered,
        s["misses"],
        s["safe_mode_ticks"],
        s["monitor_gaps"].as_array().map_or(0, Vec::len)
    );
    assert_eq!(s["completed"], true);
    h.assert_no_leftovers();
}

/// Under load the controller answers only the newest state in its inbox, so some ticks
/// never get a torque. At the very end no newer state comes to settle such a row: the
/// monitor must settle it from the controller's later torque and finish the report (it
/// used to wait forever, and with it the launcher).
#[test]
fn a_tick_the_controller_skipped_at_the_end_does_not_stall_the_report() {
    let h = Harness::new("skip-end");
    let out = h.path("rt");
    let mut cmd = std::process::Command::new(common::harness::ROTORLOOP);
    common::harness::group(&mut cmd)
        .args(["run", "--scenario", "paper-zero", "--duration", "0.3", "--mode", "realtime"])
        .args(["--domain", &h.domain, "--out"])
        .arg(&out)
        .env("ROTORLOOP_TEST_SKIP_STATE_AT", "299")
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped());
    ok(&common::harness::wait_output(cmd.spawn().expect("spawn"), Duration::from_secs(60)));
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    assert_eq!(s["trace_rows"], 301);
    // Torque 299 never came, so the plant held an older one over tick 299 and its state
    // 300 says which: 298 on an idle machine, earlier when a loaded controller answered
    // only the newest of several states.
    let row300 = timing_rows(&out).into_iter().find(|r| r.tick == 300).expect("row 300");
    assert!(row300.applied < 299, "the plant applied a torque for the skipped tick: {row300:?}");
    h.assert_no_leftovers();
}

/// The processes of a domain (by their command line).
fn processes_of(domain: &str) -> Vec<u32> {
    let mut out = Vec::new();
    for e in std::fs::read_dir("/proc").expect("/proc").flatten() {
        let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else { continue };
        let Ok(cmdline) = std::fs::read(e.path().join("cmdline")) else { continue };
        let args: Vec<&[u8]> = cmdline.split(|b| *b == 0).collect();
        if args.windows(2).any(|w| w[0] == b"--domain" && w[1] == domain.as_bytes()) {
            out.push(pid);
        }
    }
    out
}

/// `kill -9` of the launcher itself: its roles get SIGTERM from the kernel (parent-death
/// signal), stop, and leave nothing running; `clean` then leaves nothing behind.
#[test]
fn a_killed_launcher_leaves_no_role_running() {
    let mut h = Harness::new("kill-launcher");
    let out = h.path("rt");
    // Far longer than the limit below: roles that outlive the launcher would run on.
    let args: Vec<String> = ["run", "--scenario", "paper-zero", "--duration", "600"]
        .iter()
        .map(|s| s.to_string())
        .chain(["--mode", "realtime", "--domain", &h.domain, "--out"].map(String::from))
        .chain([out.to_string_lossy().into_owned()])
        .collect();
    let launcher = h.spawn(common::harness::ROTORLOOP, &args);
    let until = std::time::Instant::now() + LIMIT;
    while processes_of(&h.domain).len() < 5 || !out.join("timing.csv").exists() {
        assert!(std::time::Instant::now() < until, "the run did not start");
        std::thread::sleep(Duration::from_millis(50));
    }
    h.child(launcher).kill().expect("kill -9 the launcher");
    h.child(launcher).wait().expect("reap");
    while !processes_of(&h.domain).is_empty() {
        if std::time::Instant::now() > until {
            let left = processes_of(&h.domain);
            for &pid in &left {
                // SAFETY: plain syscall on processes this test started.
                unsafe { libc::kill(pid as libc::pid_t, libc::SIGKILL) };
            }
            panic!("roles outlived the launcher: {left:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    ok(&h.rotorloop(&["clean", "--domain", &h.domain], LIMIT));
    h.assert_no_leftovers();
}

/// A role killed just before the end and restarted after it gets no more states: it
/// learns from the plant's resume slot that the run is over and stops, instead of
/// waiting forever for a plant that has gone (the controller used to). Every tick is in
/// the report or counted lost, and a monitor restarted late reports the end as its gap.
#[test]
fn a_role_restarted_after_the_run_ended_stops_and_the_report_accounts_for_every_tick() {
    let h = Harness::new("late-restart");
    for role in ["controller", "reference", "monitor"] {
        let out = h.path(role);
        let fault = format!("{role}:kill@0.9:restart@2.5");
        let args = ["run", "--scenario", "paper-zero", "--duration", "1", "--mode", "realtime"];
        let mut cmd = std::process::Command::new(common::harness::ROTORLOOP);
        common::harness::group(&mut cmd)
            .args(args)
            .args(["--fault", &fault, "--domain", &h.domain, "--out"])
            .arg(&out)
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped());
        ok(&common::harness::wait_output(cmd.spawn().expect("spawn"), LIMIT));
        let s = json(&out.join("summary.json"));
        assert_eq!(s["completed"], true, "{role}: {s}");
        let rows = s["trace_rows"].as_u64().expect("rows");
        let lost = s["rows_lost"].as_u64().expect("lost");
        assert_eq!(rows + lost, 1001, "{role}: {rows} rows + {lost} lost");
        if role == "monitor" {
            assert_eq!(s["monitor_gaps"][0][1], 1000, "{role}: {s}");
        }
        h.assert_no_leftovers();
    }
}
