//! The live view: `rotorloop run --foxglove` and `rotorloop foxglove --domain D` serve a
//! running loop over the Foxglove WebSocket protocol. Checked with a viewer written against
//! the protocol (`rotorloop::observe::viewer`, tungstenite, not the Foxglove SDK): it
//! negotiates `foxglove.sdk.v1` (or the older `foxglove.websocket.v1`), subscribes, decodes
//! states and transforms while the loop runs, validates every JSON message against its
//! channel's schema, connects late and vanishes without a close, closes as RFC 6455 says,
//! and sends bad frames; the loop ends as one nobody watched, and nothing of the viewer's
//! server is left.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rotorloop::observe::viewer::{Closed, SUBPROTOCOL, Viewer};

use crate::common::harness::{Harness, Running, group, json, ok, wait_output};
use crate::common::schemas::Schemas;

const LIMIT: Duration = Duration::from_secs(240);

/// `rotorloop foxglove --domain D 127.0.0.1:0 EXTRA --addr-file FILE`, its stderr piped.
fn server_command(h: &Harness, file: &std::path::Path, extra: &[&str]) -> Command {
    let mut c = Command::new(crate::common::harness::ROTORLOOP);
    c.args(["foxglove", "--domain", &h.domain, "127.0.0.1:0"]).args(extra);
    c.arg("--addr-file").arg(file).stdin(Stdio::null()).stderr(Stdio::piped());
    c
}

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
    /// The log: (name, level, message).
    logs: Vec<(String, i32, String)>,
    /// The last state's tick seen before each log message.
    log_ticks: Vec<Option<u64>>,
    /// Why the stream ended before the view did, if it did.
    ended: Option<String>,
}

/// Connects to `addr`, subscribes to `topics` (of the states, transforms and log), and
/// reads for `secs`, or until what was seen is `enough`.
fn view(addr: &str, secs: f64, topics: &[&str], enough: &dyn Fn(&Seen) -> bool) -> (Viewer, Seen) {
    let mut v = Viewer::connect(addr, Duration::from_millis(100)).expect("connect");
    assert_eq!(v.subprotocol, SUBPROTOCOL);
    v.subscribe(topics).expect("subscribe");
    let mut seen = Seen { stamps_match: true, ..Seen::default() };
    // `secs` of the loop's own time from the first state seen, not of wall time from the
    // connection: a loop slow to start on a loaded machine (the suite beside it) once
    // left a 3.5 s wall-time window with under 300 states. The end of the stream (the
    // run over) ends the view too; the callers' assertions judge what was seen.
    let deadline = Instant::now() + LIMIT;
    let (mut first_t, mut last_t) = (None::<f64>, 0.0);
    while Instant::now() < deadline && first_t.is_none_or(|f| last_t < f + secs) && !enough(&seen) {
        let m = match v.receive() {
            Ok(Some(m)) => m,
            Ok(None) => continue,
            Err(e) => {
                seen.ended = Some(format!("{e:#}"));
                break;
            }
        };
        match m.topic.as_str() {
            "/rotorloop/state" => {
                let s: serde_json::Value = serde_json::from_slice(&m.payload).expect("JSON state");
                last_t = s["t_s"].as_f64().expect("t_s");
                first_t.get_or_insert(last_t);
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
                seen.logs.push((l.name, l.level, l.message));
                seen.log_ticks.push(seen.ticks.last().copied());
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
    let all = ["/rotorloop/state", "/tf", "/rotorloop/log"];
    let (first, seen) = view(&addr, 1.5, &all, &|_| false);
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
    let (second, again) = view(&addr, 1.0, &all, &|_| false);
    assert!(
        again.ticks.first().is_some_and(|k| *k > last),
        "{:?} after {last}",
        again.ticks.first()
    );
    // A close while the states flow is answered (RFC 6455: 1000 for 1000), nothing comes
    // after the server's close, and the server ends the connection.
    let closed = second.close(Duration::from_secs(10)).expect("close");
    eprintln!("close while streaming: {closed:?}");
    assert_eq!(
        (closed.code, closed.after_close, closed.ended),
        (Some(1000), 0, true),
        "{closed:?}"
    );
    let output = wait_output(child, LIMIT);
    ok(&output);
    assert_untouched(&out, 0);
    h.assert_no_leftovers();
}

/// The gaps in `ticks` (messages the server dropped for a viewer that fell behind): each
/// pair of neighbours that are not consecutive.
fn gaps(ticks: &[u64]) -> Vec<(u64, u64)> {
    ticks.windows(2).filter(|w| w[1] != w[0] + 1).map(|w| (w[0], w[1])).collect()
}

/// Where `logs` say the controller's kill (by the fault schedule) as a fault (an error, as
/// run.mcap says it), its restart (said with it, when one look saw both, or as `up`
/// later), and safe mode entered and left, in run.mcap's words.
fn kill_said(logs: &[(String, i32, String)]) -> [Option<usize>; 4] {
    let error = foxglove::messages::log::Level::Error as i32;
    let at = |p: &dyn Fn(&(String, i32, String)) -> bool| logs.iter().position(p);
    let fault = at(&|(n, l, m)| n == "controller" && *l == error && m.starts_with("fault: gone"));
    let back = fault.and_then(|f| {
        let (n, _, m) = &logs[f];
        let later = logs[f + 1..].iter().position(|(r, _, m)| r == n && m.starts_with("up"));
        if m.contains("restarted") { Some(f) } else { later.map(|k| f + 1 + k) }
    });
    [
        fault,
        back,
        at(&|(_, _, m)| m.ends_with("entered safe mode")),
        at(&|(_, _, m)| m.ends_with("left safe mode")),
    ]
}

/// `rotorloop foxglove --domain D` attached to a loop as it starts serves its states and
/// logs the controller's kill (by the fault schedule at 2 s) as a fault, an error, and its
/// restart on `/rotorloop/log`; `kill -9` of the server in the middle of the run is nothing
/// to the loop.
#[test]
fn a_server_attached_to_a_running_loop_and_killed_is_no_matter_to_it() {
    let h = Harness::new("fxattach");
    let (child, out) = start(&h, "10", &["--fault", "controller:kill@2:restart@2.3"]);
    let file = h.path("fx.addr");
    let mut server = server_command(&h, &file, &[]).spawn().expect("spawn rotorloop foxglove");
    let addr = address(&file);
    // No transforms: two a tick would fill the server's queue for this viewer three times
    // as fast when the machine is busy (the queue drops the oldest, the log among them).
    // Until the kill is said, up to 7 s of the loop's 10: a server slowed by a busy
    // machine says it later than the states of its moment.
    let all_said = |s: &Seen| kill_said(&s.logs).iter().all(Option::is_some);
    let (v, seen) = view(&addr, 7.0, &["/rotorloop/state", "/rotorloop/log"], &all_said);
    if seen.ticks.len() <= 300 {
        // The server's own words on why, if it said any.
        let _ = server.kill();
        let said = server.wait_with_output().map(|o| o.stderr).unwrap_or_default();
        panic!(
            "{} states, {} logs (stream: {:?}; advertised: {:?}); the server said: {}",
            seen.ticks.len(),
            seen.logs.len(),
            seen.ended,
            v.channels.values().map(|(t, _)| t.as_str()).collect::<Vec<_>>(),
            String::from_utf8_lossy(&said)
        );
    }
    // A viewer that falls behind loses the oldest of what waits for it (the server's
    // queue, as the live view is documented), logs included: on a busy machine that is
    // allowed, but only where the states show the loss, a gap around the kill (2 s) and
    // restart (2.3 s).
    let said = kill_said(&seen.logs);
    let gaps = gaps(&seen.ticks);
    let lost_around_the_kill = gaps.iter().any(|&(a, b)| a < 3_300 && b > 1_900);
    let logs: Vec<_> = seen.logs.iter().zip(&seen.log_ticks).collect();
    if !lost_around_the_kill {
        assert!(
            said.iter().all(Option::is_some),
            "{logs:?} (after the tick; no state lost: {gaps:?}; ticks {:?} to {:?}; the \
             view: {:?})",
            seen.ticks.first(),
            seen.ticks.last(),
            seen.ended
        );
    }
    eprintln!("logs (after the tick): {logs:?}; states lost: {gaps:?}");
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

/// `rotorloop foxglove --domain D ADDR` serving (here before any loop appears) advertises
/// every channel to a viewer at once, and ends each connection as RFC 6455 says: a
/// viewer's close is answered with its code (1000),
/// text that is not UTF-8 gets 1007, a frame announced at 16 MiB gets 1009, and nothing
/// comes after the server's close; a viewer offering only the older name of the protocol,
/// `foxglove.websocket.v1`, is served. SIGTERM ends the server, exit 0, leaving nothing.
#[test]
fn the_server_closes_as_rfc_6455_says_and_speaks_the_older_subprotocol() {
    let h = Harness::new("fxclose");
    let file = h.path("fx.addr");
    let server = group(&mut server_command(&h, &file, &["--wait-s", "120"]))
        .stdout(Stdio::piped())
        .spawn()
        .expect("spawn rotorloop foxglove");
    let pid = server.id();
    let server = Running::from(server);
    let addr = address(&file);
    let poll = Duration::from_millis(50);
    let patience = Duration::from_secs(20);
    let ended = |c: Closed, code: u16| {
        assert_eq!((c.code, c.after_close, c.ended), (Some(code), 0, true), "{c:?}");
    };
    // Every channel is advertised before any loop appears: a channel made while a viewer
    // is connected can have its subscription refused by the SDK's server ("Unknown channel
    // ID"), which once left a viewer attached before the loop without states.
    let mut v = Viewer::connect(&addr, poll).expect("connect");
    let until = Instant::now() + patience;
    while v.channels.len() < 8 && Instant::now() < until {
        assert!(v.receive().expect("receive").is_none(), "no loop, no messages");
    }
    let mut topics: Vec<&str> = v.channels.values().map(|(t, _)| t.as_str()).collect();
    topics.sort_unstable();
    assert_eq!(
        topics,
        [
            "/rotorloop/incidents",
            "/rotorloop/latency",
            "/rotorloop/log",
            "/rotorloop/reference",
            "/rotorloop/state",
            "/rotorloop/torque",
            "/rotorloop/tracking",
            "/tf"
        ]
    );
    ended(v.close(patience).expect("close"), 1000);
    // A masked client frame by hand: FIN and opcode, the length announced, a zero mask.
    let frame = |opcode: u8, len: u64, payload: &[u8]| {
        let mut f = vec![0x80 | opcode, 0x80 | 127];
        f.extend(len.to_be_bytes());
        f.extend([0u8; 4]);
        f.extend(payload);
        f
    };
    let v = Viewer::connect(&addr, poll).expect("connect");
    ended(v.send_raw(&frame(0x1, 2, &[0xff, 0xfe]), patience).expect("bad text"), 1007);
    let v = Viewer::connect(&addr, poll).expect("connect");
    ended(v.send_raw(&frame(0x2, 16 << 20, &[0; 16]), patience).expect("16 MiB"), 1009);
    let old = Viewer::connect_with(&addr, poll, "foxglove.websocket.v1").expect("websocket.v1");
    assert_eq!(old.subprotocol, "foxglove.websocket.v1");
    ended(old.close(patience).expect("close"), 1000);
    // SAFETY: signals our own child, which has not been waited for.
    unsafe { libc::kill(pid as libc::pid_t, libc::SIGTERM) };
    ok(&wait_output(server, LIMIT));
    h.assert_no_leftovers();
}

/// `rotorloop foxglove --domain D` attached to a running loop whose controller is killed
/// and restarted: every JSON message it sends validates against the schema its channel
/// advertised (a JSON Schema validator) and carries no `NO_TICK`; the log and incidents
/// channels are advertised; the kill is a fault (an error) and a live incident, the
/// run's end no error; the latency's log times never go backwards. It ends by itself
/// after the loop, telling the viewer so (a close, 1001), exit 0, and the domain leaves
/// nothing in /dev/shm.
#[test]
fn an_attached_server_validates_and_ends_with_the_loop_leaving_nothing() {
    let h = Harness::new("fxvalid");
    let (child, out) = start(&h, "7", &["--fault", "controller:kill@4:restart@4.3"]);
    let file = h.path("fx.addr");
    let server = group(&mut server_command(&h, &file, &[]))
        .stdout(Stdio::piped())
        .spawn()
        .expect("spawn rotorloop foxglove");
    let server = Running::from(server);
    let addr = address(&file);
    let mut v = Viewer::connect(&addr, Duration::from_millis(100)).expect("connect");
    v.subscribe(&["*"]).expect("subscribe");
    let mut schemas = Schemas::default();
    let (mut logs, mut incidents, mut latency_times) = (Vec::new(), Vec::new(), Vec::new());
    let (mut ticks, mut bytes) = (Vec::new(), std::collections::BTreeMap::new());
    let until = Instant::now() + LIMIT;
    let mut end = None;
    // Until the server closes (the loop's end): every message of every topic.
    while Instant::now() < until {
        let m = match v.receive() {
            Ok(Some(m)) => m,
            Ok(None) => continue,
            Err(e) => {
                end = Some(format!("{e:#}"));
                break;
            }
        };
        let (schema_name, schema) = v.schemas.get(&m.topic).cloned().unwrap_or_default();
        let b = bytes.entry(m.topic.clone()).or_insert((0, 0));
        *b = (b.0 + 1, b.1 + m.payload.len());
        match m.topic.as_str() {
            "/tf" => continue,
            "/rotorloop/log" => {
                let l = <foxglove::messages::Log as prost::Message>::decode(&m.payload[..])
                    .expect("a Log");
                logs.push((l.name, l.level, l.message));
                continue;
            }
            "/rotorloop/latency" => latency_times.push(m.log_time),
            "/rotorloop/state" => {
                let s: serde_json::Value = serde_json::from_slice(&m.payload).expect("JSON");
                ticks.push(s["tick"].as_u64().expect("tick"));
            }
            "/rotorloop/incidents" => incidents.push(m.payload.clone()),
            _ => {}
        }
        if !schemas.checked.contains_key(&m.topic) {
            assert!(schema_name.starts_with("rotorloop."), "{}: {schema_name}", m.topic);
            schemas.declare(&m.topic, schema.as_bytes());
        }
        schemas.check(&m.topic, &m.payload);
    }
    // The server ends with the loop; its words explain a stream that fell short.
    let served = wait_output(server, LIMIT);
    let said = String::from_utf8_lossy(&served.stderr).into_owned();
    // The loop's end is said as RFC 6455 says: a close, 1001 (going away), not a reset.
    let end = end.unwrap_or_default();
    assert!(end.contains("closed the connection (1001"), "{end}; server: {said}");
    let topics: Vec<&String> = v.schemas.keys().collect();
    for t in ["/rotorloop/log", "/rotorloop/incidents", "/rotorloop/tracking"] {
        assert!(v.schemas.contains_key(t), "{t} not advertised: {topics:?}; server: {said}");
    }
    for t in ["state", "torque", "reference", "latency", "tracking"] {
        let n = schemas.checked.get(&format!("/rotorloop/{t}")).copied().unwrap_or(0);
        assert!(n > 1000, "{t}: {n} validated; server: {said}");
    }
    assert!(latency_times.windows(2).all(|w| w[1] >= w[0]), "latency log times go back");
    eprintln!("messages and payload bytes by topic: {bytes:?}");
    // As in the test above: what a viewer that fell behind lost (the oldest dropped) may
    // include the kill's incident and log, but only where the states show the loss, a gap
    // around the kill (4 s) and restart (4.3 s).
    let gaps = gaps(&ticks);
    let lost_around_the_kill = gaps.iter().any(|&(a, b)| a < 5_300 && b > 3_900);
    let error = foxglove::messages::log::Level::Error as i32;
    let errors: Vec<_> = logs.iter().filter(|(_, l, _)| *l == error).collect();
    if !lost_around_the_kill {
        assert!(!incidents.is_empty(), "the kill is a live incident (no state lost: {gaps:?})");
        assert!(!errors.is_empty(), "{logs:?} (no state lost: {gaps:?})");
    }
    assert!(
        errors.iter().all(|(n, _, m)| n == "controller" && m.starts_with("fault: gone")),
        "{logs:?}"
    );
    ok(&wait_output(child, LIMIT));
    assert_untouched(&out, 1);
    ok(&served);
    h.assert_no_leftovers();
}

/// A bad address of `rotorloop foxglove` is a usage error naming the argument the user
/// gave (`ADDR`), never `--foxglove`, a flag of another command.
#[test]
fn a_bad_address_of_rotorloop_foxglove_names_its_own_argument() {
    let h = Harness::new("fxbadpos");
    let o = h.rotorloop(&["foxglove", "--domain", &h.domain, "nowhere"], LIMIT);
    assert_eq!(o.status.code(), Some(2), "{o:?}");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("ADDR address `nowhere`") && !err.contains("--foxglove"), "{err}");
}
