//! Incidents of real-time runs (`rotorloop run` → `incidents.csv`, `rotorloop explain`):
//! a plant stopped is a simulator stall that cost a deviation and recovered, an injected
//! delay is named as such, a monitor kill costs exactly 0°, a busy real-time process on
//! the controller's core is seen by the kernel's figures, and `explain` gives the run's
//! files again.

use std::path::{Path, PathBuf};
use std::time::Duration;

use crate::common::harness::{Harness, json, ok, pid_of_role};

const LIMIT: Duration = Duration::from_secs(120);

/// One row of `incidents.csv`, by column name.
pub(crate) struct Row(std::collections::BTreeMap<String, String>);

impl Row {
    pub(crate) fn get(&self, col: &str) -> &str {
        self.0.get(col).map_or("", String::as_str)
    }

    fn f64(&self, col: &str) -> Option<f64> {
        self.get(col).parse().ok()
    }
}

/// A CSV line's fields (double quotes group, `""` is a quote).
fn fields(line: &str) -> Vec<String> {
    let (mut out, mut cur, mut quoted) = (Vec::new(), String::new(), false);
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        match (c, quoted) {
            ('"', true) if chars.peek() == Some(&'"') => {
                cur.push('"');
                chars.next();
            }
            ('"', _) => quoted = !quoted,
            (',', false) => out.push(std::mem::take(&mut cur)),
            _ => cur.push(c),
        }
    }
    out.push(cur);
    out
}

/// The rows of `out/incidents.csv`.
pub(crate) fn incidents(out: &Path) -> Vec<Row> {
    let text = std::fs::read_to_string(out.join("incidents.csv")).expect("incidents.csv");
    let mut lines = text.lines();
    let header = fields(lines.next().expect("header"));
    lines.map(|l| Row(header.iter().cloned().zip(fields(l)).collect())).collect()
}

fn describe(rows: &[Row]) -> String {
    rows.iter().map(|r| format!("{:?}\n", r.0)).collect()
}

/// A real-time run of paper-zero with `extra` arguments.
fn realtime(h: &Harness, name: &str, duration: &str, extra: &[&str]) -> PathBuf {
    let out = h.path(name);
    let mut args = vec!["run", "--scenario", "paper-zero", "--duration", duration];
    args.extend(["--mode", "realtime", "--domain", &h.domain, "--quiet"]);
    args.extend(["--out", out.to_str().expect("utf8")]);
    args.extend(extra);
    ok(&h.rotorloop(&args, LIMIT));
    out
}

/// The longest incident that holds `at_s` (± `slack_s`) and whose cause is `role`.
fn incident_at<'a>(rows: &'a [Row], at_s: f64, slack_s: f64, role: &str) -> &'a Row {
    let duration = |r: &Row| r.f64("duration_s").expect("duration_s");
    rows.iter()
        .filter(|r| {
            let s = r.f64("start_s").expect("start_s");
            r.get("cause_role") == role && s <= at_s + slack_s && s + duration(r) >= at_s - slack_s
        })
        .max_by(|a, b| duration(a).total_cmp(&duration(b)))
        .unwrap_or_else(|| panic!("no incident of {role} at {at_s} s:\n{}", describe(rows)))
}

/// The incident of `role` that the fault schedule's fault caused, which must start within
/// 100 ms of `at_s` (the launcher's fault clock starts when it sees tick 0, a few ms
/// after it, and later on a loaded machine).
fn scheduled_fault<'a>(rows: &'a [Row], at_s: f64, role: &str) -> &'a Row {
    let r = rows
        .iter()
        .find(|r| {
            r.get("cause_role") == role && r.get("evidence").contains("by the fault schedule")
        })
        .unwrap_or_else(|| panic!("no incident of {role}'s fault:\n{}", describe(rows)));
    let start = r.f64("start_s").expect("start_s");
    assert!((start - at_s).abs() < 0.1, "starts at {start} s, not {at_s} s: {:?}", r.0);
    r
}

#[test]
fn a_stopped_plant_is_a_simulator_stall_that_cost_a_deviation_and_recovered() {
    let h = Harness::new("inc-stall");
    // Sixteen seconds: the deviation of a stall at 4 s takes some seconds to fall below a
    // tenth of its peak (the loop converges on its reference: about 9 s here).
    let out = realtime(&h, "stall", "16", &["--fault", "plant:stop@4:cont@4.03"]);
    let rows = incidents(&out);
    let r = scheduled_fault(&rows, 4.0, "plant");
    assert_eq!(r.get("kind"), "simulator stall", "{:?}", r.0);
    let peak = r.f64("peak_deviation_deg").expect("a computed cost");
    assert!(peak > 0.0, "{:?}", r.0);
    let recovery = r.f64("recovery_s").unwrap_or_else(|| panic!("no recovery: {:?}", r.0));
    assert!(recovery > 0.0, "{:?}", r.0);
    // The fault report carries the same cost (serde_json's default float parsing may be
    // one ulp off the number written: it once read ...016 for ...015).
    let s = json(&out.join("summary.json"));
    let f = &s["faults"][0];
    let reported = f["peak_deviation_deg"].as_f64().expect("the fault's cost");
    assert!((reported - peak).abs() <= 1e-12 * peak, "{reported} != {peak}: {f}");
    assert!(s["incidents"]["count"].as_u64().expect("count") >= 1, "{s}");
    // The costing stepped within its share of the run: 16 s, a tick's more at most.
    let stepped = s["incidents"]["counterfactual_ticks"].as_u64().expect("stepped");
    let share = 16_001 * rotorloop::pipeline::incidents::COST_TICKS_PER_S / 1000;
    assert!(stepped > 0 && stepped <= share, "{stepped} of {share}: {}", s["incidents"]);
    // Every answer was the law's, bit for bit: the counterfactual starts exactly.
    let [same, computed] = [0, 1].map(|i| s["incidents"]["law_reproduced"][i].as_u64());
    assert_eq!(same, computed, "{}", s["incidents"]);
    h.assert_no_leftovers();
}

#[test]
fn an_injected_controller_delay_is_named_and_a_monitor_kill_costs_nothing() {
    let h = Harness::new("inc-delay");
    let out = realtime(
        &h,
        "delay",
        "6",
        &["--fault", "controller:delay@4=0.02:until@4.5", "--fault", "monitor:kill@2:restart@2.5"],
    );
    let rows = incidents(&out);
    let d = incident_at(&rows, 4.0, 0.1, "controller");
    assert_eq!(d.get("kind"), "injected delay", "{:?}", d.0);
    assert!(d.f64("peak_deviation_deg").expect("cost") > 0.0, "{:?}", d.0);
    let m = scheduled_fault(&rows, 2.0, "monitor");
    assert_eq!(m.get("kind"), "fault", "{:?}", m.0);
    assert_eq!(m.f64("peak_deviation_deg"), Some(0.0), "a monitor kill cost: {:?}", m.0);
    let s = json(&out.join("summary.json"));
    let monitor = s["faults"].as_array().expect("faults").iter().find(|f| f["role"] == "monitor");
    let monitor = monitor.unwrap_or_else(|| panic!("{}", s["faults"]));
    assert_eq!(monitor["peak_deviation_deg"].as_f64(), Some(0.0), "{monitor}");
    // `explain` gives the same files again.
    let csv = std::fs::read(out.join("incidents.csv")).expect("csv");
    let md = std::fs::read(out.join("incidents.md")).expect("md");
    std::fs::remove_file(out.join("incidents.csv")).expect("rm");
    ok(&h.rotorloop(&["explain", out.to_str().expect("utf8")], LIMIT));
    assert!(std::fs::read(out.join("incidents.csv")).expect("again") == csv, "csv differs");
    assert!(std::fs::read(out.join("incidents.md")).expect("again") == md, "md differs");
    h.assert_no_leftovers();
}

/// The busy thread's name (its `comm` in the scheduler trace).
const BUSY: &str = "busy-fifo";

/// Moves the calling thread to `cpu` at SCHED_FIFO 50 and spins there for `ns` of the
/// monotonic clock (counted from then: however late a loaded machine let it start).
fn busy_fifo(cpu: usize, ns: u64) -> std::io::Result<()> {
    // SAFETY: affinity and policy of the calling thread (0), with valid arguments.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        libc::CPU_SET(cpu, &mut set);
        if libc::sched_setaffinity(0, size_of::<libc::cpu_set_t>(), &set) != 0 {
            return Err(std::io::Error::last_os_error());
        }
        let p = libc::sched_param { sched_priority: 50 };
        if libc::sched_setscheduler(0, libc::SCHED_FIFO, &p) != 0 {
            return Err(std::io::Error::last_os_error());
        }
    }
    let start = std::time::Instant::now();
    while start.elapsed() < Duration::from_nanos(ns) {
        std::hint::spin_loop();
    }
    Ok(())
}

#[test]
fn a_busy_realtime_process_on_the_controllers_core_is_named_by_the_kernels_figures() {
    // SAFETY: geteuid reads this process's effective user id.
    let root = unsafe { libc::geteuid() } == 0;
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    if !root || cores < 2 {
        eprintln!("skipped: needs root (SCHED_FIFO, tracefs) and 2 cores");
        return;
    }
    let tracefs = Path::new("/sys/kernel/tracing").is_dir();
    if !tracefs {
        eprintln!("skipped: the kernel has no tracefs (/sys/kernel/tracing)");
        return;
    }
    let h = Harness::alone("inc-busy");
    let out = h.path("busy");
    let pins = "plant=0,reference=0,monitor=0,controller=1";
    let args = [
        "run",
        "--scenario",
        "paper-zero",
        "--duration",
        "6",
        "--mode",
        "realtime",
        "--pin",
        pins,
        "--domain",
        &h.domain,
        "--quiet",
        "--trace-sched",
        "--out",
    ];
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_rotorloop"));
    cmd.args(args).arg(&out);
    cmd.stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::piped());
    let run = crate::common::harness::group(&mut cmd).spawn().expect("rotorloop run");
    // Once the scheduler trace has seen the controller run (so both the loop and the
    // trace are on, however slow the start), and a second later: 50 ms of a SCHED_FIFO
    // busy loop on the controller's core.
    let until = std::time::Instant::now() + LIMIT;
    loop {
        let trace = std::fs::read_to_string(out.join("sched-trace.txt")).unwrap_or_default();
        let seen = pid_of_role(&h.domain, "controller")
            .is_some_and(|pid| trace.contains(&format!("next_pid={pid} ")));
        if seen {
            break;
        }
        assert!(std::time::Instant::now() < until, "the run's trace never saw the controller");
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_secs(1));
    let busy = std::thread::Builder::new().name(BUSY.into()).spawn(|| busy_fifo(1, 50_000_000));
    busy.expect("busy thread").join().expect("busy thread").expect("SCHED_FIFO on CPU 1");
    let o = crate::common::harness::wait_output(run, LIMIT);
    ok(&o);
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    let rows = incidents(&out);
    // The controller's incident the busy thread caused (a loaded machine may cause more).
    let trace = std::fs::read_to_string(out.join("sched-trace.txt")).unwrap_or_default();
    let named = format!("ran instead on CPU 1 (sched trace): {BUSY} (pid");
    let r = rows
        .iter()
        .find(|r| r.get("cause_role") == "controller" && r.get("evidence").contains(&named))
        .unwrap_or_else(|| {
            panic!(
                "no incident of the controller names {BUSY} first:\n{}\nsched-trace.txt: {} \
                 lines, {} of `{BUSY}`; stderr:\n{stderr}",
                describe(&rows),
                trace.lines().count(),
                trace.lines().filter(|l| l.contains(&format!("next_comm={BUSY}"))).count()
            )
        });
    let ev = r.get("evidence");
    let waited: f64 = ev
        .split("runnable, not running for ")
        .nth(1)
        .and_then(|x| x.split(' ').next())
        .and_then(|x| x.parse().ok())
        .unwrap_or_else(|| panic!("no run-queue wait in {:?}", r.0));
    assert!(waited >= 20.0, "the controller waited {waited} ms for its core: {:?}", r.0);
    assert!(
        !std::fs::read_to_string("/proc/mounts").expect("mounts").contains("rotorloop-"),
        "nothing of the trace left mounted"
    );
    let instances = std::fs::read_dir("/sys/kernel/tracing/instances")
        .map(|d| {
            d.flatten().filter(|e| e.file_name().to_string_lossy().contains(&h.domain)).count()
        })
        .unwrap_or(0);
    assert_eq!(instances, 0, "the run's tracefs instance is removed");
    h.assert_no_leftovers();
}

#[test]
fn a_paused_world_clock_is_replayed_byte_for_byte_and_its_stall_named() {
    let h = Harness::new("inc-pause");
    let args = ["--plant-stall", "pause", "--fault", "plant:stop@1:cont@1.05"];
    let out = realtime(&h, "pause", "3", &args);
    let s = json(&out.join("summary.json"));
    assert_eq!(s["plant_stall"], "pause", "{s}");
    assert_eq!(s["trace_rows"], 3001, "{s}");
    let rows = incidents(&out);
    let r = scheduled_fault(&rows, 1.0, "plant");
    assert_eq!(r.get("kind"), "simulator stall", "{:?}", r.0);
    // Named from the fault schedule (the kernel's view of a stop is the stopped plant's
    // test: a stop this short can fall between two samples of a starved sampler).
    let ev = r.get("evidence");
    assert!(ev.contains("plant stopped (SIGSTOP) by the fault schedule"), "{:?}", r.0);
    // The grid moved on from the plant's wake: what took effect in each tick, and when,
    // is what `timing.csv` recorded, so a replay gives the run's trace byte for byte.
    let again = h.path("replay");
    let replayed = ok(&h.rotorloop(
        &["sim", "--replay", out.to_str().expect("utf8"), "--out", again.to_str().expect("utf8")],
        LIMIT,
    ));
    assert!(replayed.contains("identical byte for byte"), "{replayed}");
    h.assert_no_leftovers();
}
