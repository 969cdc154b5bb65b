//! Hostile input and who may touch a run: corrupted samples on the wire, a second
//! process for a role that runs, a process of another sample layout, and a second OS
//! user.

use std::os::unix::fs::PermissionsExt;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use crate::common::harness::{Harness, ROTORLOOP, json, ok, timing_rows, wait_output};
use crate::common::old_layout::StateSampleV2;
use rotorloop_common::graph::Topic;
use rotorloop_common::ipc::IpcError;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::wire::{LAYOUT_VERSION, StateSample};

mod link;
mod ticks;
mod viewer;

const LIMIT: Duration = Duration::from_secs(120);

fn lockstep(h: &Harness, name: &str, extra: &[&str]) -> PathBuf {
    let out = h.path(name);
    let mut args = vec![
        "run",
        "--scenario",
        "paper-zero",
        "--duration",
        "1",
        "--mode",
        "lockstep",
        "--quiet",
        "--domain",
        &h.domain,
        "--out",
        out.to_str().expect("utf8"),
    ];
    args.extend_from_slice(extra);
    ok(&h.rotorloop(&args, LIMIT));
    out
}

/// Each kind of corrupted sample (NaN, infinity, absurd magnitude, an attitude off SO(3))
/// on each topic is rejected by every receiver, counted, reported as a fault event, and
/// answered safely: the plant holds the last good torque, the controller skips the tick,
/// the monitor drops the row. No NaN ever reaches the plant's state.
#[test]
fn every_kind_of_corrupted_sample_is_rejected_counted_and_never_reaches_the_state() {
    let h = Harness::new("corrupt");
    let corrupt = [
        "controller:nan@100t",
        "controller:inf@150t",
        "controller:huge@200t",
        "plant:nan@300t",
        "plant:skew@350t",
        "plant:huge@400t",
        "reference:inf@500t",
        "reference:skew@550t",
        "reference:huge@600t",
    ];
    let extra: Vec<&str> = corrupt.iter().flat_map(|c| ["--corrupt", c]).collect();
    let out = lockstep(&h, "run", &extra);
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    let rejected = &s["wire_rejected"];
    for (receiver, n) in [
        ("plant.torque", 3),
        ("controller.state", 3),
        ("controller.reference", 3),
        ("monitor.torque", 3),
        ("monitor.state", 3),
        ("monitor.reference", 3),
    ] {
        assert_eq!(rejected[receiver], n, "{receiver}: {rejected}");
    }
    // Three rejected torques and three skipped ticks (answers to rejected states); a
    // rejected reference is replaced by the propagated last one, which costs no torque.
    assert_eq!(s["misses"], 6);
    assert_eq!(s["rows_lost"], 6, "rows of rejected states and references are not written");
    let events = s["wire_faults"].as_array().expect("events");
    let seen: Vec<(String, u64, String)> = events
        .iter()
        .map(|e| {
            (
                e["topic"].as_str().expect("present").to_owned(),
                e["tick"].as_u64().expect("present"),
                e["kind"].as_str().expect("present").to_owned(),
            )
        })
        .collect();
    for (topic, tick, kind) in [
        ("torque", 100, "non-finite"),
        ("torque", 150, "non-finite"),
        ("torque", 200, "absurd"),
        ("state", 300, "non-finite"),
        ("state", 350, "non-orthonormal"),
        ("state", 400, "absurd"),
        ("reference", 500, "non-finite"),
        ("reference", 550, "non-orthonormal"),
        ("reference", 600, "absurd"),
    ] {
        assert!(
            seen.contains(&(topic.to_owned(), tick, kind.to_owned())),
            "no {kind} {topic} event at tick {tick} in {seen:?}"
        );
    }
    assert!(
        events.iter().all(|e| e["detail"].as_str().expect("present").contains(".")),
        "field named"
    );

    // Hold: over the tick after a rejected torque k, torque k−1 was applied.
    let applied = timing_rows(&out);
    for k in [100i64, 150, 200, 300, 350, 400] {
        let row = applied.iter().find(|r| r.tick == k + 1).expect("row");
        assert_eq!(row.applied, k - 1, "tick {k}: the plant should hold torque {}", k - 1);
    }
    assert_state_columns_finite(&out);
    h.assert_no_leftovers();
}

/// No NaN or infinity anywhere in the state columns (`R…`, `W…`, `h…`) of a run's trace.
fn assert_state_columns_finite(out: &Path) {
    let trace = std::fs::read_to_string(out.join("trace.csv")).expect("trace");
    let header: Vec<&str> = trace.lines().next().expect("present").split(',').collect();
    for line in trace.lines().skip(1) {
        for (name, v) in header.iter().zip(line.split(',')) {
            if name.starts_with('R') || name.starts_with('W') || name.starts_with('h') {
                let v: f64 = v.parse().expect("number");
                assert!(v.is_finite(), "{name} = {v} in row {line}");
            }
        }
    }
}

/// Torques rejected for longer than `--hold-ticks` put the plant in safe mode (zero
/// torque), and the first good torque brings control back.
#[test]
fn rejected_torques_beyond_the_hold_put_the_plant_in_safe_mode_until_a_good_one() {
    let h = Harness::new("corrupt-safe");
    let mut extra: Vec<String> = vec!["--hold-ticks".into(), "5".into()];
    // 100..=110, and the last answer of the run (a rejected row must not stall the
    // monitor at the end).
    for k in (100..=110).chain([999]) {
        extra.extend(["--corrupt".into(), format!("controller:nan@{k}t")]);
    }
    let extra: Vec<&str> = extra.iter().map(String::as_str).collect();
    let out = lockstep(&h, "run", &extra);
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    assert_eq!(s["wire_rejected"]["plant.torque"], 12);
    assert_eq!(s["misses"], 12);
    assert_eq!(s["safe_mode_ticks"], 6, "ticks 6..=11 of the 11 rejected ones");
    let applied = timing_rows(&out);
    let at = |k: i64| applied.iter().find(|r| r.tick == k).expect("row").applied;
    assert_eq!(at(101), 99, "holding");
    assert_eq!(at(111), -1, "safe mode: no torque applied");
    assert_eq!(at(112), 111, "control back with the first good torque");
    h.assert_no_leftovers();
}

/// The pid of `role` from the launcher's rss.csv.
fn pid_of(out: &Path, role: &str) -> Option<String> {
    let text = std::fs::read_to_string(out.join("rss.csv")).ok()?;
    text.lines()
        .filter_map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f.get(1) == Some(&role)).then(|| f[2].to_owned())
        })
        .next()
}

fn start_realtime_run(h: &mut Harness, out: &Path, seconds: &str) -> usize {
    let args: Vec<String> = [
        "run",
        "--scenario",
        "paper-zero",
        "--duration",
        seconds,
        "--mode",
        "realtime",
        "--quiet",
        "--domain",
        &h.domain,
        "--out",
        out.to_str().expect("present"),
    ]
    .iter()
    .map(|s| (*s).to_owned())
    .collect();
    let i = h.spawn(ROTORLOOP, &args);
    // Running once every role has a pid and the state service exists.
    let until = Instant::now() + Duration::from_secs(30);
    while ["plant", "controller", "reference", "monitor"].iter().any(|r| pid_of(out, r).is_none()) {
        assert!(Instant::now() < until, "the run did not start");
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_millis(500));
    i
}

fn role_by_hand(h: &Harness, role: &str, extra: &[&str]) -> Output {
    let mut args = vec!["role", role, "--domain", &h.domain, "--scenario", "paper-zero"];
    args.extend_from_slice(&["--mode", "realtime"]);
    args.extend_from_slice(extra);
    h.rotorloop(&args, LIMIT)
}

/// A second process of any role in a running domain is refused with a message naming the
/// domain and the pid of the running one; the run goes on unaffected.
#[test]
fn a_second_process_of_a_running_role_is_refused_naming_the_domain_and_its_pid() {
    let mut h = Harness::new("dup");
    let out = h.path("run");
    let run = start_realtime_run(&mut h, &out, "5");
    let monitor_out = h.path("second-monitor");
    for role in ["plant", "controller", "reference", "monitor"] {
        let extra: Vec<&str> = if role == "monitor" {
            vec!["--out", monitor_out.to_str().expect("present")]
        } else {
            vec![]
        };
        let o = role_by_hand(&h, role, &extra);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "a second {role} started: {err}");
        let pid = pid_of(&out, role).expect("pid");
        let want = format!("role `{role}` is already running in domain `{}` (pid {pid})", h.domain);
        assert!(err.contains(&want), "{role}: {err}");
    }
    assert!(!monitor_out.exists(), "the refused monitor must not create its output");
    let status = h.wait_all(LIMIT);
    assert!(status[run].success(), "the first run failed");
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    assert_eq!(s["trace_rows"], 5001);
    assert_eq!(s["rows_lost"], 0);
    h.assert_no_leftovers();
}

/// A process of another sample layout version is refused with a message naming both
/// versions, in both directions: our role meeting an old build's service, and an old
/// build's type meeting ours.
#[test]
fn a_process_of_another_layout_version_is_refused_naming_both_versions() {
    let h = Harness::new("skew");
    let domain = Domain::new(&h.domain).expect("domain");
    {
        // An "old build" owns the state service.
        let node = domain.node("plant").expect("node");
        let _old = domain.outbox::<StateSampleV2>(&node, Topic::State).expect("old service");
        let o = role_by_hand(&h, "controller", &[]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success());
        assert!(
            err.contains("rotorloop::StateSample_v2")
                && err.contains("layout v2")
                && err.contains(&format!("layout v{LAYOUT_VERSION}")),
            "{err}"
        );
    }
    {
        // Our build owns it; the "old build" is refused.
        let node = domain.node("plant").expect("node");
        let _ours = domain.outbox::<StateSample>(&node, Topic::State).expect("service");
        let other = domain.node("monitor").expect("node");
        match domain.inbox::<StateSampleV2>(&other, Topic::State, 1, false) {
            Err(e @ IpcError::LayoutSkew { .. }) => {
                let msg = e.to_string();
                assert!(
                    msg.contains("layout v2") && msg.contains(&format!("layout v{LAYOUT_VERSION}")),
                    "{msg}"
                );
            }
            other => panic!("expected a layout skew error, got {other:?}"),
        }
    }
    domain.cleanup().expect("cleanup");
    h.assert_no_leftovers();
}

/// Creates a system user for the test and deletes it on drop.
pub(crate) struct TempUser {
    pub(crate) name: String,
    pub(crate) uid: u32,
}

impl TempUser {
    /// A second OS user for test `test`, or `None` once the reason it is skipped is said
    /// (not root, no `useradd`).
    pub(crate) fn for_test(test: &str) -> Option<Self> {
        Self::create().map_err(|why| eprintln!("SKIPPED {test}: {why}")).ok()
    }

    pub(crate) fn create() -> Result<Self, String> {
        // SAFETY: plain getter.
        if unsafe { libc::geteuid() } != 0 {
            return Err("not root: cannot create a second OS user".into());
        }
        // One user per test: tests of one binary run in parallel, and a name shared by
        // two would be deleted under the other's feet.
        static NEXT: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let name = format!("rlprobe{}x{n}", std::process::id() % 100_000);
        let st = Command::new("useradd")
            .args(["--system", "--no-create-home", "--shell", "/usr/sbin/nologin", &name])
            .stderr(Stdio::piped())
            .output()
            .map_err(|e| format!("useradd: {e}"))?;
        if !st.status.success() {
            return Err(format!("useradd failed: {}", String::from_utf8_lossy(&st.stderr)));
        }
        let id = Command::new("id").args(["-u", &name]).output().map_err(|e| e.to_string())?;
        let uid = String::from_utf8_lossy(&id.stdout).trim().parse().map_err(|_| "id -u")?;
        Ok(Self { name, uid })
    }
}

impl Drop for TempUser {
    fn drop(&mut self) {
        let _ = Command::new("userdel").arg(&self.name).status();
    }
}

fn probe(binary: &Path, domain: &str, uid: Option<u32>) -> String {
    let mut cmd = Command::new(binary);
    crate::common::harness::group(&mut cmd);
    cmd.args(["role", "probe", "--domain", domain])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    if let Some(uid) = uid {
        cmd.uid(uid).gid(uid); // std drops the supplementary groups when it changes uid
    }
    let out = wait_output(cmd.spawn().expect("probe"), LIMIT);
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// A run's shared memory and files belong to its user alone: a second OS user can neither
/// create a node in the domain, subscribe to the state, publish a torque, nor open any of
/// its shared-memory files; the owner can (the same probe, as a control). Skipped, with
/// the reason, where a second user cannot be created.
#[test]
fn another_os_user_can_neither_subscribe_to_the_state_nor_publish_a_torque() {
    let Some(user) = TempUser::for_test("another_os_user_…") else { return };
    let mut h = Harness::new("users");
    // The other user needs an executable it may reach.
    let bin_dir = tempfile::tempdir().expect("tempdir");
    std::fs::set_permissions(bin_dir.path(), std::fs::Permissions::from_mode(0o755))
        .expect("present");
    let binary = bin_dir.path().join("rotorloop");
    std::fs::copy(ROTORLOOP, &binary).expect("copy binary");
    std::fs::set_permissions(&binary, std::fs::Permissions::from_mode(0o755)).expect("present");

    let out = h.path("run");
    let run = start_realtime_run(&mut h, &out, "4");
    let owner = probe(&binary, &h.domain, None);
    let other = probe(&binary, &h.domain, Some(user.uid));
    let status = h.wait_all(LIMIT);

    assert!(owner.contains("subscribe state: granted (received tick"), "control:\n{owner}");
    assert!(owner.contains("for write: granted"), "control:\n{owner}");
    let shm_lines = other.lines().filter(|l| l.starts_with("open /dev/shm/")).count();
    assert!(shm_lines >= 10, "the probe should have found the run's files:\n{other}");
    for l in other.lines() {
        assert!(l.contains(": refused ("), "user {} got: {l}\n{other}", user.name);
    }
    for what in ["node:", "subscribe state:", "publish torque:"] {
        assert!(other.lines().any(|l| l.starts_with(what)), "{what} missing:\n{other}");
    }
    assert!(status[run].success(), "the run failed");
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    h.assert_no_leftovers();
}

/// The modes of a running domain's files: owner-only, nothing for group or others.
#[test]
fn a_running_domains_files_are_owner_only() {
    let mut h = Harness::new("modes");
    let out = h.path("run");
    let run = start_realtime_run(&mut h, &out, "2");
    let prefix = format!("rl_{}_", h.domain);
    let mut seen = 0;
    for e in std::fs::read_dir("/dev/shm").expect("shm").flatten() {
        if e.file_name().to_string_lossy().starts_with(&prefix) {
            let mode = e.metadata().expect("meta").permissions().mode();
            assert_eq!(mode & 0o077, 0, "{:?} has mode {mode:o}", e.file_name());
            seen += 1;
        }
    }
    assert!(seen >= 10, "found only {seen} shared-memory files");
    let root = PathBuf::from(format!("{}{prefix}", rotorloop_common::ipc::domain::ICEORYX2_ROOT));
    let mode = std::fs::metadata(&root).expect("root").permissions().mode();
    assert_eq!(mode & 0o777, 0o700, "{} has mode {mode:o}", root.display());
    let domain = Domain::new(&h.domain).expect("domain");
    let mode = std::fs::metadata(domain.global_segment()).expect("segment").permissions().mode();
    assert_eq!(mode & 0o777, 0o600, "iceoryx2's global segment has mode {mode:o}");
    // The live records: the staging directory 0700, every file in it 0600.
    let staging = rotorloop_common::flight::staging_dir(&h.domain).expect("/dev/shm");
    let mode = std::fs::symlink_metadata(&staging).expect("staging").permissions().mode();
    assert_eq!(mode & 0o777, 0o700, "{} has mode {mode:o}", staging.display());
    let mut records = 0;
    for e in std::fs::read_dir(&staging).expect("staging").flatten() {
        let mode = e.metadata().expect("meta").permissions().mode();
        assert_eq!(mode & 0o777, 0o600, "{:?} has mode {mode:o}", e.file_name());
        records += 1;
    }
    assert!(records >= 5, "only {records} files in {}", staging.display());
    let status = h.wait_all(LIMIT);
    assert!(status[run].success());
    h.assert_no_leftovers();
}

/// `sh -c script` as `user`, to completion.
pub(crate) fn as_user(user: &TempUser, script: &str) -> Output {
    let mut cmd = Command::new("sh");
    crate::common::harness::group(&mut cmd);
    cmd.args(["-c", script])
        .uid(user.uid)
        .gid(user.uid)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    wait_output(cmd.spawn().expect("sh"), LIMIT)
}

/// A root-only file a planted link points at, and whether it still holds what it did.
struct Secret(PathBuf);

impl Secret {
    fn new(h: &Harness) -> Self {
        let path = h.path("secret");
        std::fs::write(&path, b"root only").expect("secret");
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).expect("chmod");
        Self(path)
    }

    fn untouched(&self) -> bool {
        std::fs::read(&self.0).is_ok_and(|b| b == b"root only")
    }
}

/// What another OS user makes ahead of a run in `/dev/shm` (the staging directory with a
/// `run-dir` link to a root-only file, a resume slot, the domain's iceoryx2 directory,
/// iceoryx2's global segment filled with 0xff) is refused: exit 2, naming the path and
/// its owner; nothing is written through it, nothing of it is used or removed. Skipped
/// where a second user cannot be created.
#[test]
fn what_another_user_plants_in_a_runs_place_is_refused_naming_it_and_never_used() {
    let Some(user) = TempUser::for_test("what_another_user_plants_…") else { return };
    let h = Harness::new("plant");
    let secret = Secret::new(&h);
    let domain = Domain::new(&h.domain).expect("domain");
    let staging = rotorloop_common::flight::staging_dir(&h.domain).expect("/dev/shm");
    let root = domain.root_dir().display().to_string();
    let slot = format!("/dev/shm/{}resume_plant", domain.prefix());
    let segment = domain.global_segment();
    let plants: [(&str, String, String); 4] = [
        (
            "staging",
            staging.display().to_string(),
            format!(
                "mkdir -m 0777 {0} && ln -s {1} {0}/run-dir",
                staging.display(),
                secret.0.display()
            ),
        ),
        ("slot", slot.clone(), format!("umask 0; : > {slot}")),
        ("root", root.clone(), format!("mkdir -m 0777 {root}")),
        (
            "segment",
            segment.display().to_string(),
            format!("umask 0; head -c 16 /dev/zero | tr '\\0' '\\377' > {}", segment.display()),
        ),
    ];
    for (what, path, script) in plants {
        let made = as_user(&user, &script);
        assert!(made.status.success(), "{what}: {}", String::from_utf8_lossy(&made.stderr));
        let o = lockstep_run(&h, &h.path(what));
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{what}: a planted {path} was not refused:\n{err}");
        assert!(err.contains(&path) && err.contains(&user.name), "{what}: {err}");
        assert!(secret.untouched(), "{what}: the root-only file was written through a link");
        assert!(std::fs::symlink_metadata(&path).is_ok(), "{what}: {path} was removed");
        let _ = std::fs::remove_dir_all(&path).or_else(|_| std::fs::remove_file(&path));
        domain.cleanup().expect("what the refused launch made of its own is cleaned");
    }
    h.assert_no_leftovers();
}

/// A plain `rotorloop run` (no `--domain`) never falls into names another user made
/// ahead of it: the second user plants the staging directories of the next 300 pids'
/// `run-<pid>` domains, each with a `run-dir` link to a root-only file; the run's domain
/// is random, it completes, and the file is untouched.
#[test]
fn a_run_without_a_domain_cannot_be_planted_ahead_of_it() {
    let Some(user) = TempUser::for_test("a_run_without_a_domain_…") else { return };
    let h = Harness::new("nodomain");
    let secret = Secret::new(&h);
    let last: u32 = std::fs::read_to_string("/proc/sys/kernel/ns_last_pid")
        .ok()
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(1000);
    let dirs: Vec<String> =
        (last + 1..last + 300).map(|p| format!("/dev/shm/rotorloop-flight-run-{p}")).collect();
    let script = dirs
        .iter()
        .map(|d| format!("mkdir -m 0777 {d} && ln -s {} {d}/run-dir", secret.0.display()))
        .collect::<Vec<_>>()
        .join(" && ");
    let made = as_user(&user, &script);
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    let out = h.path("run");
    let o = h.rotorloop(
        &[
            "run",
            "--scenario",
            "paper-zero",
            "--duration",
            "0.5",
            "--mode",
            "lockstep",
            "--quiet",
            "--out",
            out.to_str().expect("utf8"),
        ],
        LIMIT,
    );
    for d in &dirs {
        let _ = std::fs::remove_dir_all(d);
    }
    ok(&o);
    assert!(secret.untouched(), "the root-only file was written through a planted link");
    let launch = json(&out.join("launch.json"));
    let domain = launch["domain"].as_str().expect("domain");
    let tail = domain.strip_prefix("run-").expect("run-");
    assert!(
        tail.len() == 7 && tail.parse::<u64>().is_err(),
        "the default domain `{domain}` should be random, not a pid"
    );
    assert_eq!(json(&out.join("summary.json"))["completed"], true);
}

/// A resume slot its role would refuse (here the controller's law state made NaN while
/// the controller was stopped, then killed) is a listed fault (`resume-refused`, naming
/// the field), the role starts as a fresh one would, and the run completes with no NaN
/// in its state.
#[test]
fn a_damaged_resume_slot_is_a_listed_fault_and_the_role_starts_fresh() {
    use rotorloop_common::resume::ResumeSlot;
    use rotorloop_controller::policy::ControllerResume;
    let mut h = Harness::new("badslot");
    let out = h.path("run");
    let run = start_realtime_run(&mut h, &out, "4");
    let pid: i32 = pid_of(&out, "controller").expect("pid").parse().expect("pid");
    // SAFETY: signals to our own child's child.
    unsafe { libc::kill(pid, libc::SIGSTOP) };
    let domain = Domain::new(&h.domain).expect("domain");
    let slot = ResumeSlot::<ControllerResume>::open(&domain, "controller").expect("slot");
    let mut r = slot.load().expect("the controller stored its state");
    r.law[1] = f64::NAN;
    slot.store(&r);
    drop(slot);
    unsafe { libc::kill(pid, libc::SIGKILL) };
    let status = h.wait_all(LIMIT);
    let err = h.stderr_of(run);
    assert!(status[run].success(), "{err}");
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    let faults = s["faults"].as_array().expect("faults");
    let refused = faults
        .iter()
        .find(|f| f["kind"] == "resume-refused")
        .unwrap_or_else(|| panic!("no resume-refused fault in {faults:?}\n{err}"));
    assert_eq!(refused["role"], "controller");
    let detail = refused["detail"].as_str().expect("detail");
    assert!(detail.contains("law"), "{detail}");
    assert_state_columns_finite(&out);
    h.assert_no_leftovers();
}

/// A second `rotorloop run` on a domain in use is refused before it touches anything of
/// it: the live run keeps every flight record and completes with all its rows.
#[test]
fn a_second_launch_on_a_live_domain_touches_nothing_of_it() {
    let mut h = Harness::new("second");
    let out = h.path("run");
    let run = start_realtime_run(&mut h, &out, "3");
    let o = lockstep_run(&h, &h.path("second"));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("is in use"), "{err}");
    assert!(!err.contains("removed"), "the refused launch removed something: {err}");
    let status = h.wait_all(LIMIT);
    assert!(status[run].success(), "{}", h.stderr_of(run));
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    assert_eq!(s["trace_rows"], 3001);
    assert_eq!(s["rows_lost"], 0);
    for f in ["plant-state", "plant-torque", "controller-torque", "reference"] {
        let path = out.join("flight").join(format!("{f}.flight"));
        assert!(path.exists(), "{} gone", path.display());
    }
    h.assert_no_leftovers();
}

/// The race for iceoryx2's global segment: a second OS user tries without pause to make
/// or open it for writing (`: >`, umask 0). Started before a run, that user makes it
/// first and the run is refused, naming the segment and its owner (it was: every role
/// failed to make its node, exit 1, no summary). Started once the run's launcher made
/// the segment, the user never opens it: it is made 0600 before any node exists (iceoryx2
/// made it 0666 and rotorloop closed it with a chmod a moment later). Skipped where a
/// second user cannot be created.
#[test]
fn another_user_racing_for_the_global_segment_never_holds_it_open() {
    use std::os::unix::fs::MetadataExt;
    let Some(user) = TempUser::for_test("another_user_racing_…") else { return };
    let mut h = Harness::new("race");
    let segment = Domain::new(&h.domain).expect("domain").global_segment();
    std::fs::set_permissions(h.dir.path(), std::fs::Permissions::from_mode(0o755)).expect("dir");
    // The racer: until `stop` exists, prints a line for each time it had the file open.
    let racer = |stop: &Path| {
        let script = format!(
            "while [ ! -e {stop} ]; do (umask 0; : > {seg}) 2>/dev/null && echo opened; done",
            stop = stop.display(),
            seg = segment.display()
        );
        let mut racer = Command::new("sh");
        crate::common::harness::group(&mut racer);
        racer
            .args(["-c", &script])
            .uid(user.uid)
            .gid(user.uid)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::null());
        racer.spawn().expect("racer")
    };
    let opened = |racer, stop: &Path| {
        std::fs::write(stop, b"").expect("stop");
        String::from_utf8_lossy(&wait_output(racer, LIMIT).stdout).lines().count()
    };

    // The other user first.
    let stop = h.path("stop-first");
    let first = racer(&stop);
    let until = Instant::now() + Duration::from_secs(30);
    while std::fs::symlink_metadata(&segment).is_err() {
        assert!(Instant::now() < until, "the racer never made {}", segment.display());
        std::thread::sleep(Duration::from_millis(10));
    }
    let out = h.path("refused");
    let run = lockstep_run(&h, &out);
    opened(first, &stop);
    let err = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(2), "{err}");
    let named = segment.display().to_string();
    assert!(err.contains(&named) && err.contains(&user.name), "{err}");
    let theirs = std::fs::symlink_metadata(&segment).is_ok_and(|m| m.uid() == user.uid);
    assert!(theirs, "the refused run removed or replaced the other user's file");
    std::fs::remove_file(&segment).expect("remove the planted segment");

    // The run first: once its launcher made the segment, the other user races the roles.
    let out = h.path("run");
    let run = start_realtime_run(&mut h, &out, "3");
    let stop = h.path("stop-second");
    let second = racer(&stop);
    std::thread::sleep(Duration::from_millis(1500));
    assert_eq!(opened(second, &stop), 0, "the other user opened the run's global segment");
    let status = h.wait_all(LIMIT);
    assert!(status[run].success(), "{}", h.stderr_of(run));
    assert_eq!(json(&out.join("summary.json"))["completed"], true);
    h.assert_no_leftovers();
}

fn lockstep_run(h: &Harness, out: &Path) -> Output {
    h.rotorloop(
        &[
            "run",
            "--scenario",
            "paper-zero",
            "--duration",
            "0.2",
            "--mode",
            "lockstep",
            "--quiet",
            "--domain",
            &h.domain,
            "--out",
            out.to_str().expect("utf8"),
        ],
        LIMIT,
    )
}

/// A directory like `/tmp` (mode 1777, root's) where the second user can make things: the
/// test's to remove.
fn public_dir() -> tempfile::TempDir {
    let searchable = |p: &Path| {
        p.ancestors().all(|d| std::fs::metadata(d).is_ok_and(|m| m.permissions().mode() & 1 != 0))
    };
    let tmp = std::env::temp_dir();
    let base = if searchable(&tmp) { tmp } else { PathBuf::from("/var/tmp") };
    let dir = tempfile::tempdir_in(base).expect("tempdir");
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o1777)).expect("chmod");
    dir
}

/// Every name a run writes into OUT (issue 62 found 32 of 38 written through links).
const OUT_NAMES: &[&str] = &[
    "trace.csv",
    "timing.csv",
    "sched.csv",
    "rss.csv",
    "doctor.json",
    "cpus.json",
    "summary.json",
    "launch.json",
    "summary.json.partial",
    "launch.json.partial",
    "run.mcap",
    "run.mcap.part",
    "incidents.md",
    "incidents.csv",
    "incidents.png",
    "sense_to_actuate.hgrm",
    "sense_to_actuate.hlog",
    "state_transport.hgrm",
    "controller_compute.hgrm",
    "tracking.png",
    "latency_percentiles.png",
];

/// Issue 62, point 2: a run's OUT in a place another user controls. The second user makes
/// OUT (0777) with a link per output name (and `config/iceoryx2.toml`, and `flight` to a
/// root-only directory): the run is refused (exit 2, naming OUT, its owner, its mode) and
/// writes nothing through any link. The same for an OUT that is the other user's link to a
/// root-only directory, and for an OUT below the other user's directory (on the way). A
/// root-owned OUT in the same public place runs (the control). Before, root overwrote 32
/// of 38 linked files and wrote the whole run through the OUT link. Skipped where a second
/// user cannot be created.
#[test]
fn an_out_another_user_controls_is_refused_and_nothing_is_written_through_it() {
    let Some(user) = TempUser::for_test("an_out_another_user_controls_…") else { return };
    let h = Harness::new("outlinks");
    let secret = Secret::new(&h);
    let root_only = h.path("root-only");
    std::fs::create_dir(&root_only).expect("dir");
    std::fs::set_permissions(&root_only, std::fs::Permissions::from_mode(0o700)).expect("chmod");
    let public = public_dir();
    let o = public.path().join("o");
    let link = public.path().join("link");
    let links: Vec<String> = OUT_NAMES
        .iter()
        .map(|n| format!("ln -s {} {}/{n}", secret.0.display(), o.display()))
        .collect();
    let script = format!(
        "mkdir -m 0777 {o} {o}/config && {links} && ln -s {s} {o}/config/iceoryx2.toml && \
         ln -s {r} {o}/flight && ln -s {r} {l}",
        o = o.display(),
        links = links.join(" && "),
        s = secret.0.display(),
        r = root_only.display(),
        l = link.display(),
    );
    let made = as_user(&user, &script);
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    let nothing_in_root_only = || std::fs::read_dir(&root_only).expect("dir").next().is_none();

    for (what, out, named) in [
        ("the other user's OUT", o.clone(), "0777"),
        ("the other user's link as OUT", link.clone(), "symbolic link"),
        ("an OUT below the other user's directory", o.join("run"), "on the way"),
    ] {
        let r = lockstep_run(&h, &out);
        let err = String::from_utf8_lossy(&r.stderr);
        assert_eq!(r.status.code(), Some(2), "{what} was not refused:\n{err}");
        let shown =
            if named == "on the way" { o.display().to_string() } else { out.display().to_string() };
        assert!(err.contains(&shown) && err.contains(&user.name), "{what}: {err}");
        assert!(err.contains(named), "{what}: {err}");
        assert!(secret.untouched(), "{what}: the root-only file was written through a link");
        assert!(nothing_in_root_only(), "{what}: the run wrote into the root-only directory");
        assert!(!o.join("run").exists(), "{what}: made a directory in the other user's");
    }
    // The other commands that write an OUT refuse it the same way (they wrote with plain
    // paths before).
    let o_str = o.to_str().expect("utf8");
    for args in [
        vec!["margin", "--duration", "1", "--out", o_str],
        vec!["montecarlo", "--runs", "1", "--duration", "1", "--out", o_str],
        vec!["paper", "--duration", "1", "--out", o_str],
        vec!["bench", "--seconds", "1", "--out", o_str],
        vec!["sim", "--scenario", "paper-zero", "--duration", "1", "--out", o_str],
    ] {
        let r = h.rotorloop(&args, LIMIT);
        let err = String::from_utf8_lossy(&r.stderr);
        assert_eq!(r.status.code(), Some(2), "{args:?} was not refused:\n{err}");
        assert!(err.contains(o_str) && err.contains(&user.name), "{args:?}: {err}");
        assert!(secret.untouched(), "{args:?}: the root-only file was written through a link");
        assert!(nothing_in_root_only(), "{args:?}: wrote into the root-only directory");
    }
    // The control: an OUT of root's own in the same public place runs.
    let mine = public.path().join("mine");
    ok(&lockstep_run(&h, &mine));
    assert_eq!(json(&mine.join("summary.json"))["completed"], true);
    assert!(secret.untouched());
    h.assert_no_leftovers();
}

/// Issue 62, point 6: the flight records moved into `OUT/flight` keep 0600 (the packer
/// wrote them with a plain open: 0644 under the usual umask), in a directory of 0700.
#[test]
fn the_flight_records_in_out_keep_0600() {
    let h = Harness::new("flightmodes");
    let out = h.path("run");
    let mut cmd = Command::new(ROTORLOOP);
    crate::common::harness::group(&mut cmd);
    cmd.args(["run", "--scenario", "paper-zero", "--duration", "0.2", "--mode", "lockstep"])
        .args(["--quiet", "--domain", &h.domain, "--out", out.to_str().expect("utf8")])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    // SAFETY: umask is async-signal-safe; the usual 022, whatever the test runner's.
    unsafe {
        cmd.pre_exec(|| {
            libc::umask(0o022);
            Ok(())
        })
    };
    ok(&wait_output(cmd.spawn().expect("rotorloop"), LIMIT));
    let flight = out.join("flight");
    let mode = |p: &Path| std::fs::symlink_metadata(p).expect("meta").permissions().mode() & 0o777;
    assert_eq!(mode(&flight), 0o700, "{}", flight.display());
    let mut n = 0;
    for e in std::fs::read_dir(&flight).expect("flight").flatten() {
        assert_eq!(mode(&e.path()), 0o600, "{}", e.path().display());
        n += 1;
    }
    assert!(n >= 4, "only {n} records in {}", flight.display());
    h.assert_no_leftovers();
}

/// `sh -c script` as root in a mount namespace of its own with a private `/dev/shm`
/// (`size` of tmpfs), so that nothing of other tests' (or other users') runs is in it.
fn in_private_shm(size: &str, script: &str) -> Result<Output, String> {
    let mut cmd = Command::new("unshare");
    crate::common::harness::group(&mut cmd);
    let setup = format!(
        "mount --make-rprivate / && mount -t tmpfs -o size={size},mode=1777 none /dev/shm || \
         {{ echo 'setup: no private /dev/shm' >&2; exit 97; }}\n{script}"
    );
    cmd.args(["-m", "sh", "-c", &setup])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let o = wait_output(cmd.spawn().map_err(|e| format!("unshare: {e}"))?, 3 * LIMIT);
    match o.status.code() {
        Some(97) => Err(String::from_utf8_lossy(&o.stderr).into_owned()),
        _ => Ok(o),
    }
}

/// Issue 62, point 4: the default domain planted from its first file. In a `/dev/shm` of
/// its own, the second user watches for the staging directory of a `run-…` domain and, as
/// soon as it appears, makes every resume slot of that domain (`rl_<D>_resume_*`). The
/// plain `rotorloop run` (no `--domain`) is never refused: it draws another name where it
/// found the other user's files, completes, and leaves nothing of its own in `/dev/shm`
/// (the other user's files stay). Before, the run was refused (exit 2) and left its
/// segments behind. Skipped where a second user or a mount namespace is missing.
#[test]
fn a_planted_default_domain_is_never_a_refusal() {
    let Some(user) = TempUser::for_test("a_planted_default_domain_…") else { return };
    let h = Harness::new("planted-default");
    std::fs::set_permissions(h.dir.path(), std::fs::Permissions::from_mode(0o755)).expect("chmod");
    let out = h.path("run");
    let planted = h.path("planted");
    std::fs::write(&planted, "").expect("log");
    std::os::unix::fs::chown(&planted, Some(user.uid), None).expect("chown");
    // The watcher: a busy loop of shell built-ins (no fork between seeing and planting);
    // it logs each domain it saw (`seen D`) and each file it made (`made PATH`).
    let watcher = format!(
        r#"seen=" "
while :; do for d in /dev/shm/rotorloop-flight-run-*; do [ -e "$d" ] || continue
  D=${{d#/dev/shm/rotorloop-flight-}}
  case "$seen" in *" $D "*) continue;; esac
  seen="$seen$D "
  for r in plant reference controller monitor plant-refusals; do
    f=/dev/shm/rl_${{D}}_resume_$r
    true 2>/dev/null > "$f" && echo "made $f" >> {planted}
  done
  echo "seen $D" >> {planted}
done; done"#,
        planted = planted.display()
    );
    let script = format!(
        "setpriv --reuid={uid} --regid={uid} --clear-groups sh -c '{watcher}' &\nw=$!\n\
         sleep 0.5\n{bin} run --scenario paper-zero --duration 0.5 --mode lockstep --quiet \
         --out {out}\nrc=$?\nkill $w\nwait $w 2>/dev/null\necho rc=$rc\n\
         ls -la /dev/shm\nfor f in /dev/shm/* /dev/shm/.rl_*; do [ -e \"$f\" ] && stat -c '%U %n' \"$f\"; done\n\
         exit $rc",
        uid = user.uid,
        bin = ROTORLOOP,
        out = out.display(),
    );
    let o = match in_private_shm("256m", &script) {
        Ok(o) => o,
        Err(why) => {
            eprintln!("SKIPPED a_planted_default_domain_…: {why}");
            return;
        }
    };
    let (said, err) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    let planted = std::fs::read_to_string(&planted).expect("log");
    assert!(
        planted.contains("seen run-"),
        "the watcher never saw the run's domain:\n{said}\n{err}"
    );
    assert_eq!(
        o.status.code(),
        Some(0),
        "a planted default domain refused the run:\n{said}\n{err}"
    );
    assert_eq!(json(&out.join("summary.json"))["completed"], true);
    let domain = json(&out.join("launch.json"))["domain"].as_str().expect("domain").to_owned();
    // Whatever the watcher planted, the run's own domain is not one of them (it was
    // planted too late, or the name was drawn again), and nothing of root's is left.
    let roots: Vec<&str> = said.lines().filter(|l| l.starts_with("root /dev/shm/")).collect();
    assert!(roots.is_empty(), "left in /dev/shm by the run: {roots:?}\n{said}");
    // The other user's files are never removed.
    for made in planted.lines().filter_map(|l| l.strip_prefix("made ")) {
        assert!(said.contains(&format!("{} {made}", user.name)), "{made} was removed:\n{said}");
    }
    assert!(domain.starts_with("run-"), "{domain}");
}

/// Issue 62, point 3: the monitor's fallback report directory (where the report goes when
/// OUT's filesystem is full) cannot be planted. The second user makes the old predictable
/// `$TMPDIR/rotorloop-report-<D>` (0777) with a `.hgrm` link to a root-only file: the run
/// (its OUT a full 2 MiB tmpfs) never writes into it nor through the link, and its report
/// lands in a directory of root's alone (0700, a random name). Before, root chmodded the
/// planted directory 0700, the other user still read the summary, and the link was written
/// through. Needs root with `mount` and a second user; skipped with a message elsewhere.
///
/// Once the loop runs (the trace has rows), the test takes OUT's last inodes: a full disk
/// alone left room now and then (a journal's frame that did not fit is cut off again), and
/// a loaded machine's monitor once wrote its whole report into OUT there (CI, stop 76).
#[test]
fn the_fallback_report_directory_cannot_be_planted() {
    let Some(user) = TempUser::for_test("the_fallback_report_directory_…") else { return };
    let mut h = Harness::new("fallback");
    let secret = Secret::new(&h);
    let Some(disk) = crate::common::harness::SmallDisk::mount_with(&h, "full", ",nr_inodes=64")
    else {
        eprintln!("SKIPPED the_fallback_report_directory_…: cannot mount a tmpfs here");
        return;
    };
    let out = disk.path().to_owned();
    let old = std::env::temp_dir().join(format!("rotorloop-report-{}", h.domain));
    let made = as_user(
        &user,
        &format!(
            "mkdir -m 0777 {o} && ln -s {s} {o}/sense_to_actuate.hgrm",
            o = old.display(),
            s = secret.0.display()
        ),
    );
    assert!(made.status.success(), "{}", String::from_utf8_lossy(&made.stderr));
    let args: Vec<String> = [
        "run",
        "--scenario",
        "paper-sinusoid",
        "--duration",
        "6",
        "--mode",
        "realtime",
        "--force",
        "--domain",
        &h.domain,
        "--out",
        out.to_str().expect("utf8"),
    ]
    .into_iter()
    .map(str::to_owned)
    .collect();
    let run = h.spawn(ROTORLOOP, &args);
    let trace = out.join("trace.csv");
    let started = Instant::now();
    while !std::fs::metadata(&trace).is_ok_and(|m| m.len() > 0) && started.elapsed() < LIMIT {
        std::thread::sleep(Duration::from_millis(10));
    }
    let taken = disk.take_every_inode();
    let status = h.wait_all(3 * LIMIT);
    let err = h.stderr_of(run);
    assert!(trace.exists(), "the monitor never wrote its trace: {err}");
    eprintln!("took OUT's last {taken} inodes once the trace had rows");
    let planted: Vec<String> = std::fs::read_dir(&old)
        .expect("the planted directory stays")
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    let old_mode = std::fs::symlink_metadata(&old).expect("meta").permissions().mode() & 0o777;
    let _ = std::fs::remove_dir_all(&old);
    assert!(status[run].success(), "{err}");
    assert!(secret.untouched(), "the root-only file was written through the planted link");
    assert_eq!(planted, ["sense_to_actuate.hgrm"], "the run wrote into the planted directory");
    assert_eq!(old_mode, 0o777, "the run changed the planted directory");
    let prefix = rotorloop_monitor::recording::fallback_prefix(&h.domain);
    let fallbacks: Vec<PathBuf> = std::fs::read_dir(std::env::temp_dir())
        .expect("tmp")
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
        .map(|e| e.path())
        .collect();
    let summary = std::iter::once(out.join("summary.json"))
        .chain(fallbacks.iter().map(|f| f.join("summary.json")))
        .find(|p| p.exists());
    for f in &fallbacks {
        let m = std::fs::symlink_metadata(f).expect("meta");
        assert_eq!(m.permissions().mode() & 0o777, 0o700, "{}", f.display());
        assert_eq!(std::os::unix::fs::MetadataExt::uid(&m), 0, "{}", f.display());
    }
    assert!(!fallbacks.is_empty(), "OUT never filled, no fallback was used: {err}");
    let summary = summary.unwrap_or_else(|| panic!("no summary.json anywhere: {err}"));
    let s = json(&summary);
    assert_eq!(s["completed"], true);
    // The records could not be moved onto the full disk: they stay on /dev/shm.
    if let Some(flight) = s["flight"]["dir"].as_str() {
        let _ = std::fs::remove_dir_all(flight);
    }
    for f in &fallbacks {
        let _ = std::fs::remove_dir_all(f);
    }
    h.assert_no_leftovers();
}
