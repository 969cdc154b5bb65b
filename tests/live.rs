//! The live view: `rotorloop run --foxglove` and `rotorloop foxglove --domain D` serve a
//! running loop over the Foxglove WebSocket protocol. Checked with a viewer written against
//! the protocol (`rotorloop::observe::viewer`, tungstenite, not the Foxglove SDK): it
//! negotiates `foxglove.sdk.v1`, subscribes, decodes states and transforms while the loop
//! runs, connects late and vanishes without a close; the loop ends as one nobody watched.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rotorloop::observe::viewer::{SUBPROTOCOL, Viewer};

use crate::common::harness::{Harness, Running, group, json, ok, wait_output};

const LIMIT: Duration = Duration::from_secs(240);

/// A real-time run of `seconds` in `h`'s domain with `extra` arguments.
fn start(h: &Harness, seconds: &str, extra: &[&str]) -> (Running, std::path::PathBuf) {
    let out = h.path("run");
    let child = group(&mut Command::new(crate::common::harness::ROTORLOOP))
        .args(["run", "--scenario", "paper-sinusoid", "--mode", "realtime", "--duration", seconds])
        .args(["--quiet", "--domain", &h.domain])
        .args(extra)
        .arg("--out")
        .arg(&out)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn");
    (Running::from(child), out)
}

/// The address in `file` once it is written.
fn address(file: &Path) -> String {
    let until = Instant::now() + LIMIT;
    loop {
        if let Ok(a) = std::fs::read_to_string(file) {
            if a.ends_with('\n') {
                return a.trim().to_owned();
            }
        }
        assert!(Instant::now() < until, "no address in {}", file.display());
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// What a viewer saw: the states' ticks and the publish stamps they carried, and the
/// transforms' quaternions.
#[derive(Default)]
struct Seen {
    ticks: Vec<u64>,
    stamps_match: bool,
    quaternions: Vec<[f64; 4]>,
    logs: Vec<String>,
}

/// Connects to `addr`, subscribes to the states and transforms, and reads for `secs`.
fn view(addr: &str, secs: f64) -> (Viewer, Seen) {
    let mut v = Viewer::connect(addr, Duration::from_millis(100)).expect("connect");
    assert_eq!(v.subprotocol, SUBPROTOCOL);
    v.subscribe(&["/rotorloop/state", "/tf", "/rotorloop/log"]).expect("subscribe");
    let mut seen = Seen { stamps_match: true, ..Seen::default() };
    let until = Instant::now() + Duration::from_secs_f64(secs);
    while Instant::now() < until {
        let Some(m) = v.receive().expect("read") else { continue };
        match m.topic.as_str() {
            "/rotorloop/state" => {
                let s: serde_json::Value = serde_json::from_slice(&m.payload).expect("JSON state");
                seen.ticks.push(s["tick"].as_u64().expect("tick"));
                seen.stamps_match &= s["publish_ns"].as_u64() == Some(m.log_time);
            }
            "/tf" => {
                let t =
                    <foxglove::messages::FrameTransform as prost::Message>::decode(&m.payload[..])
                        .expect("a FrameTransform");
                let q = t.rotation.expect("rotation");
                seen.quaternions.push([q.x, q.y, q.z, q.w]);
            }
            "/rotorloop/log" => {
                let l = <foxglove::messages::Log as prost::Message>::decode(&m.payload[..])
                    .expect("a Log");
                seen.logs.push(l.message);
            }
            _ => {}
        }
    }
    (v, seen)
}

/// The run ended as one nobody watched: completed, `faults` faults (those it was given),
/// every tick in its trace and records.
fn assert_untouched(out: &Path, faults: usize) {
    let s = json(&out.join("summary.json"));
    assert_eq!(s["completed"], true, "{s}");
    assert_eq!(s["faults"].as_array().map(Vec::len), Some(faults), "faults: {}", s["faults"]);
    assert_eq!(s["rows_lost"], 0);
    let ticks = s["ticks"].as_u64().expect("ticks");
    assert_eq!(s["trace_rows"].as_u64(), Some(ticks + 1), "{s}");
    let state = &s["flight"]["streams"][0];
    assert_eq!(
        (state["stream"].as_str(), state["records"].as_u64()),
        (Some("plant-state"), Some(ticks + 1))
    );
}

/// `run --foxglove HOST:0`: a viewer that connects 2 s into the run sees the loop from
/// then on (consecutive ticks, log times the states' own publish stamps, unit
/// quaternions), vanishes without a close, and a second viewer still gets the newer
/// ticks. The run completes as one nobody watched, and the server ends with it.
#[test]
fn a_viewer_connects_late_and_vanishes_and_the_loop_never_notices() {
    let h = Harness::new("fxlive");
    let (child, out) = start(&h, "7", &["--foxglove", "127.0.0.1:0"]);
    let addr = address(&out.join("foxglove.addr"));
    std::thread::sleep(Duration::from_secs(2));
    let (first, seen) = view(&addr, 1.5);
    assert!(seen.ticks.len() > 300, "{} states in 1.5 s of a 1 kHz loop", seen.ticks.len());
    assert!(seen.ticks[0] > 500, "connected late, yet saw tick {}", seen.ticks[0]);
    let consecutive = seen.ticks.windows(2).filter(|w| w[1] == w[0] + 1).count();
    assert!(consecutive + 1 >= seen.ticks.len() * 9 / 10, "mostly consecutive: {:?}", seen.ticks);
    assert!(seen.ticks.windows(2).all(|w| w[1] > w[0]), "in order");
    assert!(seen.stamps_match, "log time = the state's publish stamp");
    assert!(seen.quaternions.len() > 300);
    for q in &seen.quaternions {
        let n = q.iter().map(|x| x * x).sum::<f64>();
        assert!((n - 1.0).abs() < 1e-9, "{q:?}");
    }
    let last = *seen.ticks.last().expect("ticks");
    first.vanish();
    let (second, again) = view(&addr, 1.0);
    assert!(
        again.ticks.first().is_some_and(|k| *k > last),
        "{:?} after {last}",
        again.ticks.first()
    );
    drop(second);
    let output = wait_output(child, LIMIT);
    ok(&output);
    assert_untouched(&out, 0);
    h.assert_no_leftovers();
}

/// `rotorloop foxglove --domain D` attached to a loop as it starts serves its states and
/// logs the controller's restart (killed by the fault schedule at 2 s) on
/// `/rotorloop/log`; `kill -9` of the server in the middle of the run is nothing to the
/// loop.
#[test]
fn a_server_attached_to_a_running_loop_and_killed_is_no_matter_to_it() {
    let h = Harness::new("fxattach");
    let (child, out) = start(&h, "6", &["--fault", "controller:kill@2:restart@2.3"]);
    let file = h.path("fx.addr");
    let mut server = Command::new(crate::common::harness::ROTORLOOP)
        .args(["foxglove", "--domain", &h.domain, "127.0.0.1:0", "--addr-file"])
        .arg(&file)
        .stdin(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn rotorloop foxglove");
    let addr = address(&file);
    let (v, seen) = view(&addr, 3.5);
    assert!(seen.ticks.len() > 300, "{} states", seen.ticks.len());
    // Gone and back (seen five times a second: "restarted" when both fell between two
    // looks), and safe mode entered and left in between.
    let logs = &seen.logs;
    let at = |p: &dyn Fn(&str) -> bool| logs.iter().position(|l| p(l));
    let gone = at(&|l| l.starts_with("controller (pid") && l.ends_with("gone"));
    let back = gone.and_then(|g| {
        logs[g..].iter().position(|l| l.starts_with("controller (pid") && l.ends_with("up"))
    });
    let restarted = at(&|l| l.starts_with("controller restarted (pid"));
    let cycle = restarted.is_some() || back.is_some();
    assert!(cycle, "{logs:?}");
    assert!(at(&|l| l.starts_with("safe mode entered")).is_some(), "{logs:?}");
    assert!(at(&|l| l.starts_with("control resumed")).is_some(), "{logs:?}");
    server.kill().expect("kill -9");
    let _ = server.wait();
    drop(v);
    ok(&wait_output(child, LIMIT));
    assert_untouched(&out, 1);
    h.assert_no_leftovers();
}

/// A bad address is a usage error naming the option and what is allowed, before
/// anything starts.
#[test]
fn a_bad_foxglove_address_is_refused_before_the_run() {
    let h = Harness::new("fxbad");
    let out = h.path("run");
    let o = h.rotorloop(
        &["run", "--scenario", "paper-zero", "--mode", "lockstep", "--foxglove", "nowhere"]
            .into_iter()
            .chain(["--domain", &h.domain, "--out", out.to_str().expect("utf8")])
            .collect::<Vec<_>>(),
        LIMIT,
    );
    assert_eq!(o.status.code(), Some(2), "{o:?}");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--foxglove") && err.contains("HOST:PORT"), "{err}");
    assert!(!out.join("summary.json").exists());
}
