//! Seeing a loop that runs: `rotorloop ps`, `rotorloop watch`, and iceoryx2's own CLI
//! finding a run's services from the config the run writes. The observers are passive:
//! a run watched has the same ports on its services as one that is not.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::common::harness::{Harness, Running, group, ok};
const LIMIT: Duration = Duration::from_secs(240);

fn start(h: &Harness, seconds: &str) -> (Running, std::path::PathBuf) {
    let out = h.path("run");
    let child = group(&mut Command::new(crate::common::harness::ROTORLOOP))
        .args([
            "run",
            "--scenario",
            "paper-sinusoid",
            "--mode",
            "realtime",
            "--duration",
            seconds,
            "--quiet",
        ])
        .args(["--domain", &h.domain, "--out"])
        .arg(&out)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn");
    let child = Running::from(child);
    // Running: the plant has published and the monitor written rows.
    let until = Instant::now() + LIMIT;
    while std::fs::read(out.join("trace.csv")).map_or(0, |t| t.len()) < 50_000 {
        assert!(Instant::now() < until, "the run did not start");
        std::thread::sleep(Duration::from_millis(20));
    }
    (child, out)
}

/// How long each test's run lasts at most: a test stops its run ([`stop`]) once it has
/// seen what it looks for. Long, so that no step of a test can outlast it on a loaded
/// machine: under `repeat-tests --load` a process took up to 13 s to start (tmux's
/// `new-session` to the `watch` it runs; the `watch` drew 0.3 s after its `exec`), and a
/// 9 s run once ended before the test's `ps` looked.
const RUN_S: &str = "300";

/// Stops a run of [`start`] as Ctrl-C does: exit 3 (stopped before its last tick), a
/// partial report, nothing left behind.
fn stop(h: &Harness, child: Running) {
    let o = child.terminate(LIMIT);
    assert_eq!(o.status.code(), Some(3), "{}", String::from_utf8_lossy(&o.stderr));
    h.assert_no_leftovers();
}

/// A child's stdout, line by line, as it writes them.
fn lines_of(out: std::process::ChildStdout) -> std::sync::mpsc::Receiver<String> {
    use std::io::BufRead;
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(out).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

fn json_of(h: &Harness, args: &[&str]) -> serde_json::Value {
    let text = ok(&h.rotorloop(args, LIMIT));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{e}: {text}"))
}

/// The pub-sub services iceoryx2 lists with the config the run wrote into its directory:
/// the same lookup `cd DIR && iox2 service list` does.
fn services(dir: &std::path::Path) -> Vec<String> {
    use iceoryx2::prelude::*;
    let text = std::fs::read_to_string(dir.join("config/iceoryx2.toml")).expect("config written");
    let config: iceoryx2::config::Config = toml::from_str(&text).expect("iceoryx2 reads it");
    let mut names = Vec::new();
    ipc::Service::list(&config, |s| {
        use iceoryx2::service::static_config::messaging_pattern::MessagingPattern as P;
        if matches!(s.static_details.messaging_pattern(), P::PublishSubscribe(_)) {
            names.push(s.static_details.name().as_str().to_owned());
        }
        CallbackProgression::Continue
    })
    .expect("list");
    names.sort();
    names
}

/// A run writes its domain's iceoryx2 config (prefix, root path) to `DIR/config/iceoryx2.toml`,
/// where iceoryx2's CLI looks, and with it iceoryx2 lists exactly the run's services.
#[test]
fn the_run_directory_holds_the_iceoryx2_config_that_finds_its_services() {
    let h = Harness::new("iox2cfg");
    let (child, out) = start(&h, RUN_S);
    let text = std::fs::read_to_string(out.join("config/iceoryx2.toml")).expect("config");
    let prefix = format!("rl_{}_", h.domain);
    let t: toml::Value = toml::from_str(&text).expect("toml");
    assert_eq!(t["global"]["prefix"].as_str(), Some(prefix.as_str()));
    assert_eq!(
        t["global"]["root-path"].as_str(),
        Some(format!("{}{prefix}/", rotorloop_common::ipc::domain::ICEORYX2_ROOT).as_str())
    );
    let services = services(&out);
    let want: Vec<String> = ["reference", "state", "torque"]
        .iter()
        .map(|t| format!("rotorloop/{}/{t}", h.domain))
        .collect();
    assert_eq!(services, want);
    stop(&h, child);
}

/// `rotorloop ps --domain D --json` of a running loop: the four roles alive with their
/// pids, a core and a policy, the plant's rate near 1 kHz, progress marks, and the nodes
/// attached to each service; it creates nothing (no node of its own appears).
#[test]
fn ps_lists_the_roles_of_a_running_loop_and_creates_nothing() {
    let h = Harness::new("ps");
    let (child, _out) = start(&h, RUN_S);
    let v = json_of(&h, &["ps", "--domain", &h.domain, "--json", "--sample-ms", "300"]);
    let d = &v[0];
    assert_eq!(d["domain"], h.domain.as_str());
    let roles = d["roles"].as_array().expect("roles");
    let names: Vec<&str> = roles.iter().filter_map(|r| r["role"].as_str()).collect();
    assert_eq!(names, ["monitor", "reference", "controller", "plant"], "no node but the loop's");
    for r in roles {
        assert_eq!(r["state"], "alive", "{r}");
        assert!(
            r["pid"].as_u64().expect("pid") > 0 && r["core"].is_u64() && r["policy"] == "other",
            "{r}"
        );
    }
    let rate = d["rate_hz"].as_f64().expect("rate");
    assert!(rate > 500.0 && rate < 1500.0, "rate {rate}");
    assert!(d["ticks"]["plant"].as_u64().expect("tick") > 100);
    let state = d["services"]
        .as_array()
        .expect("services")
        .iter()
        .find(|s| {
            s["name"] == format!("rotorloop/{}/state", h.domain)
                && s["pattern"] == "publish_subscribe"
        })
        .expect("state service")
        .clone();
    assert_eq!(state["nodes"].as_array().expect("nodes").len(), 4, "{state}");
    stop(&h, child);
}

/// `rotorloop watch --once --json` on a running loop shows it ticking at about 1 kHz
/// with tick lateness and actuation delays; a controller killed by hand and restarted by
/// the supervisor shows as a restart in the lines `watch` prints without a terminal; the
/// monitor, with the watchers attached, loses no sample.
#[test]
fn watch_shows_a_running_loop_and_a_restart_as_it_happens() {
    let h = Harness::new("watch");
    // The run outlasts every step (see `RUN_S`): with 9 s, under `repeat-tests --load`,
    // `ps` once found the domain empty.
    let started = Instant::now();
    let (mut child, out) = start(&h, RUN_S);
    let first = json_of(&h, &["watch", "--domain", &h.domain, "--once", "--seconds", "1"]);
    assert!(first["rate_hz"].as_f64().expect("rate") > 500.0, "{first}");
    assert!(first["tick_lateness_1s"]["count"].as_u64().expect("count") > 50, "{first}");
    assert!(first["actuation_delay_1s"]["p50"].as_f64().expect("p50") > 0.0, "{first}");
    assert!(first["err_deg"].is_f64(), "{first}");
    // The watcher streams plain lines (no terminal) until it is stopped, so that it sees
    // the restart however long a loaded machine takes to start it and the `ps` below.
    let mut watcher = group(&mut Command::new(crate::common::harness::ROTORLOOP))
        .args(["watch", "--domain", &h.domain])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("watch");
    let lines = lines_of(watcher.stdout.take().expect("stdout"));
    let watcher = Running::from(watcher);
    // Its first block: it has seen the controller's pid before the kill.
    let mut shown = vec![lines.recv_timeout(LIMIT).expect("the watcher printed nothing")];
    let ps = json_of(&h, &["ps", "--domain", &h.domain, "--json", "--sample-ms", "10"]);
    // While watched: still only the loop's four nodes on its services, no port of the
    // watcher's.
    let roles = ps[0]["roles"].as_array().expect("roles").len();
    if roles != 4 {
        let (ago, ended) = (started.elapsed(), child.ended());
        panic!("{roles} roles, not 4, {ago:?} after the run's start (ended: {ended:?}): {ps}");
    }
    for svc in ps[0]["services"].as_array().expect("services") {
        assert!(svc["nodes"].as_array().expect("nodes").len() <= 4, "{svc}");
    }
    let pid = ps[0]["roles"]
        .as_array()
        .expect("roles")
        .iter()
        .find(|r| r["role"] == "controller")
        .expect("controller")["pid"]
        .as_u64()
        .expect("pid");
    // SAFETY: kills a process of this test's own run.
    unsafe { libc::kill(pid as libc::pid_t, libc::SIGKILL) };
    while !shown.last().is_some_and(|l| l.contains("controller restarted (pid")) {
        match lines.recv_timeout(LIMIT) {
            Ok(line) => shown.push(line),
            Err(e) => panic!("no restart seen ({e}):\n{}", shown.join("\n")),
        }
    }
    ok(&watcher.terminate(LIMIT));
    stop(&h, child);
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).expect("summary"))
            .expect("json");
    for (name, c) in s["subscribers"].as_object().expect("subscribers") {
        if name.starts_with("monitor.") {
            assert_eq!(c["lost"], 0, "{name}: the watcher cost the monitor samples");
        }
    }
}

/// `watch` in a terminal draws its charts: in a tmux window of 160×50, its screen
/// (`tmux capture-pane`, looked at every 250 ms for up to a minute) shows the three charts
/// (attitude error, actuation delay p50/p99, misses per second) with points drawn in them
/// (braille cells). Skipped with a message where tmux is not installed.
#[test]
fn watch_in_a_terminal_draws_its_charts() {
    if Command::new("tmux").arg("-V").output().is_err() {
        eprintln!("skipped: tmux is not installed");
        return;
    }
    let h = Harness::new("wtmux");
    // The screen looked at until it shows the charts, for up to a minute: under
    // `repeat-tests --load`, tmux once took 13 s to start the `watch` (which drew 0.3 s
    // after its start); with 9 s and one look after 5 s the pane was once empty.
    let (child, _out) = start(&h, RUN_S);
    let socket = h.path("tmux");
    let tmux = |args: &[&str]| {
        Command::new("tmux").arg("-S").arg(&socket).args(args).stdin(Stdio::null()).output()
    };
    let watch = format!("{} watch --domain {}", crate::common::harness::ROTORLOOP, h.domain);
    let started = tmux(&["new-session", "-d", "-s", "w", "-x", "160", "-y", "50", &watch]);
    assert!(started.as_ref().is_ok_and(|o| o.status.success()), "{started:?}");
    let titles = ["attitude error", "actuation delay", "misses per second", "controlling"];
    let drawn =
        |screen: &str| screen.chars().filter(|c| ('\u{2801}'..='\u{28ff}').contains(c)).count();
    let since = Instant::now();
    let (mut screen, mut capture_err) = (String::new(), String::new());
    while since.elapsed() < Duration::from_secs(60) {
        std::thread::sleep(Duration::from_millis(250));
        let shown = tmux(&["capture-pane", "-p", "-t", "w"]).expect("capture-pane");
        screen = String::from_utf8_lossy(&shown.stdout).into_owned();
        capture_err = String::from_utf8_lossy(&shown.stderr).into_owned();
        if titles.iter().all(|t| screen.contains(t)) && drawn(&screen) > 10 {
            break;
        }
    }
    let _ = tmux(&["kill-server"]);
    let looked = since.elapsed();
    for title in titles {
        assert!(screen.contains(title), "no {title} after {looked:?} ({capture_err}):\n{screen}");
    }
    let cells = drawn(&screen);
    assert!(cells > 10, "{cells} braille cells drawn after {looked:?}:\n{screen}");
    stop(&h, child);
}
