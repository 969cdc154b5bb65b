//! The gateway loop: one thread drives iceoryx2's link. It blocks (ppoll) on the
//! carrier's wake (something arrived from the other host) and on listeners of the
//! domain's own event services (a role here published), at most `LOOK_ANYWAY_NS`, then
//! propagates; every `--discover-ms` it runs the link's discovery and says what it
//! bridges. Nothing crosses while a discovery runs (3-7 ms on 2 vCPUs), so it is rare.
//!
//! The listeners belong to the link's own node, so the link never takes them for a local
//! offer to export. The link's event bridge carries the roles' notifications, but a
//! notification can overtake its sample: iceoryx2-link 0.10 propagates samples before
//! events within one pass, yet when a role publishes and notifies while the sending
//! gateway is inside a pass, the event leaves in that pass and the sample in the next; on
//! the other host the receiver is woken before its sample is there, and nothing wakes it
//! when the sample lands. Its wait is bounded at 10 ms, which was the 10 ms mode of 3-8 %
//! of link round trips. So after every pass that follows an arrival from the other host,
//! the gateway notifies the receivers of the topics that come in (those no role here
//! publishes), skipping the link's own listeners as the link's bridge does.

use std::collections::BTreeSet;
use std::time::Duration;

use anyhow::Context;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::*;
use iceoryx2_bb_posix::file_descriptor::FileDescriptorBased;
use iceoryx2_integrations_zenoh_link_carrier::ZenohCarrier;
use iceoryx2_link::Link;
use iceoryx2_link_tunnel::Tunnel;
use rotorloop_common::clock::now_ns;
use rotorloop_common::graph::Topic;
use rotorloop_common::ipc::domain::{Domain, HeldTopic};
use rotorloop_common::ipc::wait::wait_any_readable;
use rotorloop_common::signals::{install_signal_handlers, shutdown_requested};
use zenoh::Wait;

use crate::config::{
    ConfigError, GatewayWait, LinkArgs, endpoints, loose_secret_files, zenoh_config,
};

type ZenohLink = Link<ipc::Service, Tunnel<ZenohCarrier>>;

/// The gateway propagates at least this often, woken or not. Frames from the other host
/// are sometimes left in the carrier's inbox with no wake-up pending (cause not found in
/// iceoryx2-link 0.10): with discovery every 500 ms and no other bound, the carrier's
/// inboxes (64 frames each) overflowed and dropped 15101 frames in a 10 s loop at 1 kHz;
/// with this bound, none, and the loop's misses fell from 6268 to 621 of 10000.
const LOOK_ANYWAY_NS: u64 = 5_000_000;

/// While nothing is bridged yet, and for this long after what is bridged changed, the
/// gateway discovers every [`SETTLING_PERIOD_NS`] rather than every `--discover-ms`: at
/// 500 ms from the start a loaded CI run's plant gateway bridged the loop only after the
/// plant had gone into safe mode, and that run never ended.
const SETTLE_NS: u64 = 2_000_000_000;
/// See [`SETTLE_NS`]: the discovery period of earlier versions.
const SETTLING_PERIOD_NS: u64 = 20_000_000;

/// A gateway without a peer for this long says so, once per such stretch (issue 42).
/// Zenoh refuses a peer whose credentials do not match without a word on either side
/// (it logs at debug level, with `RUST_LOG`): a wrong password looked like a gateway that
/// waits. On loopback the sessions of a split run are up within a second.
const ALONE_WARN_NS: u64 = 5_000_000_000;

/// Runs the gateway until SIGINT or SIGTERM.
pub fn run(args: &LinkArgs) -> anyhow::Result<()> {
    let spin = args.wait == GatewayWait::Spin;
    let zenoh_cfg = zenoh_config(args)?;
    let who = format!("link[{}]", args.host.as_deref().unwrap_or(&args.domain));
    for w in loose_secret_files(args, &zenoh_cfg) {
        eprintln!("{who}: warning: {w}");
    }
    let connect = endpoints(&zenoh_cfg, "connect/endpoints");
    let refuses =
        crate::config::config_string(&zenoh_cfg, "transport/auth/usrpwd/dictionary_file").is_some();
    // iceoryx2's notice that no config file was loaded is noise (the domain makes its own);
    // the link's warnings (a dropped arrival, a failed bridge) are not.
    rotorloop_common::ipc::quiet_iceoryx_logs();
    let domain = Domain::on_host(&args.domain, args.host.as_deref())
        .map_err(|e| ConfigError::Bad(e.to_string()))?;
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Warn);
    install_signal_handlers();
    // A killed predecessor's ports would hold the services' gateway slots.
    let _ = domain.cleanup();
    let node = domain.node("link").context("link")?;
    // The node that holds this host's topics offered while a role here restarts (see
    // `Gateway::hold`); its own, because the link's node does not count as offering.
    let hold_node = domain.node("link-hold").context("link")?;
    let zenoh_cfg_copy = zenoh_cfg.clone();
    let session = zenoh::open(zenoh_cfg)
        .wait()
        .map_err(|e| anyhow::anyhow!("cannot open the Zenoh session: {e}"))?;
    // The listener's answer to the connecting side's question (`proof`), and the
    // connecting side's gate: nothing crosses to a peer that has not answered it.
    let _answerer =
        crate::proof::Answerer::open(&session, &zenoh_cfg_copy, &args.domain, args.test_proof)?;
    let mut gate = crate::proof::Gate::open(&session, &zenoh_cfg_copy, &args.domain)?;
    let carrier = ZenohCarrier::open(session.clone())
        .map_err(|e| anyhow::anyhow!("cannot create the Zenoh carrier: {e}"))?;
    let prefix = domain.service_prefix();
    let filter_prefix = prefix.clone();
    let mut link = Link::new(node, Tunnel::new(carrier, domain.config()))
        .with_filter(move |name: &ServiceName| name.as_str().starts_with(&filter_prefix));
    let wake =
        link.listener().map_err(|e| anyhow::anyhow!("cannot create the link's wake: {e}"))?;
    let side = match args.read_only {
        true => "read-only: imports the loop's topics, puts nothing into it",
        false => "both directions",
    };
    let host = args.host.as_deref().unwrap_or("this machine");
    eprintln!("{who}: domain `{}` on host `{host}` ({side}); bridging {prefix}*", args.domain);
    let mut g = Gateway {
        who,
        prefix,
        domain,
        events: Default::default(),
        hold_node,
        held: Default::default(),
        bridged: BTreeSet::new(),
        peers: 0,
        alone: Alone { since: now_ns(), warned: false, connect, refuses },
        errors: 0,
        discovery: Durations::default(),
        changed_at: 0,
        proofs_said: 0,
    };
    let period = args.discover_ms.max(1) * 1_000_000;
    let mut next_discover = 0;
    let mut arrived = false;
    while !shutdown_requested() {
        let now = now_ns();
        // Every pass: a transport that opened or closed since the peers were proven is
        // asked about before anything more crosses, and none opens during the pass.
        let held = match gate.as_mut().map(|gate| gate.hold(&session)).transpose() {
            Err(e) => return Err(anyhow::anyhow!("{}: {e}", g.who)),
            Ok(Some(None)) => {
                // No peer yet: nothing to carry, nothing offered; look again shortly.
                g.peers_changed(&session, args)?;
                if let Some(w) = g.alone.warning(g.peers, now_ns()) {
                    eprintln!("{}: warning: {w}", g.who);
                }
                std::thread::sleep(Duration::from_millis(5));
                continue;
            }
            Ok(held) => held.flatten(),
        };
        if now >= next_discover {
            let cpu = thread_cpu_ns();
            g.discover(&mut link, &session, args)?;
            // Until the domain's services are bridged and have stayed so for a while, look
            // as often as before (a loop starting up); then every --discover-ms.
            let settling = g.bridged.is_empty() || now < g.changed_at + SETTLE_NS;
            next_discover = now + if settling { SETTLING_PERIOD_NS.min(period) } else { period };
            g.discovery.add(now_ns() - now, thread_cpu_ns().saturating_sub(cpu));
            // Outside the timed discovery: its check of the endpoints may take a second.
            if let Some(w) = g.alone.warning(g.peers, now_ns()) {
                eprintln!("{}: warning: {w}", g.who);
            }
        }
        if let Err(e) = link.propagate() {
            g.error("propagate", &e);
        }
        if arrived {
            g.rewake_incoming();
        }
        drop(held);
        if let Some(n) = gate.as_ref().map(|g| g.proofs()).filter(|n| *n > g.proofs_said) {
            let again = if g.proofs_said > 0 { " (again: a new transport)" } else { "" };
            eprintln!("{}: the listening gateway proved it is the run's{again}", g.who);
            g.proofs_said = n;
        }
        if !spin {
            g.wait(&wake, next_discover.saturating_sub(now_ns()).min(LOOK_ANYWAY_NS))?;
        }
        arrived = g.drain(&wake);
    }
    eprintln!("{}: stopping; {}", g.who, g.discovery);
    Ok(())
}

/// What the loop keeps between passes.
struct Gateway {
    /// `link[HOST]`, what its messages start with.
    who: String,
    /// `rotorloop/<domain>/`: the services it bridges.
    prefix: String,
    domain: Domain,
    /// The gateway's ports per topic whose event service exists here.
    events: [Option<TopicEvents>; 3],
    /// The node that holds this host's topics (not the link's).
    hold_node: Node<ipc::Service>,
    /// Each topic's services, held once a role here made them ([`Gateway::hold`]).
    held: [Option<HeldTopic>; 3],
    /// `(service, pattern)` bridged at the last discovery.
    bridged: BTreeSet<(String, &'static str)>,
    peers: usize,
    /// Since when the gateway has had no peer, and whether it said so.
    alone: Alone,
    errors: u64,
    /// How long discoveries took: the loop propagates nothing while one runs.
    discovery: Durations,
    /// When the bridged set last changed.
    changed_at: u64,
    /// The gate's proofs said so far.
    proofs_said: u64,
}

/// What the discoveries took: count, total and longest, in wall-clock time (nothing
/// crosses meanwhile) and, for the longest, in the gateway thread's CPU time. A
/// discovery's wall time includes any time the process was stopped in it (Ctrl-Z, a
/// `stop` fault) or blocked; the CPU time tells such a wait from work.
#[derive(Default)]
struct Durations {
    n: u64,
    total_ns: u64,
    max_ns: u64,
    /// The CPU time of the longest.
    max_cpu_ns: u64,
}

impl Durations {
    fn add(&mut self, wall_ns: u64, cpu_ns: u64) {
        (self.n, self.total_ns) = (self.n + 1, self.total_ns + wall_ns);
        if wall_ns >= self.max_ns {
            (self.max_ns, self.max_cpu_ns) = (wall_ns, cpu_ns);
        }
    }
}

/// `N discoveries took … on average, … at most …` (the gateway's last words).
impl std::fmt::Display for Durations {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.n == 0 {
            return write!(f, "no discovery ran");
        }
        write!(
            f,
            "{} discoveries took {} on average, {} at most (nothing crosses meanwhile)",
            self.n,
            duration(self.total_ns / self.n),
            duration(self.max_ns)
        )?;
        // More than a few milliseconds off the CPU: say so, it is not the link's work.
        let waited = self.max_ns.saturating_sub(self.max_cpu_ns);
        if waited > 10_000_000 && waited > self.max_ns / 2 {
            write!(
                f,
                "; the longest spent {} on the CPU and waited the rest (blocked, or the \
                 gateway was stopped)",
                duration(self.max_cpu_ns)
            )?;
        }
        Ok(())
    }
}

/// A duration in the unit that reads best: µs below 10 ms, ms below 10 s, then s.
fn duration(ns: u64) -> String {
    match ns {
        0..10_000_000 => format!("{} µs", ns / 1_000),
        10_000_000..10_000_000_000 => format!("{} ms", ns / 1_000_000),
        _ => format!("{:.1} s", ns as f64 / 1e9),
    }
}

/// The CPU time this thread has used (ns): `CLOCK_THREAD_CPUTIME_ID`.
fn thread_cpu_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes into the timespec we own.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    u64::try_from(ts.tv_sec).unwrap_or(0) * 1_000_000_000 + u64::try_from(ts.tv_nsec).unwrap_or(0)
}

impl Gateway {
    /// One discovery: the link's, then what it bridges and whether the peer is there.
    fn discover(
        &mut self,
        link: &mut ZenohLink,
        session: &zenoh::Session,
        args: &LinkArgs,
    ) -> anyhow::Result<()> {
        if let Err(e) = link.discover() {
            self.error("discover", &e);
        }
        self.hold();
        for (slot, topic) in self.events.iter_mut().zip(Topic::ALL) {
            if slot.is_none() {
                let ports = self.domain.event_ports_if_exists(link.node(), topic).ok().flatten();
                *slot = ports.map(|(listener, notifier)| TopicEvents {
                    listener,
                    notifier,
                    published_here: false,
                });
            }
        }
        self.peers_changed(session, args)?;
        let now = bridged(link, self.domain.config(), &self.prefix);
        for (name, pattern) in now.difference(&self.bridged) {
            eprintln!("{}: bridging {name} ({pattern})", self.who);
        }
        for (name, pattern) in self.bridged.difference(&now) {
            eprintln!("{}: no longer bridging {name} ({pattern})", self.who);
        }
        if now != self.bridged {
            self.changed_at = now_ns();
        }
        self.bridged = now;
        Ok(())
    }

    /// Says when the peers came or went, and writes the ready file at the first.
    fn peers_changed(&mut self, session: &zenoh::Session, args: &LinkArgs) -> anyhow::Result<()> {
        let peers = session.info().peers_zid().wait().count();
        if peers != self.peers {
            match peers {
                0 => eprintln!("{}: the other host's gateway is gone; waiting for it", self.who),
                n => eprintln!("{}: connected to {n} peer(s)", self.who),
            }
            if peers == 0 {
                (self.alone.since, self.alone.warned) = (now_ns(), false);
            }
            if self.peers == 0 {
                if let Some(f) = args.ready_file.as_ref().filter(|_| peers > 0) {
                    rotorloop_common::outdir::write_file(f, b"connected\n")
                        .with_context(|| format!("cannot write {}", f.display()))?;
                }
            }
            self.peers = peers;
        }
        Ok(())
    }

    /// Holds every topic a role on this host publishes or subscribes, once its services
    /// exist, for as long as the gateway runs. The link offers a service to the other host
    /// while a node other than its own is attached to it; without the hold, a role killed
    /// here (the only one on its host, as a far-host controller) took every topic out of
    /// the offer: both hosts closed all their bridges and reopened them when the restarted
    /// role came back. Held, no bridge closes through a restart and the new role's ports
    /// join the open bridges: with a busy loop per core, control came back 180-330 ticks
    /// after the restart in 15 of 18 runs, against 400-940 in 8 of 11 before. (The other
    /// runs, before and after, took 4 s or more: the restarted controller's own start,
    /// its iceoryx2 node's fsync'd details file on the disk; see `ICEORYX2_ROOT` and
    /// docs/across-machines.md.)
    fn hold(&mut self) {
        for (slot, topic) in self.held.iter_mut().zip(Topic::ALL) {
            if slot.is_none() && self.domain.used_by_a_role_here(topic) {
                *slot = self.domain.hold_if_exists(&self.hold_node, topic).ok().flatten();
            }
        }
    }

    /// Blocks until the carrier or a local event wakes the gateway, or `timeout_ns`.
    fn wait(
        &self,
        wake: &Listener<iceoryx2_link_backend::WakeService>,
        timeout_ns: u64,
    ) -> anyhow::Result<()> {
        // SAFETY: the listeners own their descriptors and outlive this call; only polled.
        let fd = |l: &dyn FileDescriptorBased| unsafe { l.file_descriptor().native_handle() };
        let mut fds = [fd(wake); 4];
        for (slot, e) in fds[1..].iter_mut().zip(self.events.iter().flatten()) {
            *slot = fd(&e.listener);
        }
        let n = 1 + self.events.iter().flatten().count();
        wait_any_readable(&fds[..n], timeout_ns).context("link")?;
        Ok(())
    }

    /// Takes the pending wake-ups: whether something arrived from the other host, and
    /// which topics a role here published (only a role's notification reaches the
    /// gateway's listeners: the link's own are delivered past them).
    fn drain(&mut self, wake: &Listener<iceoryx2_link_backend::WakeService>) -> bool {
        let mut arrived = false;
        let _ = wake.try_wait(|_| arrived = true);
        for e in self.events.iter_mut().flatten() {
            let mut here = false;
            let _ = e.listener.try_wait(|_| here = true);
            e.published_here |= here;
        }
        arrived
    }

    /// Wakes the receivers of every topic that comes in from the other host (no role here
    /// has published it), past the link's own listeners so that nothing goes back.
    fn rewake_incoming(&self) {
        for e in self.events.iter().flatten().filter(|e| !e.published_here) {
            // The call iceoryx2-link's own event bridge delivers with (skip the node's
            // own listeners); a receiver that is gone is cleaned up by iceoryx2.
            let _ = e.notifier.__internal_notify(EventId::default(), true);
        }
    }

    /// Reports a failed cycle (the link stays usable): the first ten, then every 1000th.
    fn error(&mut self, what: &str, e: &dyn std::fmt::Display) {
        self.errors += 1;
        if self.errors <= 10 || self.errors % 1000 == 0 {
            eprintln!("{}: warning: {what} failed ({e}); {} so far", self.who, self.errors);
        }
        std::thread::sleep(Duration::from_micros(100));
    }
}

/// A stretch without a peer ([`ALONE_WARN_NS`]).
struct Alone {
    /// When the gateway started, or its last peer went.
    since: u64,
    /// Whether this stretch was reported.
    warned: bool,
    /// The endpoints the gateway connects to (none: it only listens).
    connect: Vec<String>,
    /// Peers must authenticate against a users dictionary here.
    refuses: bool,
}

impl Alone {
    /// What to say, once per stretch, when the gateway has had no peer for
    /// [`ALONE_WARN_NS`] at `now`. A connecting gateway tries each endpoint with a plain
    /// TCP connection (at most a second each) to tell "nobody there" from "refused".
    fn warning(&mut self, peers: usize, now: u64) -> Option<String> {
        if peers > 0 || self.warned || now < self.since + ALONE_WARN_NS {
            return None;
        }
        self.warned = true;
        let secs = ALONE_WARN_NS / 1_000_000_000;
        match (self.connect.is_empty(), self.refuses) {
            (true, true) => {
                return Some(format!(
                    "no peer for {secs} s. A peer whose credentials this gateway refuses \
                     (--users) is not reported by Zenoh, here or there: check the other \
                     gateway's --user and --password-file"
                ));
            }
            (true, false) => return Some(format!("no peer for {secs} s")),
            (false, _) => {}
        }
        let (open, closed): (Vec<&String>, Vec<&String>) =
            self.connect.iter().partition(|e| accepts_connections(e));
        let list = |v: &[&String]| v.iter().map(|s| s.as_str()).collect::<Vec<_>>().join(", ");
        Some(match open.is_empty() {
            true => format!(
                "no peer for {secs} s: nothing accepts connections at {}; still trying",
                list(&closed)
            ),
            false => format!(
                "no peer accepted our credentials: {} accepts connections, but no session came \
                 up in {secs} s. The gateway there refuses us (a wrong or missing --user or \
                 --password-file; Zenoh does not say which) or does not answer",
                list(&open)
            ),
        })
    }
}

/// Whether a TCP (or TLS) endpoint `proto/host:port` takes a plain TCP connection within a
/// second; false for any other kind.
fn accepts_connections(endpoint: &str) -> bool {
    use std::net::ToSocketAddrs;
    let bare = endpoint.split(['#', '?']).next().unwrap_or_default();
    let Some(("tcp" | "tls", address)) = bare.split_once('/') else { return false };
    let Ok(mut addrs) = address.to_socket_addrs() else { return false };
    addrs.any(|a| std::net::TcpStream::connect_timeout(&a, Duration::from_secs(1)).is_ok())
}

/// The gateway's own ports on one topic's event service.
struct TopicEvents {
    /// Hears the notifications of this host's roles.
    listener: Listener<ipc::Service>,
    /// Re-wakes this host's receivers after a pass that followed an arrival.
    notifier: Notifier<ipc::Service>,
    /// A role on this host has published the topic: it goes out, not in.
    published_here: bool,
}

/// The domain's services the link bridges now, by name and pattern.
fn bridged(
    link: &ZenohLink,
    config: &iceoryx2::config::Config,
    prefix: &str,
) -> BTreeSet<(String, &'static str)> {
    let mut out = BTreeSet::new();
    let _ = ipc::Service::list(config, |details| {
        let s = &details.static_details;
        let name = s.name().as_str();
        if name.starts_with(prefix) && link.bridges().contains(s.service_hash()) {
            use iceoryx2::service::static_config::messaging_pattern::MessagingPattern as P;
            let pattern = match s.messaging_pattern() {
                P::PublishSubscribe(_) => "publish-subscribe",
                P::Event(_) => "event",
                _ => "other",
            };
            out.insert((name.to_owned(), pattern));
        }
        CallbackProgression::Continue
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 42's "1903384357 µs at most": a discovery's figure is its wall time, which
    /// counts a process stopped (or blocked) in it. The exit line reads in a unit that
    /// fits and, when the longest was mostly off the CPU, says so rather than pass the
    /// wait off as the link's work.
    #[test]
    fn a_discovery_that_mostly_waited_is_told_from_work() {
        let mut d = Durations::default();
        assert_eq!(d.to_string(), "no discovery ran");
        for _ in 0..9 {
            d.add(150_000, 140_000);
        }
        d.add(4_200_000, 4_100_000);
        let work = d.to_string();
        assert!(
            work.starts_with("10 discoveries took 555 µs on average, 4200 µs at most"),
            "{work}"
        );
        assert!(!work.contains("waited"), "{work}");
        d.add(1_903_384_357_000, 2_000_000);
        let stopped = d.to_string();
        assert!(stopped.contains("1903.4 s at most"), "{stopped}");
        assert!(stopped.contains("the longest spent 2000 µs on the CPU and waited"), "{stopped}");
        assert_eq!(duration(25_000_000), "25 ms");
    }
}
