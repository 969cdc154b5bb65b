//! The launcher as a supervisor: a role that dies unplanned (a `kill -9` by anyone, a
//! crash) or hangs is restarted by its policy, a restart-intensity breach stops the run
//! naming the role, and an observer that cannot write never stops the loop.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::common::harness::{Harness, Running, assert_same_trace, group, json, ok, wait_output};

const LIMIT: Duration = Duration::from_secs(240);

fn launcher(h: &Harness, out: &Path, args: &[&str]) -> Running {
    let child = group(&mut Command::new(crate::common::harness::ROTORLOOP))
        .args(["run", "--domain", &h.domain, "--out"])
        .arg(out)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn the launcher");
    Running::from(child)
}

/// The pid of `role` started by the launcher `parent` (`rotorloop role ROLE …`), other
/// than `not`, once there is one.
fn role_pid(parent: u32, role: &str, not: Option<u32>) -> u32 {
    let until = Instant::now() + LIMIT;
    loop {
        for e in std::fs::read_dir("/proc").expect("/proc").flatten() {
            let Ok(pid) = e.file_name().to_string_lossy().parse::<u32>() else { continue };
            let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
            // The parent pid is the 2nd field after the parenthesised command name.
            let ppid = stat.rsplit(')').next().and_then(|r| r.split_whitespace().nth(1));
            let cmd = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
            let words: Vec<&[u8]> = cmd.split(|b| *b == 0).collect();
            let is_role = words.windows(2).any(|w| w[0] == b"role" && w[1] == role.as_bytes());
            if ppid == Some(&parent.to_string()) && is_role && Some(pid) != not {
                return pid;
            }
        }
        assert!(Instant::now() < until, "no {role} process of launcher {parent}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Waits until `trace.csv` in `out` has at least `rows` rows (the loop is running).
fn wait_rows(out: &Path, rows: usize) {
    let until = Instant::now() + LIMIT;
    while std::fs::read(out.join("trace.csv"))
        .map_or(0, |t| t.iter().filter(|b| **b == b'\n').count())
        < rows
    {
        assert!(Instant::now() < until, "the run did not get to {rows} rows");
        std::thread::sleep(Duration::from_millis(10));
    }
}

fn kill(pid: u32, sig: libc::c_int) {
    // SAFETY: signals a process of this test's own run.
    unsafe { libc::kill(pid as libc::pid_t, sig) };
}

fn sim_trace(h: &Harness, duration: &str) -> Vec<u8> {
    let out = h.path("sim");
    let args = ["sim", "--scenario", "paper-sinusoid", "--duration", duration, "--no-figures"];
    let mut all: Vec<&str> = args.to_vec();
    all.extend(["--out", out.to_str().expect("utf8")]);
    ok(&h.rotorloop(&all, LIMIT));
    std::fs::read(out.join("trace.csv")).expect("sim trace")
}

fn stderr(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The faults of a report, as `(role, kind)`.
fn fault_kinds(s: &serde_json::Value) -> Vec<(String, String)> {
    let faults = s["faults"].as_array().cloned().unwrap_or_default();
    faults
        .iter()
        .map(|f| (f["role"].as_str().unwrap_or("").into(), f["kind"].as_str().unwrap_or("").into()))
        .collect()
}

/// A `kill -9` by hand of `role` under `rotorloop run` (lockstep): the supervisor starts it
/// again (restart policy on-failure), the run exits 0 with the fault listed as `killed`,
/// and the trace equals the simulator's, bit for bit (outside the monitor's own gap).
fn killed_by_hand_is_restarted(role: &str) {
    let h = Harness::new(&format!("sup-{role}"));
    let out = h.path("run");
    let args = ["--scenario", "paper-sinusoid", "--duration", "60", "--mode", "lockstep"];
    let child = launcher(&h, &out, &args);
    let pid = role_pid(child.id(), role, None);
    wait_rows(&out, 2000);
    kill(pid, libc::SIGKILL);
    let o = wait_output(child, LIMIT);
    assert!(o.status.success(), "exit {}: {}", o.status, stderr(&o));
    assert!(stderr(&o).contains(&format!("restarted {role}")), "{}", stderr(&o));
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    assert!(fault_kinds(&s).contains(&(role.into(), "killed".into())), "{}", s["faults"]);
    let trace = std::fs::read(out.join("trace.csv")).expect("trace");
    if role == "monitor" {
        let gaps = s["monitor_gaps"].as_array().expect("gaps").len();
        let rows = s["trace_rows"].as_u64().expect("rows") + s["rows_lost"].as_u64().expect("lost");
        assert_eq!((gaps, rows), (1, 60_001), "one gap, every tick written or lost");
    } else {
        assert_same_trace(role, &trace, &sim_trace(&h, "60"));
    }
    h.assert_no_leftovers();
}

#[test]
fn controller_killed_by_hand_under_run_is_restarted_and_stays_bit_for_bit() {
    killed_by_hand_is_restarted("controller");
}

#[test]
fn reference_killed_by_hand_under_run_is_restarted_and_stays_bit_for_bit() {
    killed_by_hand_is_restarted("reference");
}

#[test]
fn monitor_killed_by_hand_under_run_is_restarted_and_accounts_its_gap() {
    killed_by_hand_is_restarted("monitor");
}

/// A role restarted more often than `--restart-limit` allows stops the run with exit code
/// 1 and a message naming the role, its last exit and the limit.
#[test]
fn a_restart_intensity_breach_stops_the_run_naming_the_role() {
    let h = Harness::new("sup-limit");
    let out = h.path("run");
    let args = ["--scenario", "paper-zero", "--duration", "60", "--mode", "realtime"];
    // The watchdog at 30 s, not 3 s: this test is about the restart limit, and in one
    // harness round under load the second controller, SIGKILLed by this test, still made
    // no progress and was not reaped 3 s later, so the watchdog judged it hung first
    // (breach "controller hung", not "exited with signal: 9"). How long a SIGKILLed
    // controller takes to exit, and in which states, is now in the failure message.
    let limits = ["--restart-limit", "1/60", "--watchdog-ms", "30000"];
    let child = launcher(&h, &out, &[&args[..], &limits].concat());
    let first = role_pid(child.id(), "controller", None);
    wait_rows(&out, 300);
    kill(first, libc::SIGKILL);
    let second = role_pid(child.id(), "controller", Some(first));
    std::thread::sleep(Duration::from_millis(300));
    kill(second, libc::SIGKILL);
    let exit = crate::common::harness::exit_of(second);
    let o = wait_output(child, LIMIT);
    assert_eq!(o.status.code(), Some(1), "{exit}: {}", stderr(&o));
    let err = stderr(&o);
    assert!(
        err.contains("controller exited with signal: 9")
            && err.contains("1/60")
            && err.contains("the run was stopped"),
        "{exit}: {err}"
    );
    h.assert_no_leftovers();
}

/// A monitor whose file writes are held up (here 5 s before its first write, the stand-in
/// for a `write(2)` blocked by disk writeback, which under the repeat harness once held a
/// monitor long enough for a 2 s watchdog to kill it) goes on taking rows: its files are
/// written by a thread of their own, and its progress mark is the rows taken. Nobody is
/// judged hung and the trace is the simulator's. Fails with the writes in the monitor's
/// loop (`IN_FLIGHT_MAX` 0: every poll waits for its write): the monitor is killed.
#[test]
fn a_monitor_whose_writes_are_held_up_is_not_hung() {
    let h = Harness::new("sup-slowdisk");
    let out = h.path("run");
    let args = ["--scenario", "paper-sinusoid", "--duration", "60", "--mode", "lockstep"];
    let extra = ["--test-files-stall-ms", "5000", "--watchdog-ms", "2000"];
    let o = wait_output(launcher(&h, &out, &[&args[..], &extra].concat()), LIMIT);
    assert!(o.status.success(), "exit {}: {}", o.status, stderr(&o));
    assert!(!stderr(&o).contains("hung"), "{}", stderr(&o));
    let s = json(&out.join("summary.json"));
    assert_eq!(fault_kinds(&s), [], "nobody was judged hung");
    assert_eq!(s["monitor_restarts"], 0);
    let trace = std::fs::read(out.join("trace.csv")).expect("trace");
    assert_same_trace("slow disk", &trace, &sim_trace(&h, "60"));
    h.assert_no_leftovers();
}

/// A controller stopped between writing its resume slot and sending its answer looks, by
/// its mark, as if it had answered: in lockstep the watchdog then blamed the plant waiting
/// for that answer, and killed and restarted it every 10 s while the run never ended (once
/// in 20 rounds of the repeat harness). A stopped role of the loop is now the one to
/// blame: the controller is judged hung and restarted, it re-sends that very answer, and
/// the trace is the simulator's. Without the rule this test runs into its limit.
#[test]
fn a_controller_stopped_between_its_slot_and_its_send_is_the_one_judged_hung() {
    let h = Harness::new("sup-slotstop");
    let out = h.path("run");
    let args = ["--scenario", "paper-sinusoid", "--duration", "60", "--mode", "lockstep"];
    let extra = ["--test-stop-before-send-at", "5000", "--watchdog-ms", "2000"];
    let o = wait_output(launcher(&h, &out, &[&args[..], &extra].concat()), LIMIT);
    assert!(o.status.success(), "exit {}: {}", o.status, stderr(&o));
    let s = json(&out.join("summary.json"));
    let kinds = fault_kinds(&s);
    let want = [("controller".to_owned(), "stop".to_owned()), ("controller".into(), "hang".into())];
    assert_eq!(kinds, want, "{}", stderr(&o));
    let trace = std::fs::read(out.join("trace.csv")).expect("trace");
    assert_same_trace("stopped before its send", &trace, &sim_trace(&h, "60"));
    h.assert_no_leftovers();
}

/// A controller that hangs (SIGSTOP, no SIGCONT) in lockstep holds the loop up: the
/// watchdog kills it after `--watchdog-ms` without progress, the supervisor restarts it,
/// and the trace is still the simulator's, bit for bit.
#[test]
fn a_hung_controller_is_killed_by_the_watchdog_and_restarted_bit_for_bit() {
    let h = Harness::new("sup-hang");
    let out = h.path("run");
    let args = ["--scenario", "paper-sinusoid", "--duration", "120", "--mode", "lockstep"];
    // 2 s, not 500 ms: under a busy loop per core and the I/O of other tests, the monitor
    // (writing the 120 s lockstep trace as fast as the loop makes it) once made no
    // progress for 500 ms with rows waiting, and a 500 ms watchdog rightly judged it hung
    // too; this test is about whom the watchdog blames for a stopped controller.
    let extra = ["--fault", "controller:stop@0.5", "--watchdog-ms", "2000"];
    let o = wait_output(launcher(&h, &out, &[&args[..], &extra].concat()), LIMIT);
    assert!(o.status.success(), "exit {}: {}", o.status, stderr(&o));
    let s = json(&out.join("summary.json"));
    let kinds = fault_kinds(&s);
    assert!(kinds.contains(&("controller".into(), "stop".into())), "{kinds:?}");
    assert!(kinds.contains(&("controller".into(), "hang".into())), "{kinds:?}");
    assert_eq!(kinds.len(), 2, "nobody else was blamed: {kinds:?}");
    assert!(stderr(&o).contains("hung; killed"), "{}", stderr(&o));
    let trace = std::fs::read(out.join("trace.csv")).expect("trace");
    // Shown with a failure (captured otherwise): under load the trace once began at tick
    // 22732. The flight part said why: the rings had come round before a mover slowed by
    // writeback copied them (now lockstep waits for it: faults::lockstep_waits_for_a_slow…).
    eprintln!(
        "trace_rows {} rows_lost {} flight {}\nstderr:\n{}",
        s["trace_rows"],
        s["rows_lost"],
        s["flight"],
        stderr(&o)
    );
    assert_same_trace("hang", &trace, &sim_trace(&h, "120"));
    h.assert_no_leftovers();
}

/// A controller stopped and continued in real time before the watchdog's limit: the plant
/// holds, then enters safe mode, control resumes after the SIGCONT, and the watchdog did
/// nothing.
#[test]
fn a_controller_stopped_and_continued_in_real_time_recovers_without_the_watchdog() {
    let h = Harness::new("sup-cont");
    let out = h.path("run");
    let args = ["--scenario", "paper-sinusoid", "--duration", "4", "--mode", "realtime"];
    let extra = ["--fault", "controller:stop@1:cont@1.4", "--watchdog-ms", "5000"];
    let o = wait_output(launcher(&h, &out, &[&args[..], &extra].concat()), LIMIT);
    assert!(o.status.success(), "exit {}: {}", o.status, stderr(&o));
    let s = json(&out.join("summary.json"));
    assert_eq!(fault_kinds(&s), [("controller".to_owned(), "stop".to_owned())]);
    assert!(s["faults"][0]["detail"].as_str().expect("detail").contains("SIGCONT"));
    assert!(s["safe_mode_ticks"].as_u64().expect("safe") > 0, "the plant entered safe mode");
    assert!(s["faults"][0]["ticks_to_first_fresh_torque"].as_u64().is_some(), "control resumed");
    h.assert_no_leftovers();
}

/// The output directory on a 2 MiB tmpfs fills up about a second into a real-time run: the
/// loop still completes every tick (exit 0), the monitor reports from which tick the
/// trace is incomplete, `summary.json` and the histograms land in its fallback
/// directory, and the flight records, which cannot be moved there, stay whole where they
/// were recorded, named in the report.
/// Needs `mount` (root with CAP_SYS_ADMIN); skipped with a message elsewhere.
#[test]
fn a_full_disk_never_stops_the_loop() {
    let h = Harness::new("sup-full");
    let Some(disk) = crate::common::harness::SmallDisk::mount(&h, "full") else {
        eprintln!("skipped: cannot mount a tmpfs here (not root, or no CAP_SYS_ADMIN)");
        return;
    };
    let out = disk.path().to_owned();
    // --force: the launcher's estimate (about 19 MB) says the 2 MiB disk cannot hold the
    // run, and refuses it without.
    let args = ["--scenario", "paper-sinusoid", "--duration", "6", "--mode", "realtime", "--force"];
    let o = wait_output(launcher(&h, &out, &args), LIMIT);
    assert!(o.status.success(), "exit {}: {}", o.status, stderr(&o));
    // The fallback's name is random (`$TMPDIR/rotorloop-report-DOMAIN-…`): found by its prefix.
    let prefix = rotorloop_monitor::recording::fallback_prefix(&h.domain);
    let fallbacks: Vec<PathBuf> = std::fs::read_dir(std::env::temp_dir())
        .expect("tmp")
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
        .map(|e| e.path())
        .collect();
    let summary = std::iter::once(out.join("summary.json"))
        .chain(fallbacks.iter().map(|f| f.join("summary.json")))
        .find(|p| p.exists())
        .unwrap_or_else(|| panic!("no summary.json anywhere: {}", stderr(&o)));
    let s = json(&summary);
    assert_eq!(s["completed"], true);
    assert_eq!(s["ticks"], 6000);
    // The flight records (on /dev/shm during the run) are whole, but cannot be moved onto
    // the full disk: they stay where they are, and the report says where.
    let flight = PathBuf::from(s["flight"]["dir"].as_str().expect("the records' place"));
    assert!(flight.join("plant-state.flight").exists(), "{s}");
    assert!(stderr(&o).contains("flight records stay in"), "{}", stderr(&o));
    let _ = std::fs::remove_dir_all(&flight);
    let from = s["trace_incomplete_from_tick"].as_u64().expect("the trace is reported incomplete");
    assert!(from < 6000, "{from}");
    assert!(!s["storage_errors"].as_array().expect("errors").is_empty());
    assert_eq!(
        s["trace_rows"].as_u64().expect("rows") + s["rows_lost"].as_u64().expect("lost"),
        6001
    );
    let hgrm_dir = s["report_dir"].as_str().map_or(out.clone(), PathBuf::from);
    assert!(
        hgrm_dir.join("sense_to_actuate.hgrm").exists(),
        "histograms in {}",
        hgrm_dir.display()
    );
    for f in &fallbacks {
        let _ = std::fs::remove_dir_all(f);
    }
    h.assert_no_leftovers();
}
