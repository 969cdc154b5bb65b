//! Who may watch a run: the live Foxglove view serves loopback only unless the user says
//! they mean the network, an address asked for that another process holds is refused
//! rather than served by that process, and a second OS user's `watch` and `ps` say they
//! cannot read the run instead of showing a loop of zeros.

use std::net::TcpListener;
use std::os::unix::fs::PermissionsExt;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use crate::common::harness::{Harness, ROTORLOOP, group, json, ok, wait_output};

use super::{LIMIT, TempUser, start_realtime_run};

/// `rotorloop run --scenario paper-zero --mode lockstep --duration 1` in `h`'s domain, with
/// `extra`, into `h`'s `name`.
fn lockstep_run(h: &Harness, name: &str, extra: &[&str]) -> (Output, PathBuf) {
    let out = h.path(name);
    let mut args = vec!["run", "--scenario", "paper-zero", "--mode", "lockstep"];
    args.extend_from_slice(&["--duration", "1", "--quiet", "--domain", &h.domain, "--out"]);
    args.push(out.to_str().expect("utf8"));
    args.extend_from_slice(extra);
    (h.rotorloop(&args, LIMIT), out)
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// The live view has no authentication, so `--foxglove` on an address beyond loopback
/// (`0.0.0.0:0`: every interface) is refused, exit 2 naming the address and the flag that
/// allows it, before anything starts; with `--foxglove-allow-network` the same run is
/// served there and completes. `rotorloop foxglove` refuses it the same way.
#[test]
fn a_foxglove_address_beyond_loopback_is_refused_unless_the_user_means_it() {
    let h = Harness::new("fxnet");
    let (o, out) = lockstep_run(&h, "refused", &["--foxglove", "0.0.0.0:0"]);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("`0.0.0.0:0`") && err.contains("--foxglove-allow-network"), "{err}");
    assert!(!out.join("summary.json").exists(), "nothing may start");
    h.assert_no_leftovers();

    let alone = ["foxglove", "--domain", &h.domain, "0.0.0.0:0", "--wait-s", "1"];
    let o = h.rotorloop(&alone, LIMIT);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("`0.0.0.0:0`") && err.contains("--allow-network"), "{err}");

    let allowed = ["--foxglove", "0.0.0.0:0", "--foxglove-allow-network"];
    let (o, out) = lockstep_run(&h, "allowed", &allowed);
    ok(&o);
    let served = std::fs::read_to_string(out.join("foxglove.addr")).expect("foxglove.addr");
    assert!(served.starts_with("0.0.0.0:"), "{served}");
    assert_eq!(json(&out.join("summary.json"))["completed"], true);
    h.assert_no_leftovers();
}

/// A port asked for by name that another process holds is an error, exit 2 naming the
/// address, before anything starts: the run is never served by whatever holds the port.
/// `rotorloop foxglove` on it too.
#[test]
fn a_foxglove_port_asked_for_and_taken_is_refused_naming_it() {
    let h = Harness::new("fxtaken");
    let squatter = TcpListener::bind("127.0.0.1:0").expect("a free port");
    let addr = squatter.local_addr().expect("bound").to_string();
    let (o, out) = lockstep_run(&h, "run", &["--foxglove", &addr]);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains(&addr) && err.contains("taken"), "{err}");
    assert!(!out.join("summary.json").exists(), "nothing may start");
    assert!(!out.join("foxglove.addr").exists());
    h.assert_no_leftovers();

    let o = h.rotorloop(&["foxglove", "--domain", &h.domain, &addr, "--wait-s", "1"], LIMIT);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains(&addr) && err.contains("taken"), "{err}");
    drop(squatter);
}

/// The default port taken (by anyone: this test holds it if it is free) keeps the run
/// going without a live view (exit 0, no `foxglove.addr`), and the launcher says that
/// viewers at that port do not reach this run, on the console and in `summary.json`'s
/// `warnings`.
#[test]
fn the_default_foxglove_port_taken_is_said_to_reach_another_process() {
    let h = Harness::new("fxdefault");
    let default = rotorloop::observe::foxglove::DEFAULT_ADDR;
    // Held by this test, or already by another process: taken either way.
    let _held = TcpListener::bind(default).ok();
    let (o, out) = lockstep_run(&h, "run", &["--foxglove"]);
    let err = stderr(&o);
    ok(&o);
    let said = format!("viewers at ws://{default} do not reach this run");
    assert!(err.contains(&said), "{err}");
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true);
    let warned = s["warnings"].as_array().into_iter().flatten().filter_map(|w| w.as_str());
    assert!(warned.into_iter().any(|w| w.contains(&said)), "{}", s["warnings"]);
    assert!(!out.join("foxglove.addr").exists());
    h.assert_no_leftovers();
}

/// A copy of the binary that every user may run, in a directory of its own (removed on
/// drop) under the first temporary directory every user may pass through (`/tmp` may be
/// owner-only, 0700).
fn binary_for_everyone() -> (tempfile::TempDir, PathBuf) {
    let passable = |d: &Path| {
        d.ancestors()
            .all(|a| std::fs::metadata(a).is_ok_and(|m| m.permissions().mode() & 0o001 != 0))
    };
    let base = [std::env::temp_dir(), PathBuf::from("/var/tmp")]
        .into_iter()
        .find(|d| passable(d))
        .expect("a temporary directory every user may pass through");
    let dir = tempfile::tempdir_in(base).expect("tempdir");
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).expect("chmod");
    let binary = dir.path().join("rotorloop");
    std::fs::copy(ROTORLOOP, &binary).expect("copy binary");
    std::fs::set_permissions(&binary, std::fs::Permissions::from_mode(0o755)).expect("chmod");
    (dir, binary)
}

/// `rotorloop ARGS` as `uid` (its own group, no others), from `binary`.
fn as_user(binary: &Path, uid: u32, args: &[&str]) -> Output {
    let mut cmd = Command::new(binary);
    group(&mut cmd)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .uid(uid)
        .gid(uid);
    wait_output(cmd.spawn().expect("spawn as the other user"), LIMIT)
}

/// A second OS user cannot read a run (its files are owner-only), and its observers say
/// so: `watch --once --json` and `ps --domain D` exit 2 naming the domain, the owner's uid
/// and "permission denied" (not a loop of zeros with exit 0), and a listing of every
/// domain (`ps --json`) marks the run unreachable. The owner's `watch` of the same run, as
/// a control, sees it tick. Skipped, with the reason, where a second user cannot be made.
#[test]
fn watch_and_ps_as_another_os_user_are_refused_naming_the_domain() {
    let Some(user) = TempUser::for_test("watch_and_ps_as_another_os_user_…") else {
        return;
    };
    let mut h = Harness::new("watchuser");
    let (_bin_dir, binary) = binary_for_everyone();

    let out = h.path("run");
    let run = start_realtime_run(&mut h, &out, "8");
    // SAFETY: plain getter.
    let owner = format!("owned by uid {}", unsafe { libc::geteuid() });
    let watch = ["watch", "--domain", &h.domain, "--once", "--json", "--seconds", "0.3"];

    let o = as_user(&binary, user.uid, &watch);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{}: {err}", String::from_utf8_lossy(&o.stdout));
    assert!(o.stdout.is_empty(), "no view printed: {}", String::from_utf8_lossy(&o.stdout));
    let domain = format!("domain `{}`", h.domain);
    for want in [&domain, &owner, "permission denied"] {
        assert!(err.contains(want), "no `{want}` in: {err}");
    }

    let o = as_user(&binary, user.uid, &["ps", "--domain", &h.domain, "--json"]);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains(&domain) && err.contains("permission denied"), "{err}");

    let o = as_user(&binary, user.uid, &["ps", "--json", "--sample-ms", "10"]);
    let listed: serde_json::Value = serde_json::from_str(&ok(&o)).expect("JSON");
    let ours = listed
        .as_array()
        .expect("domains")
        .iter()
        .find(|d| d["domain"] == h.domain.as_str())
        .unwrap_or_else(|| panic!("{} not listed: {listed}", h.domain))
        .clone();
    let why = ours["unreachable"].as_str().unwrap_or_default();
    assert!(why.contains("permission denied"), "{ours}");
    assert_eq!(ours["roles"].as_array().map(Vec::len), Some(0), "{ours}");

    // The control: the owner sees the loop.
    let seen: serde_json::Value =
        serde_json::from_str(&ok(&h.rotorloop(&watch, LIMIT))).expect("JSON");
    assert!(seen["tick"].as_u64().is_some_and(|t| t > 0), "{seen}");

    let status = h.wait_all(LIMIT);
    assert!(status[run].success(), "the run failed");
    assert_eq!(json(&out.join("summary.json"))["completed"], true);
    h.assert_no_leftovers();
}
