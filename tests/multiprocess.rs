//! The four processes over iceoryx2: system contracts of `rotorloop run` and of the role
//! binaries started by hand.

use std::time::Duration;

use crate::common::harness::{
    Harness, ROTORLOOP, assert_same_trace, json, ok, proc_state, sim_trace,
};

const LIMIT: Duration = Duration::from_secs(120);

/// A lockstep run of the four processes produces the same trace, bit for bit, as the
/// in-process simulator (both actuations).
#[test]
fn lockstep_run_matches_sim_byte_for_byte() {
    let h = Harness::new("lockstep");
    for (scenario, actuation) in [("paper-sinusoid", "internal"), ("paper-constant", "external")] {
        let out = h.path(&format!("run-{scenario}"));
        ok(&h.rotorloop(
            &[
                "run",
                "--scenario",
                scenario,
                "--duration",
                "1",
                "--actuation",
                actuation,
                "--mode",
                "lockstep",
                "--domain",
                &h.domain,
                "--out",
                out.to_str().expect("utf8"),
            ],
            LIMIT,
        ));
        let run = std::fs::read(out.join("trace.csv")).expect("run trace");
        let sim = sim_trace(&h, scenario, "1", &["--actuation", actuation]);
        assert_same_trace(&format!("{scenario}/{actuation}"), &run, &sim);
        let s = json(&out.join("summary.json"));
        assert_eq!(s["trace_rows"], 1001);
        assert_eq!(s["monitor_kept_up"], true);
        for f in ["sense_to_actuate.hgrm", "latency_percentiles.png", "attitude_entries.png"] {
            assert!(out.join(f).exists(), "{f}");
        }
    }
    h.assert_no_leftovers();
}

/// A real-time 1 kHz run completes; every histogram is populated; for each subscriber
/// the samples received plus the losses it counted equal what was published.
#[test]
fn realtime_run_populates_every_histogram_and_counts_add_up() {
    let h = Harness::new("realtime");
    let out = h.path("rt");
    let stdout = ok(&h.rotorloop(
        &[
            "run",
            "--scenario",
            "paper-zero",
            "--duration",
            "3",
            "--rate",
            "1000",
            "--mode",
            "realtime",
            "--domain",
            &h.domain,
            "--out",
            out.to_str().expect("utf8"),
        ],
        LIMIT,
    ));
    assert!(stdout.contains("T:sense_to_actuate"), "{stdout}");
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    let ticks = s["ticks"].as_u64().expect("ticks");
    assert_eq!(ticks, 3000);
    for hop in [
        "sense_to_actuate",
        "state_transport",
        "controller_compute",
        "torque_transport",
        "tick_lateness",
        "reference_lead",
    ] {
        let count = s["hops"][hop]["count"].as_u64().expect("count");
        assert!(count > ticks / 2, "{hop}: only {count} samples");
        let hgrm = std::fs::read_to_string(out.join(format!("{hop}.hgrm"))).expect("hgrm");
        assert!(hgrm.contains(&format!("Total count    = {count:>12}")), "{hop}.hgrm");
        let log = std::fs::read_to_string(out.join(format!("{hop}.hlog"))).expect("hlog");
        assert!(
            log.lines().filter(|l| !l.starts_with('#') && !l.starts_with('"')).count() >= 2,
            "{hop}.hlog"
        );
    }
    let sub = |name: &str| {
        let v = &s["subscribers"][name];
        (v["received"].as_u64().expect(name), v["lost"].as_u64().expect(name))
    };
    for name in ["monitor.state", "monitor.reference", "controller.state"] {
        let (r, l) = sub(name);
        assert_eq!(r + l, ticks + 1, "{name}: {r} received + {l} lost");
    }
    let (tr, tl) = sub("monitor.torque");
    let skipped = s["states_skipped_by_controller"].as_u64().expect("skipped");
    // A state the controller never took (its buffer overflowed while it was starved) has
    // no torque: every tick's torque is received, lost, skipped, or its state was lost.
    let cl = sub("controller.state").1;
    assert_eq!(
        tr + tl + skipped + cl,
        ticks + 1,
        "torque: {tr} + {tl} lost + {skipped} skipped + {cl} states lost"
    );
    let (pr, pl) = sub("plant.torque");
    // As above: a state the controller lost has no torque for the plant to receive.
    assert!(
        pr + pl + skipped + cl >= ticks,
        "plant torque counts: {pr} + {pl} lost + {skipped} skipped + {cl} states lost"
    );
    let misses = s["misses"].as_u64().expect("misses");
    assert!(misses <= ticks);
    assert!(s["achieved_rate_hz"].as_f64().expect("rate") > 0.0);
    h.assert_no_leftovers();
}

/// With the plain zero-order hold (`--actuation-delay 0`: a torque in force from the start
/// of its tick) and nothing late, real time gives the lockstep trace: every row up to the
/// first miss equals the simulator's, bit for bit. (With the default, `measured`, each
/// torque takes effect when it arrived, and the trace carries the loop's real latency;
/// `tests/delay.rs` replays such a run byte for byte.) At 10 Hz: a miss needs a role
/// kept off the CPU for 100 ms; at 200 Hz the first miss under a busy loop per core came
/// at the second row, and the test compared nothing.
#[test]
fn realtime_trace_equals_lockstep_until_the_first_miss() {
    let h = Harness::new("rt-equal");
    let out = h.path("rt");
    ok(&h.rotorloop(
        &[
            "run",
            "--actuation-delay",
            "0",
            "--scenario",
            "paper-constant",
            "--duration",
            "3",
            "--rate",
            "10",
            "--mode",
            "realtime",
            "--domain",
            &h.domain,
            "--out",
            out.to_str().expect("utf8"),
        ],
        LIMIT,
    ));
    let run = std::fs::read_to_string(out.join("trace.csv")).expect("trace");
    let sim =
        String::from_utf8(sim_trace(&h, "paper-constant", "3", &["--rate", "10"])).expect("utf8");
    // A miss shows as a row without a torque (NaN u); the state after it differs.
    let first_miss = run.lines().position(|l| l.contains("NaN")).unwrap_or(usize::MAX);
    let mut compared = 0;
    for (i, (a, b)) in run.lines().zip(sim.lines()).enumerate() {
        if i > first_miss {
            break;
        }
        if i < first_miss {
            assert_eq!(a, b, "row {i} differs before any miss");
            compared += 1;
        }
    }
    assert!(compared > 10, "only {compared} rows before the first miss");
    h.assert_no_leftovers();
}

/// The four role binaries, started by hand in every one of the 24 orders, connect and
/// run; the trace is the simulator's.
#[test]
fn processes_started_by_hand_in_every_order_connect_and_run() {
    let sim = {
        let h = Harness::new("order-sim");
        sim_trace(&h, "paper-zero", "0.1", &[])
    };
    let roles = ["plant", "reference", "controller", "monitor"];
    let bin = |r: &str| match r {
        "plant" => env!("CARGO_BIN_EXE_plant"),
        "reference" => env!("CARGO_BIN_EXE_reference"),
        "controller" => env!("CARGO_BIN_EXE_controller"),
        _ => env!("CARGO_BIN_EXE_monitor"),
    };
    let mut orders = Vec::new();
    permute(&mut roles.to_vec(), 0, &mut orders);
    assert_eq!(orders.len(), 24);
    for (n, order) in orders.iter().enumerate() {
        let mut h = Harness::new(&format!("order{n}"));
        let out = h.path("mon");
        for role in order {
            let mut args: Vec<String> =
                ["--domain", &h.domain, "--scenario", "paper-zero", "--duration", "0.1"]
                    .iter()
                    .map(|s| s.to_string())
                    .collect();
            match *role {
                "plant" => args.extend(["--subscribers".into(), "3".into()]),
                "monitor" => args.extend(["--out".into(), out.to_string_lossy().into_owned()]),
                _ => {}
            }
            h.spawn(bin(role), &args);
            std::thread::sleep(Duration::from_millis(40));
        }
        for (i, st) in h.wait_all(LIMIT).into_iter().enumerate() {
            assert!(st.success(), "order {order:?}: {} exited with {st}", order[i]);
        }
        // Shown with a failure (captured otherwise): once, in CI, the monitor's last row had
        // no torque (the controller's last answer never reached it); what each role said.
        for (i, role) in order.iter().enumerate() {
            eprintln!("{role}:\n{}", h.stderr_of(i));
        }
        let summary = std::fs::read_to_string(out.join("summary.json")).unwrap_or_default();
        eprintln!("the monitor's summary.json:\n{summary}");
        let trace = std::fs::read(out.join("trace.csv")).expect("trace");
        assert_same_trace(&format!("order {order:?}"), &trace, &sim);
        // Started by hand, nobody runs the launcher's final clean-up: `rotorloop clean` does.
        ok(&h.rotorloop(&["clean", "--domain", &h.domain], LIMIT));
        h.assert_no_leftovers();
    }
}

/// The race behind a rare failure of the test above (the monitor's last row without its
/// torque): the plant marks its end before it publishes its last state, and a monitor
/// slow to start (the plant runs once it connects) found the run over and wrote its last
/// row at once, before the controller's last answer came. Made certain here: the
/// controller stops itself before its last send, the monitor waits 0.5 s after it
/// connects, and the controller goes on 0.8 s after it stopped.
#[test]
fn a_monitor_started_after_the_plants_end_waits_for_the_last_answer() {
    let sim = {
        let h = Harness::new("late-mon-sim");
        sim_trace(&h, "paper-zero", "0.1", &[])
    };
    let mut h = Harness::new("late-mon");
    let (out, domain) = (h.path("mon"), h.domain.clone());
    let args = |extra: &[&str]| -> Vec<String> {
        ["--domain", &domain, "--scenario", "paper-zero", "--duration", "0.1"]
            .iter()
            .chain(extra)
            .map(|s| s.to_string())
            .collect()
    };
    let (plant, reference, controller) =
        (args(&["--subscribers", "3"]), args(&[]), args(&["--test-stop-before-send-at", "100"]));
    h.spawn(env!("CARGO_BIN_EXE_plant"), &plant);
    h.spawn(env!("CARGO_BIN_EXE_reference"), &reference);
    let c = h.spawn(env!("CARGO_BIN_EXE_controller"), &controller);
    let monitor = ["--test-start-stall-ms", "500", "--out", out.to_str().expect("utf8")];
    h.spawn(env!("CARGO_BIN_EXE_monitor"), &args(&monitor));
    let pid = h.child(c).id();
    let until = std::time::Instant::now() + LIMIT;
    while proc_state(pid) != Some('T') {
        assert!(std::time::Instant::now() < until, "the controller never stopped itself");
        std::thread::sleep(Duration::from_millis(5));
    }
    std::thread::sleep(Duration::from_millis(800));
    // SAFETY: a signal to this test's own child.
    unsafe { libc::kill(pid as libc::pid_t, libc::SIGCONT) };
    for (i, st) in h.wait_all(LIMIT).into_iter().enumerate() {
        assert!(st.success(), "child {i} exited with {st}: {}", h.stderr_of(i));
    }
    let trace = std::fs::read(out.join("trace.csv")).expect("trace");
    assert_same_trace("a monitor started after the end", &trace, &sim);
    ok(&h.rotorloop(&["clean", "--domain", &h.domain], LIMIT));
    h.assert_no_leftovers();
}

fn permute<'a>(v: &mut Vec<&'a str>, k: usize, out: &mut Vec<Vec<&'a str>>) {
    if k == v.len() {
        out.push(v.clone());
        return;
    }
    for i in k..v.len() {
        v.swap(k, i);
        permute(v, k + 1, out);
        v.swap(k, i);
    }
}

/// Two runs in different domains, at the same time, do not see each other.
#[test]
fn two_domains_in_parallel_do_not_interfere() {
    let h = Harness::new("domains");
    let spawn = |scenario: &str, domain: &str| {
        let out = h.path(&format!("run-{scenario}"));
        let child = crate::common::harness::group(&mut std::process::Command::new(ROTORLOOP))
            .args(["run", "--scenario", scenario, "--duration", "1", "--domain", domain, "--out"])
            .arg(&out)
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .expect("spawn");
        (crate::common::harness::Running::from(child), out)
    };
    let d1 = format!("{}-a", h.domain);
    let d2 = format!("{}-b", h.domain);
    let (c1, o1) = spawn("paper-zero", &d1);
    let (c2, o2) = spawn("paper-sinusoid", &d2);
    ok(&crate::common::harness::wait_output(c1, LIMIT));
    ok(&crate::common::harness::wait_output(c2, LIMIT));
    let t1 = std::fs::read(o1.join("trace.csv")).expect("t1");
    assert_same_trace("domain a", &t1, &sim_trace(&h, "paper-zero", "1", &[]));
    let t2 = std::fs::read(o2.join("trace.csv")).expect("t2");
    assert_same_trace("domain b", &t2, &sim_trace(&h, "paper-sinusoid", "1", &[]));
    for d in [d1, d2] {
        let mut other = Harness::new("unused");
        other.domain = d;
        other.assert_no_leftovers();
    }
}

/// SIGTERM to the launcher stops the four processes cleanly, leaves a partial report
/// marked as not completed, removes the run's shared memory, and exits with code 3 (the
/// control loop did not complete: stopped by a signal).
#[test]
fn sigterm_stops_the_run_cleanly_with_a_partial_report() {
    let h = Harness::new("sigterm");
    let out = h.path("rt");
    let child = crate::common::harness::group(&mut std::process::Command::new(ROTORLOOP))
        .args([
            "run",
            "--scenario",
            "paper-zero",
            "--duration",
            "60",
            "--mode",
            "realtime",
            "--domain",
            &h.domain,
            "--out",
        ])
        .arg(&out)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("spawn");
    let child = crate::common::harness::Running::from(child);
    // Wait until the monitor has written interval data, then stop the run.
    let until = std::time::Instant::now() + LIMIT;
    while std::fs::read_to_string(out.join("sense_to_actuate.hlog"))
        .map_or(true, |l| l.lines().count() < 4)
    {
        assert!(std::time::Instant::now() < until, "run did not start");
        std::thread::sleep(Duration::from_millis(50));
    }
    let o = child.terminate(LIMIT);
    assert_eq!(o.status.code(), Some(3), "{}", String::from_utf8_lossy(&o.stderr));
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], false);
    assert!(s["trace_rows"].as_u64().expect("rows") > 100);
    h.assert_no_leftovers();
}

/// Bad launcher arguments are refused with exit code 2 and a message naming them.
#[test]
fn launcher_refuses_bad_arguments() {
    let h = Harness::new("badargs");
    let out = h.path("x");
    let o = out.to_str().expect("utf8");
    for (args, needle) in [
        (vec!["run", "--scenario", "paper-zero", "--pin", "plant=99", "--out", o], "plant="),
        (vec!["run", "--scenario", "paper-zero", "--pin", "pump=0", "--out", o], "pump"),
        (vec!["run", "--scenario", "paper-zero", "--domain", "a b", "--out", o], "--domain"),
        (
            vec![
                "run",
                "--scenario",
                "paper-zero",
                "--domain",
                "abcdefghijklmnopqrstuvwxy",
                "--out",
                o,
            ],
            "1 to 24",
        ),
        (vec!["run", "--scenario", "paper-zero", "--wait", "nap", "--out", o], "nap"),
    ] {
        let r = h.rotorloop(&args, LIMIT);
        let err = String::from_utf8_lossy(&r.stderr);
        assert_eq!(r.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(needle), "{args:?}: {err}");
    }
}

/// The first states can reach the controller before any reference sample (the reference
/// started late on a loaded machine). Those ticks are answered as skipped, never left
/// unanswered: every torque tick is received, lost or skipped, and the counts add up
/// (found by CI, where one tick 0 went unanswered and uncounted).
#[test]
fn states_before_the_first_reference_are_answered_as_skipped_and_counted() {
    let h = Harness::new("ref-late");
    let out = h.path("rt");
    let mut cmd = std::process::Command::new(ROTORLOOP);
    crate::common::harness::group(&mut cmd)
        .args(["run", "--scenario", "paper-zero", "--duration", "0.5", "--mode", "realtime"])
        .args(["--domain", &h.domain, "--out"])
        .arg(&out)
        .args(["--test-reference-late-ms", "100"])
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped());
    ok(&crate::common::harness::wait_output(cmd.spawn().expect("spawn"), LIMIT));
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    let ticks = s["ticks"].as_u64().expect("ticks");
    let count = |name: &str, what: &str| s["subscribers"][name][what].as_u64().expect(what);
    let (tr, tl) = (count("monitor.torque", "received"), count("monitor.torque", "lost"));
    let (cr, cl) = (count("controller.state", "received"), count("controller.state", "lost"));
    assert_eq!(cr + cl, ticks + 1, "controller states: {cr} + {cl} lost");
    let skipped = s["states_skipped_by_controller"].as_u64().expect("skipped");
    assert_eq!(
        tr + tl + skipped + cl,
        ticks + 1,
        "torque: {tr} + {tl} lost + {skipped} skipped + {cl} states lost"
    );
    // The late start really happened: the controller had states without a reference.
    assert!(s["reference_misses"].as_u64().expect("misses") > 0, "{s}");
    h.assert_no_leftovers();
}

/// The harness reads a child's output while it runs: a child that writes more than a
/// pipe holds (64 KiB) to stdout and to stderr finishes, and nothing is lost. (A pipe
/// nobody read blocked a loaded split run's launcher and roles mid-loop until the test's
/// time limit.)
#[test]
fn the_harness_reads_a_childs_output_while_it_runs() {
    let mut h = Harness::new("pipes");
    let script =
        "head -c 1000000 /dev/zero | tr '\\0' o; head -c 1000000 /dev/zero | tr '\\0' e >&2";
    let child = crate::common::harness::group(&mut std::process::Command::new("sh"))
        .args(["-c", script])
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("spawn sh");
    let o = crate::common::harness::wait_output(child, Duration::from_secs(60));
    assert!(o.status.success());
    assert_eq!((o.stdout.len(), o.stderr.len()), (1_000_000, 1_000_000));
    assert!(o.stdout.iter().all(|b| *b == b'o') && o.stderr.iter().all(|b| *b == b'e'));
    // The background children of `Harness::spawn` are read too.
    let i = h.spawn("sh", &["-c".into(), "head -c 1000000 /dev/zero >&2".into()]);
    assert!(h.wait_all(Duration::from_secs(60))[i].success());
    assert_eq!(h.stderr_of(i).len(), 1_000_000);
}
