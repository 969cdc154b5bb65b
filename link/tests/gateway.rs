//! Two gateways on loopback, each host its own iceoryx2 space: who may join, and in which
//! direction samples may go. Each refusal has a positive control beside it (the same
//! set-up with the permission given carries the samples), so a test cannot pass by
//! carrying nothing at all.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

#[path = "../../tests/common/old_layout.rs"]
mod old_layout;

use iceoryx2::prelude::ZeroCopySend;
use old_layout::StateSampleV2;
use rotorloop_common::clock::now_ns;
use rotorloop_common::graph::Topic;
use rotorloop_common::ipc::IpcError;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::ipc::ports::Inbox;
use rotorloop_common::ipc::wait::Wait;
use rotorloop_common::wire::{LAYOUT_VERSION, ReferenceSample, StateSample, TorqueSample};

const LINK: &str = env!("CARGO_BIN_EXE_rotorloop-link");

/// A gateway process, stopped (SIGKILL) when dropped.
struct Gateway(Child);

impl Drop for Gateway {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn gateway(domain: &str, host: &str, ready: &Path, extra: &[&str]) -> Gateway {
    let child = Command::new(LINK)
        .args(["--domain", domain, "--host", host, "--ready-file"])
        .arg(ready)
        .args(extra)
        .stdin(Stdio::null())
        .spawn()
        .expect("start rotorloop-link");
    Gateway(child)
}

/// A gateway whose messages (stderr) are collected as they come.
fn gateway_heard(
    domain: &str,
    host: &str,
    ready: &Path,
    extra: &[&str],
) -> (Gateway, std::sync::Arc<std::sync::Mutex<String>>) {
    use std::io::BufRead;
    let mut child = Command::new(LINK)
        .args(["--domain", domain, "--host", host, "--ready-file"])
        .arg(ready)
        .args(extra)
        .stdin(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start rotorloop-link");
    let heard = std::sync::Arc::new(std::sync::Mutex::new(String::new()));
    let (pipe, sink) = (child.stderr.take().expect("piped"), heard.clone());
    std::thread::spawn(move || {
        for line in std::io::BufReader::new(pipe).lines().map_while(Result::ok) {
            let mut s = sink.lock().unwrap_or_else(|e| e.into_inner());
            s.push_str(&line);
            s.push('\n');
        }
    });
    (Gateway(child), heard)
}

fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    l.local_addr().expect("addr").port()
}

fn wait_for(timeout: Duration, mut f: impl FnMut() -> bool) -> bool {
    let start = Instant::now();
    while start.elapsed() < timeout {
        if f() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    f()
}

fn torque(tick: u64) -> TorqueSample {
    TorqueSample { tick, ..Default::default() }
}

/// What crossed in each direction while both hosts published torques for `secs`: the
/// ticks host `a` received from `b` (≥ 9000) and host `b` received from `a` (< 9000).
fn exchange(domain: &str, secs: f64) -> (usize, usize) {
    let (a, b) = (
        Domain::on_host(domain, Some("a")).expect("a"),
        Domain::on_host(domain, Some("b")).expect("b"),
    );
    let (na, nb) = (a.node("plant").expect("node a"), b.node("monitor").expect("node b"));
    let out_a = a.outbox::<TorqueSample>(&na, Topic::Torque).expect("publisher a");
    let in_a = a.inbox::<TorqueSample>(&na, Topic::Torque, 64, false).expect("subscriber a");
    let out_b = b.outbox::<TorqueSample>(&nb, Topic::Torque).expect("publisher b");
    let in_b = b.inbox::<TorqueSample>(&nb, Topic::Torque, 64, false).expect("subscriber b");
    let (mut from_b_at_a, mut from_a_at_b) = (0, 0);
    let start = Instant::now();
    let mut k = 0;
    while start.elapsed().as_secs_f64() < secs {
        k += 1;
        out_a.send(torque(k), |_| {}).expect("send a");
        out_b.send(torque(9000 + k), |_| {}).expect("send b");
        in_a.drain(|t| from_b_at_a += usize::from(t.tick >= 9000)).expect("drain a");
        in_b.drain(|t| from_a_at_b += usize::from(t.tick < 9000)).expect("drain b");
        std::thread::sleep(Duration::from_millis(2));
    }
    (from_b_at_a, from_a_at_b)
}

/// Two hosts of one domain, `a` listening and `b` connected, on loopback. Bind every
/// field: the gateways write their ready files into `_dir` and stop when it is gone.
struct Pair {
    _dir: tempfile::TempDir,
    domain: String,
    a: Domain,
    b: Domain,
    gateways: (Gateway, Gateway),
}

fn connected_pair(tag: &str) -> Pair {
    let dir = tempfile::tempdir().expect("tempdir");
    let domain = format!("lk-{tag}-{}", std::process::id());
    let listen = format!("tcp/127.0.0.1:{}", free_port());
    let (ra, rb) = (dir.path().join("a"), dir.path().join("b"));
    let ga = gateway(&domain, "a", &ra, &["--listen", &listen]);
    let gb = gateway(&domain, "b", &rb, &["--connect", &listen]);
    assert!(wait_for(Duration::from_secs(10), || rb.exists()), "not connected");
    Pair {
        a: Domain::on_host(&domain, Some("a")).expect("a"),
        b: Domain::on_host(&domain, Some("b")).expect("b"),
        domain,
        gateways: (ga, gb),
        _dir: dir,
    }
}

fn cleanup(domain: &str) {
    for h in ["a", "b"] {
        let _ = Domain::on_host(domain, Some(h)).map(|d| d.cleanup());
    }
}

/// A listening gateway with a user/password dictionary: a peer without the credentials
/// never connects (and so can inject nothing); the same peer with them does, and samples
/// cross.
#[test]
fn a_peer_without_the_credentials_cannot_connect_or_inject() {
    let dir = tempfile::tempdir().expect("tempdir");
    std::fs::write(dir.path().join("users"), "loop:s3cret\n").expect("users");
    std::fs::write(dir.path().join("pw"), "s3cret\n").expect("pw");
    std::fs::write(dir.path().join("wrong"), "guess\n").expect("pw");
    let domain = format!("lk-auth-{}", std::process::id());
    let port = free_port();
    let listen = format!("tcp/127.0.0.1:{port}");
    let users = dir.path().join("users");
    let (ra, rb) = (dir.path().join("a.ready"), dir.path().join("b.ready"));
    let _a = gateway(
        &domain,
        "a",
        &ra,
        &["--listen", &listen, "--users", users.to_str().expect("utf8")],
    );
    for creds in [None, Some("wrong")] {
        let mut extra = vec!["--connect", listen.as_str()];
        let pw = creds.map(|f| dir.path().join(f));
        if let Some(pw) = &pw {
            extra.extend(["--user", "loop", "--password-file", pw.to_str().expect("utf8")]);
        }
        let b = gateway(&domain, "b", &rb, &extra);
        assert!(!wait_for(Duration::from_secs(3), || rb.exists()), "{creds:?} connected");
        let (in_a, _) = exchange(&domain, 1.0);
        assert_eq!(in_a, 0, "a peer with {creds:?} injected samples");
        drop(b);
        cleanup(&domain);
    }
    let pw = dir.path().join("pw");
    let extra =
        ["--connect", &listen, "--user", "loop", "--password-file", pw.to_str().expect("utf8")];
    let _b = gateway(&domain, "b", &rb, &extra);
    assert!(
        wait_for(Duration::from_secs(10), || rb.exists()),
        "the right credentials did not connect"
    );
    let (in_a, in_b) = exchange(&domain, 3.0);
    assert!(in_a > 0 && in_b > 0, "with the credentials samples must cross: {in_a} / {in_b}");
    drop((_a, _b));
    cleanup(&domain);
}

/// Issue 42: nothing fails silently. A users file that others can read is named with its
/// mode by the gateway that reads it, and a gateway whose password the other refuses says
/// that no peer accepted its credentials (Zenoh itself says nothing outside its debug
/// log); the same pair with the right password says neither (the control).
#[test]
fn a_refused_password_and_a_readable_users_file_are_reported() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().expect("tempdir");
    let users = dir.path().join("users");
    std::fs::write(&users, "loop:s3cret\n").expect("users");
    std::fs::set_permissions(&users, std::fs::Permissions::from_mode(0o644)).expect("chmod");
    for (password, refused) in [("guess", true), ("s3cret", false)] {
        let pw = dir.path().join(password);
        std::fs::write(&pw, format!("{password}\n")).expect("pw");
        std::fs::set_permissions(&pw, std::fs::Permissions::from_mode(0o600)).expect("chmod");
        let domain = format!("lk-said-{refused}-{}", std::process::id());
        let listen = format!("tcp/127.0.0.1:{}", free_port());
        let (ra, rb) =
            (dir.path().join(format!("{refused}a")), dir.path().join(format!("{refused}b")));
        let users_arg = users.to_str().expect("utf8");
        let (a, heard_a) =
            gateway_heard(&domain, "a", &ra, &["--listen", &listen, "--users", users_arg]);
        let pw_arg = pw.to_str().expect("utf8");
        let extra = ["--connect", &listen, "--user", "loop", "--password-file", pw_arg];
        let (b, heard_b) = gateway_heard(&domain, "b", &rb, &extra);
        let said =
            |h: &std::sync::Mutex<String>| h.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let refusal = "no peer accepted our credentials";
        if refused {
            let told = wait_for(Duration::from_secs(30), || said(&heard_b).contains(refusal));
            assert!(told, "a refused password went unsaid:\n{}", said(&heard_b));
            assert!(!rb.exists(), "a wrong password connected");
        } else {
            assert!(wait_for(Duration::from_secs(10), || rb.exists()), "not connected");
            // Longer than the gateway waits before it speaks of a refusal.
            std::thread::sleep(Duration::from_secs(6));
            assert!(!said(&heard_b).contains(refusal), "{}", said(&heard_b));
        }
        drop((a, b));
        let told = said(&heard_a);
        assert!(told.contains(&format!("--users {users_arg} (mode 0644)")), "{told}");
        let private = format!("--password-file {pw_arg} (mode");
        assert!(!said(&heard_b).contains(&private), "0600 is private: {}", said(&heard_b));
        cleanup(&domain);
    }
}

/// A read-only gateway (a remote monitor's host) receives the loop's samples but puts
/// nothing into the loop, even from a process on its host that publishes a torque; the
/// same set-up without `--read-only` carries that torque in.
#[test]
fn a_read_only_gateway_cannot_publish_into_the_loop() {
    let dir = tempfile::tempdir().expect("tempdir");
    for read_only in [true, false] {
        let domain = format!("lk-ro{}-{}", u8::from(read_only), std::process::id());
        let listen = format!("tcp/127.0.0.1:{}", free_port());
        let (ra, rb) =
            (dir.path().join(format!("{read_only}a")), dir.path().join(format!("{read_only}b")));
        let _a = gateway(&domain, "a", &ra, &["--listen", &listen]);
        let mut extra = vec!["--connect", listen.as_str()];
        if read_only {
            extra.push("--read-only");
        }
        let _b = gateway(&domain, "b", &rb, &extra);
        assert!(wait_for(Duration::from_secs(10), || rb.exists()), "not connected");
        let (in_a, in_b) = exchange(&domain, 3.0);
        assert!(
            in_b > 0,
            "the monitor's host must receive the loop's samples (read-only {read_only})"
        );
        if read_only {
            assert_eq!(in_a, 0, "a read-only gateway carried {in_a} samples into the loop");
        } else {
            assert!(in_a > 0, "without --read-only the torque must cross (the control)");
        }
        drop((_a, _b));
        cleanup(&domain);
    }
}

/// A gateway asked to listen beyond loopback without authentication refuses to start,
/// naming the endpoint (exit code 2), before it opens anything.
#[test]
fn an_unauthenticated_network_endpoint_is_refused_before_anything_opens() {
    let o = Command::new(LINK)
        .args(["--domain", "lk-open", "--listen", "tcp/0.0.0.0:7447"])
        .output()
        .expect("run");
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("tcp/0.0.0.0:7447") && err.contains("not on loopback"), "{err}");
}

/// The state service of host `a`, published by `T`, as host `b`'s controller opens it
/// through the link (once its mirror is there).
fn open_mirrored_state<T>(tag: &str) -> Result<(), IpcError>
where
    T: ZeroCopySend + std::fmt::Debug + Copy + 'static,
{
    let Pair { _dir, domain, a, b, gateways: (_a, _b) } = connected_pair(tag);
    let plant = a.node("plant").expect("node a");
    let _out = a.outbox::<T>(&plant, Topic::State).expect("state publisher on a");
    assert!(
        wait_for(Duration::from_secs(10), || b.topic_exists(Topic::State)),
        "the state service was not mirrored on b"
    );
    let controller = b.node("controller").expect("node b");
    let opened = b.inbox::<StateSample>(&controller, Topic::State, 8, false).map(drop);
    drop((controller, plant, _out, _a, _b));
    cleanup(&domain);
    opened
}

/// The link checks nothing but the type's name, size and alignment: a plant of an older
/// build on the other host is refused when the controller opens its mirrored service,
/// with the message a process of another layout gets on one host (naming both layout
/// versions); the same build on both hosts opens it (the control).
#[test]
fn a_peer_of_another_sample_layout_is_refused_across_the_link_as_on_one_host() {
    match open_mirrored_state::<StateSampleV2>("skew") {
        Err(e @ IpcError::LayoutSkew { .. }) => {
            let msg = e.to_string();
            let ours = format!("layout v{LAYOUT_VERSION}");
            assert!(msg.contains("layout v2") && msg.contains(&ours), "{msg}");
        }
        other => panic!("expected a layout skew error, got {other:?}"),
    }
    open_mirrored_state::<StateSample>("same").expect("the same layout opens");
}

/// Whether a sample `is_it` comes into `inbox` within `wait_ns`, waiting on its listener.
fn arrives<T>(inbox: &Inbox<T>, wait_ns: u64, is_it: impl Fn(&T) -> bool) -> bool
where
    T: ZeroCopySend + std::fmt::Debug + Copy + 'static,
{
    let got = inbox.wait_for(Wait::Event, now_ns() + wait_ns, |i| {
        let mut hit = None;
        i.drain(|x| hit = hit.or(is_it(&x).then_some(())))?;
        Ok(hit)
    });
    got.expect("wait").is_some()
}

/// Every sample that crosses the link wakes its receiver. A ping-pong between a plant on
/// host `a` and a controller on host `b`, each blocked on its listener (`Wait::Event`):
/// no receiver may find its sample only after a whole 10 ms bound passed without a
/// notification (`Inbox::unnotified`), but for one in 200 (a gateway not scheduled for
/// 10 ms on a loaded machine). Without the gateway's re-wake, a notification that
/// overtook its sample on the link left 3-8 % of round trips waiting out the bound.
#[test]
fn every_sample_that_crosses_the_link_wakes_its_receiver() {
    let Pair { _dir, domain, a, b, gateways: (_a, _b) } = connected_pair("wake");
    let (na, nb) = (a.node("plant").expect("node a"), b.node("controller").expect("node b"));
    let state_out = a.outbox::<StateSample>(&na, Topic::State).expect("state publisher");
    let torque_in = a.inbox::<TorqueSample>(&na, Topic::Torque, 8, true).expect("torque inbox");
    let state_in = b.inbox::<StateSample>(&nb, Topic::State, 8, true).expect("state inbox");
    let torque_out = b.outbox::<TorqueSample>(&nb, Topic::Torque).expect("torque publisher");
    let init =
        rotorloop_common::scenario::Scenario::load("paper-zero").expect("builtin").plant_init;
    // One round trip of tick `k`: whether both samples came within `wait_ns` each.
    let trip = |k: u64, wait_ns: u64| {
        state_out.send(StateSample::of(k, 0.0, &init), |_| {}).expect("send");
        arrives(&state_in, wait_ns, |s| s.tick == k) && {
            torque_out.send(torque(k), |_| {}).expect("send");
            arrives(&torque_in, wait_ns, |t| t.tick == k)
        }
    };
    // Until one round trip has crossed: the mirrors and their bridges are up.
    let first = (1..=500).find(|&k| trip(k, 20_000_000)).expect("no round trip in 500 tries");
    let before = (state_in.unnotified(), torque_in.unnotified());
    const TRIPS: u64 = 1000;
    for k in first + 1..=first + TRIPS {
        assert!(trip(k, 2_000_000_000), "round trip {k} lost a sample");
        std::thread::sleep(Duration::from_micros(500));
    }
    let lost = (state_in.unnotified() - before.0, torque_in.unnotified() - before.1);
    // A gateway that is not scheduled for 10 ms between a sample's landing and its wake-up
    // (a loaded machine: seen once in 1000, 1 state, with a lockstep day and the test
    // suite on 2 vCPUs) looks the same from here; the defect this guards against left
    // 30 to 80 of 1000.
    assert!(
        lost.0 + lost.1 <= TRIPS / 200,
        "(states, torques) {lost:?} of {TRIPS} round trips found only after a 10 ms wait with \
         no wake-up"
    );
    drop((state_out, torque_in, state_in, torque_out, na, nb, _a, _b));
    cleanup(&domain);
}

/// A gateway's resident memory, from `/proc` (KiB).
fn rss_kib(g: &Gateway) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{}/status", g.0.id())).expect("status");
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).expect("VmRSS");
    line.split_whitespace().nth(1).and_then(|v| v.parse().ok()).expect("a number")
}

/// A gateway that bridges the loop's three topics holds little memory. With iceoryx2-link
/// 0.10 as published, the link's publisher of each bridged service prepared all 255
/// segments it could ever grow to: 67 MB of reference counters per service at a
/// 4096-sample subscriber buffer, so 260 MiB per gateway, touched while it discovered
/// (on a loaded machine up to half a second in which nothing crossed, and the plant went
/// into safe mode at the start of split runs). The vendored link allocates the publishers
/// of fixed-size samples statically (`vendor/iceoryx2-link/PATCH.md`): 26 MiB.
#[test]
fn a_gateway_that_bridges_the_loop_holds_little_memory() {
    let Pair { _dir, domain, a, b, gateways: (ga, gb) } = connected_pair("rss");
    let (na, nb) = (a.node("plant").expect("node a"), b.node("controller").expect("node b"));
    let state_out = a.outbox::<StateSample>(&na, Topic::State).expect("state publisher");
    let refs_out = a.outbox::<ReferenceSample>(&na, Topic::Reference).expect("reference");
    let torque_in = a.inbox::<TorqueSample>(&na, Topic::Torque, 8, true).expect("torque inbox");
    let state_in = b.inbox::<StateSample>(&nb, Topic::State, 8, true).expect("state inbox");
    let refs_in = b.inbox::<ReferenceSample>(&nb, Topic::Reference, 128, true).expect("refs");
    let torque_out = b.outbox::<TorqueSample>(&nb, Topic::Torque).expect("torque publisher");
    let init =
        rotorloop_common::scenario::Scenario::load("paper-zero").expect("builtin").plant_init;
    // Until each topic has crossed: every service is bridged by both gateways.
    let crossed = (1..=500).find(|&k| {
        state_out.send(StateSample::of(k, 0.0, &init), |_| {}).expect("send");
        refs_out.send(ReferenceSample::zeroed(k), |_| {}).expect("send");
        arrives(&state_in, 20_000_000, |s| s.tick == k)
            && arrives(&refs_in, 20_000_000, |r| r.tick == k)
            && {
                torque_out.send(torque(k), |_| {}).expect("send");
                arrives(&torque_in, 20_000_000, |t| t.tick == k)
            }
    });
    crossed.expect("the three topics did not cross in 500 tries");
    const BOUND_KIB: u64 = 96 * 1024;
    for (host, g) in [("a", &ga), ("b", &gb)] {
        let rss = rss_kib(g);
        assert!(rss < BOUND_KIB, "the gateway of {host} holds {rss} KiB (bound {BOUND_KIB})");
    }
    drop((state_out, refs_out, torque_in, state_in, refs_in, torque_out, na, nb, ga, gb));
    cleanup(&domain);
}
