//! `rotorloop foxglove --domain D [ADDR]` (and `rotorloop run --foxglove [ADDR]`, which
//! starts it beside the loop): a live view of a running loop in Foxglove or Lichtblick,
//! over the Foxglove WebSocket protocol, served by the Foxglove SDK (subprotocol
//! `foxglove.sdk.v1`, and `foxglove.sdk.v1.1` where the viewer offers it).
//!
//! It subscribes to the loop's three services like the monitor, but never listens to
//! their events: it polls its subscribers every millisecond, so a publish wakes nobody more
//! than before, and its queues overflow (oldest dropped) rather than hold anything up. The
//! SDK's server drops the oldest messages for a viewer that does not keep up. A viewer that
//! connects late sees the loop from then on; a viewer gone is nothing to the loop, and
//! neither is this process killed (`kill -9`): its node is cleaned like any dead one.
//!
//! Topics: those of `run.mcap` ([`crate::export::mcap`]) that a live loop has, at the same
//! log times (the loop's `CLOCK_MONOTONIC` stamps): `/rotorloop/state`, `/rotorloop/torque`,
//! `/rotorloop/reference`, `/rotorloop/latency` (per tick, once its answer came or two
//! ticks later without it), `/rotorloop/tracking` (`err_deg`: the angle of `R_d Rᵀ`, and
//! the torque in force), `/rotorloop/log` (safe mode entered and left; a role gone, up or
//! restarted, seen five times a second) and `/tf`
//! (`world → body`, `world → reference`).
//!
//! Who may watch: the server has no authentication, so it listens on loopback only, where
//! every user of the machine may connect; another address is refused (exit 2) unless the
//! user says they mean it (`--allow-network`, `run --foxglove-allow-network`), as `rotorloop
//! link` refuses an unauthenticated endpoint beyond loopback. A port asked for by name that
//! another process holds is refused (exit 2), so that no viewer there takes that process
//! for this loop; the default port taken, `run` goes on without a live view and says so.

use std::collections::BTreeMap;
use std::net::{SocketAddr, ToSocketAddrs};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context as _;
use foxglove::messages::{FrameTransform, Log};
use foxglove::{Channel, ChannelBuilder, Context, WebSocketServer};
use rotorloop_common::clock::now_ns;
use rotorloop_common::graph::Topic;
use rotorloop_common::ipc::MAX_BUFFER;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::ipc::ports::Inbox;
use rotorloop_common::role::UsageError;
use rotorloop_common::signals::{install_signal_handlers, shutdown_requested};
use rotorloop_common::wire::{FLAG_SAFE_MODE, ReferenceSample, StateSample, TorqueSample};

use crate::export::mcap::{JsonChannel, latency, log_message, transform};

/// Where the server listens unless told otherwise: loopback only.
pub const DEFAULT_ADDR: &str = "127.0.0.1:8765";

/// The node name of the live server in its domain (`rotorloop/<domain>/foxglove`).
pub const NODE: &str = Domain::VIEWER_NODE;

/// `rotorloop foxglove` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct FoxgloveArgs {
    /// The loop's domain (`rotorloop ps` lists them).
    #[arg(long)]
    pub domain: String,
    /// The address to serve on (`HOST:PORT`; port 0: any free port). Loopback only (where
    /// any local user may watch); another address needs `--allow-network`. A port that is
    /// taken is an error (exit 2).
    #[arg(default_value = DEFAULT_ADDR)]
    pub addr: String,
    /// Serve on an address that is not loopback: anyone who can reach it watches the loop,
    /// with no authentication. Refused without this flag (exit 2).
    #[arg(long)]
    pub allow_network: bool,
    /// Write the address actually bound (`HOST:PORT`) to this file once serving.
    #[arg(long)]
    pub addr_file: Option<PathBuf>,
    /// Seconds to wait for the loop to appear before giving up, 0 to 86400 (a day, the
    /// longest run).
    #[arg(long, allow_hyphen_values = true, default_value_t = 30.0,
          value_parser = rotorloop_common::input::number_in(0.0, 86_400.0, "seconds"))]
    pub wait_s: f64,
}

/// Parses `HOST:PORT`, or says what is allowed.
pub fn parse_addr(addr: &str) -> Result<SocketAddr, UsageError> {
    addr.to_socket_addrs().ok().and_then(|mut a| a.next()).ok_or_else(|| {
        UsageError(format!(
            "--foxglove address `{addr}` is not allowed: HOST:PORT, e.g. {DEFAULT_ADDR}"
        ))
    })
}

/// Parses `addr` and applies the rule of who may watch: the server has no authentication,
/// so it serves on loopback only (where every local user may watch) unless `allowed`, the
/// user's `flag` saying they mean it (as `rotorloop link` refuses a non-loopback endpoint
/// without authentication).
pub fn check_reach(addr: &str, allowed: bool, flag: &str) -> Result<SocketAddr, UsageError> {
    let at = parse_addr(addr)?;
    if at.ip().is_loopback() || allowed {
        return Ok(at);
    }
    Err(UsageError(format!(
        "the Foxglove address `{addr}` is not on loopback: anyone who can reach {at} would watch \
         the loop, with no authentication; give {flag} if you mean it, or use \
         127.0.0.1:PORT (loopback: every user of this machine may watch there)"
    )))
}

/// What a taken `addr` means to the user: viewers there reach whatever holds it.
fn taken(addr: SocketAddr) -> String {
    format!(
        "the Foxglove address {addr} is taken by another process: viewers at ws://{addr} \
         would reach it, not this loop; name a free port (or port 0: any free one)"
    )
}

/// Whether `addr` can be listened on now (a listener opened and closed at once; port 0
/// always can): a taken port, or an address not of this machine, is a usage error naming
/// it, before anything starts.
fn can_listen(addr: SocketAddr) -> Result<(), UsageError> {
    match std::net::TcpListener::bind(addr) {
        Ok(_) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::AddrInUse => Err(UsageError(taken(addr))),
        Err(e) => Err(UsageError(format!("cannot serve the Foxglove WebSocket on {addr}: {e}"))),
    }
}

/// The live channels and what they need to remember between ticks.
struct Live {
    state: JsonChannel,
    torque: JsonChannel,
    reference: JsonChannel,
    latency: JsonChannel,
    tracking: JsonChannel,
    tf: Channel<FrameTransform>,
    log: Channel<Log>,
    /// Recent states by tick, waiting for their answer (at most a few ticks).
    pending: BTreeMap<u64, StateSample>,
    /// Recent references by tick (the reference leads the state).
    references: BTreeMap<u64, ReferenceSample>,
    safe: bool,
}

impl Live {
    fn new(ctx: &Arc<Context>) -> Self {
        Self {
            state: JsonChannel::new(ctx, "/rotorloop/state", "rotorloop.StateSample"),
            torque: JsonChannel::new(ctx, "/rotorloop/torque", "rotorloop.TorqueSample"),
            reference: JsonChannel::new(ctx, "/rotorloop/reference", "rotorloop.ReferenceSample"),
            latency: JsonChannel::new(ctx, "/rotorloop/latency", "rotorloop.Latency"),
            tracking: JsonChannel::new(ctx, "/rotorloop/tracking", "rotorloop.Tracking"),
            tf: ChannelBuilder::new("/tf").context(ctx).build(),
            log: ChannelBuilder::new("/rotorloop/log").context(ctx).build(),
            pending: BTreeMap::new(),
            references: BTreeMap::new(),
            safe: false,
        }
    }

    fn on_reference(&mut self, r: ReferenceSample) -> anyhow::Result<()> {
        self.reference.log(&serde_json::to_value(r)?, r.publish_ns)?;
        self.references.insert(r.tick, r);
        while self.references.len() > 256 {
            self.references.pop_first();
        }
        Ok(())
    }

    fn on_state(&mut self, s: StateSample) -> anyhow::Result<()> {
        let ns = s.publish_ns;
        self.state.log(&serde_json::to_value(s)?, ns)?;
        self.tf.log_with_time(&transform("world", "body", &s.r_row_major, ns), ns);
        let r = self.references.get(&s.tick).copied();
        if let Some(r) = r {
            self.tf.log_with_time(&transform("world", "reference", &r.r_d_row_major, ns), ns);
        }
        let err_deg = r.map(|r| attitude_error_deg(&s.r_row_major, &r.r_d_row_major));
        let u = s.applied_rotor_torque_nm;
        let row = serde_json::json!({
            "t": s.t_s, "err_deg": err_deg, "u1": u[0], "u2": u[1], "u3": u[2],
        });
        self.tracking.log(&row, ns)?;
        let safe = s.flags & FLAG_SAFE_MODE != 0;
        if safe != self.safe {
            use foxglove::messages::log::Level;
            let (level, what) = match safe {
                true => (Level::Warning, format!("safe mode entered at tick {}", s.tick)),
                false => (Level::Info, format!("control resumed at tick {}", s.tick)),
            };
            self.log.log_with_time(&log_message(ns, level, "plant", what), ns);
            self.safe = safe;
        }
        // A state two ticks old has had its chance to be answered.
        while let Some((&k, _)) = self.pending.first_key_value() {
            if k + 2 > s.tick {
                break;
            }
            if let Some(old) = self.pending.remove(&k) {
                self.latency_of(&old, None)?;
            }
        }
        self.pending.insert(s.tick, s);
        Ok(())
    }

    fn on_torque(&mut self, t: TorqueSample) -> anyhow::Result<()> {
        self.torque.log(&serde_json::to_value(t)?, t.publish_ns)?;
        if let Some(s) = self.pending.remove(&t.tick) {
            self.latency_of(&s, Some(&t))?;
        }
        Ok(())
    }

    /// A role came, went or restarted (seen at `ns`, this process's clock, the same
    /// `CLOCK_MONOTONIC` as the loop's stamps on one machine).
    fn log_event(&self, ns: u64, what: &str) {
        use foxglove::messages::log::Level;
        let level = if what.contains("gone") { Level::Error } else { Level::Info };
        let role = what.split_whitespace().next().unwrap_or_default();
        self.log.log_with_time(&log_message(ns, level, role, what.to_owned()), ns);
    }

    fn latency_of(&mut self, s: &StateSample, t: Option<&TorqueSample>) -> anyhow::Result<()> {
        let r = self.references.get(&s.tick);
        self.latency.log(&latency(s, t, r), s.publish_ns)
    }
}

/// The angle of `R_d Rᵀ` (deg).
fn attitude_error_deg(r: &[f64; 9], rd: &[f64; 9]) -> f64 {
    // trace(R_d Rᵀ) = Σ_ij R_d[ij] R[ij].
    let tr: f64 = r.iter().zip(rd).map(|(a, b)| a * b).sum();
    ((tr - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
}

/// The live roles of the loop in `domain` (link gateways and viewers' servers aside):
/// role → pid.
fn live_roles(domain: &Domain) -> BTreeMap<String, u32> {
    use iceoryx2::node::NodeView;
    use iceoryx2::prelude::*;
    let prefix = format!("rotorloop/{}/", domain.name());
    let mut roles = BTreeMap::new();
    let _ = Node::<ipc::Service>::list(domain.config(), |state| {
        if let NodeState::Alive(v) = &state {
            let name = v.details().as_ref().map(|d| d.name().as_str().to_owned());
            let role = name.as_deref().and_then(|n| n.strip_prefix(&prefix));
            if let Some(role) = role.filter(|r| *r != NODE && *r != "link") {
                roles.insert(role.to_owned(), (v.id().value() >> 64) as u32);
            }
        }
        CallbackProgression::Continue
    });
    roles
}

/// What changed between two looks at the roles, as log lines: a role gone, back, or
/// restarted (another pid).
fn role_events(before: &BTreeMap<String, u32>, now: &BTreeMap<String, u32>) -> Vec<String> {
    let mut said = Vec::new();
    for (role, pid) in before {
        match now.get(role) {
            None => said.push(format!("{role} (pid {pid}) gone")),
            Some(p) if p != pid => said.push(format!("{role} restarted (pid {pid} -> {p})")),
            Some(_) => {}
        }
    }
    for (role, pid) in now.iter().filter(|(r, _)| !before.contains_key(*r)) {
        said.push(format!("{role} (pid {pid}) up"));
    }
    said
}

/// The inbox of `topic` once its service exists (never creating it).
fn open_when_there<T>(
    domain: &Domain,
    node: &iceoryx2::node::Node<iceoryx2::prelude::ipc::Service>,
    topic: Topic,
    inbox: &mut Option<Inbox<T>>,
) -> anyhow::Result<()>
where
    T: iceoryx2::prelude::ZeroCopySend + std::fmt::Debug + Copy + 'static,
{
    if inbox.is_none() && domain.topic_exists(topic) {
        *inbox = Some(domain.inbox::<T>(node, topic, MAX_BUFFER, false)?);
    }
    Ok(())
}

/// Runs `rotorloop foxglove`: serves until the loop has ended (no role alive for a
/// second), or SIGINT/SIGTERM.
pub fn run(a: &FoxgloveArgs) -> anyhow::Result<()> {
    let addr = check_reach(&a.addr, a.allow_network, "--allow-network")?;
    let domain = Domain::new(&a.domain).map_err(|e| UsageError(e.to_string()))?;
    super::refuse_unreachable(&domain)?;
    install_signal_handlers();
    let ctx = Context::new();
    let server = WebSocketServer::new()
        .name(format!("rotorloop {}", a.domain))
        .bind(addr.ip().to_string(), addr.port())
        .context(&ctx)
        .start_blocking()
        .map_err(|e| match e {
            foxglove::FoxgloveError::Bind(e) if e.kind() == std::io::ErrorKind::AddrInUse => {
                anyhow::Error::from(UsageError(taken(addr)))
            }
            foxglove::FoxgloveError::Bind(e) => {
                UsageError(format!("cannot serve the Foxglove WebSocket on {addr}: {e}")).into()
            }
            e => anyhow::Error::from(e)
                .context(format!("cannot serve the Foxglove WebSocket on {addr}")),
        })?;
    let bound = SocketAddr::new(addr.ip(), server.port());
    if let Some(f) = &a.addr_file {
        // Renamed into place: whoever waits for the file never reads half of it.
        let mut part = f.clone().into_os_string();
        part.push(".part");
        std::fs::write(&part, format!("{bound}\n"))
            .and_then(|()| std::fs::rename(&part, f))
            .with_context(|| format!("cannot write {}", f.display()))?;
    }
    eprintln!("foxglove: domain {} on ws://{bound} (subprotocol foxglove.sdk.v1)", a.domain);
    let result = serve(a, &domain, &ctx);
    let _ = server.stop();
    result
}

fn serve(a: &FoxgloveArgs, domain: &Domain, ctx: &Arc<Context>) -> anyhow::Result<()> {
    let give_up = now_ns() + (a.wait_s * 1e9) as u64;
    while !domain.topic_exists(Topic::State) {
        if shutdown_requested() {
            return Ok(());
        }
        if now_ns() > give_up {
            anyhow::bail!("no loop appeared in domain `{}` within {} s", a.domain, a.wait_s);
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let node = domain.node(NODE)?;
    let (mut states, mut torques, mut references) = (None, None, None);
    let mut live = Live::new(ctx);
    let mut last_alive = now_ns();
    let mut seen_roles = BTreeMap::new();
    let mut next_check = 0;
    while !shutdown_requested() {
        open_when_there::<StateSample>(domain, &node, Topic::State, &mut states)?;
        open_when_there::<ReferenceSample>(domain, &node, Topic::Reference, &mut references)?;
        open_when_there::<TorqueSample>(domain, &node, Topic::Torque, &mut torques)?;
        // References first: the reference leads the state it belongs to.
        if let Some(i) = &references {
            let mut got = Vec::new();
            i.drain(|r| got.push(r))?;
            got.into_iter().try_for_each(|r| live.on_reference(r))?;
        }
        if let Some(i) = &states {
            let mut got = Vec::new();
            i.drain(|s| got.push(s))?;
            got.into_iter().try_for_each(|s| live.on_state(s))?;
        }
        if let Some(i) = &torques {
            let mut got = Vec::new();
            i.drain(|t| got.push(t))?;
            got.into_iter().try_for_each(|t| live.on_torque(t))?;
        }
        let now = now_ns();
        if now >= next_check {
            next_check = now + 200_000_000;
            let roles = live_roles(domain);
            for what in role_events(&seen_roles, &roles) {
                live.log_event(now, &what);
            }
            if !roles.is_empty() {
                last_alive = now;
            } else if now - last_alive > 1_000_000_000 {
                break;
            }
            seen_roles = roles;
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    Ok(())
}

/// `rotorloop run --foxglove`: the server beside the loop, stopped when the loop has ended.
#[derive(Debug)]
pub struct Beside {
    /// The server, or none: it could not listen on the default address (said at the start).
    child: Option<std::process::Child>,
    addr: String,
}

impl Beside {
    /// `--foxglove ADDR` checked before anything starts: the address, not with `--split`
    /// (each host has its own space), and a port asked for by name that is taken (a
    /// listener opened and closed at once; the default address is left to [`Beside::start`]).
    /// The rule of who may watch is [`check_reach`]'s, applied by the command line.
    pub fn check(addr: Option<&str>, split: bool) -> Result<(), UsageError> {
        let Some(addr) = addr else { return Ok(()) };
        let at = parse_addr(addr)?;
        if split {
            return Err(UsageError(
                "--foxglove is not allowed with --split (each host has its own space): \
                 run `rotorloop foxglove --domain D` beside a run without --split"
                    .into(),
            ));
        }
        if addr != DEFAULT_ADDR && at.port() != 0 {
            can_listen(at)?;
        }
        Ok(())
    }

    /// Starts `rotorloop foxglove --domain DOMAIN ADDR`, which writes the address it bound
    /// to `OUT/foxglove.addr`, and waits until it listens or has ended. One that could not
    /// listen on an address asked for by name stops the launch (exit 2, before any role
    /// starts); on the default address the loop goes on without it, saying that viewers
    /// there do not reach this run. An address beyond loopback was allowed by the command
    /// line (`--foxglove-allow-network`, [`check_reach`]), and the server is told so.
    pub fn start(
        exe: &std::path::Path,
        domain: &str,
        addr: &str,
        out: &std::path::Path,
    ) -> anyhow::Result<Self> {
        let at = parse_addr(addr)?;
        let file = out.join("foxglove.addr");
        // An earlier run's address in the same directory is not this server's.
        let _ = std::fs::remove_file(&file);
        let mut command = std::process::Command::new(exe);
        command.args(["foxglove", "--domain", domain, addr, "--addr-file"]).arg(&file);
        if !at.ip().is_loopback() {
            command.arg("--allow-network");
        }
        let mut child = command
            .stdin(std::process::Stdio::null())
            .spawn()
            .context("cannot start the Foxglove server (rotorloop foxglove)")?;
        let until = now_ns() + 10_000_000_000;
        loop {
            if file.exists() {
                break;
            }
            if let Ok(Some(status)) = child.try_wait() {
                if addr != DEFAULT_ADDR {
                    let why = format!(
                        "--foxglove {addr}: the Foxglove server could not listen there \
                         ({status}; its message is above); no role was started"
                    );
                    return Err(match status.code() {
                        Some(2) => UsageError(why).into(),
                        _ => anyhow::anyhow!(why),
                    });
                }
                eprintln!("warning: {}; the loop goes on without a live view", not_served(addr));
                return Ok(Self { child: None, addr: addr.to_owned() });
            }
            if now_ns() > until {
                eprintln!(
                    "warning: the Foxglove server is not listening on {addr} after 10 s; \
                     the loop starts without waiting for it"
                );
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        Ok(Self { child: Some(child), addr: addr.to_owned() })
    }

    /// Stops the server (SIGTERM; SIGKILL after 3 s). One that ended during the run (killed
    /// by hand) or never listened is said, and was no matter to the loop.
    pub fn stop(self) {
        let Some(mut child) = self.child else {
            eprintln!("warning: {}", not_served(&self.addr));
            return;
        };
        if let Ok(Some(status)) = child.try_wait() {
            eprintln!(
                "warning: the Foxglove server ended during the run ({status}); the loop went on"
            );
            return;
        }
        let pid = child.id() as libc::pid_t;
        // SAFETY: signals our own child, which has not been reaped (try_wait said so).
        unsafe { libc::kill(pid, libc::SIGTERM) };
        let until = now_ns() + 3_000_000_000;
        while now_ns() < until {
            if let Ok(Some(_)) = child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = child.kill();
        let _ = child.wait();
    }
}

/// Why viewers of the default address did not see this run.
fn not_served(addr: &str) -> String {
    format!(
        "the Foxglove server could not listen on {addr} (taken by another process? its message \
         is above): viewers at ws://{addr} do not reach this run, whatever answers there"
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The error angle of a rotation about z by 30° against the identity is 30°.
    #[test]
    fn the_error_is_the_angle_between_the_attitudes() {
        let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        let r = [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0];
        let i = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        assert!((attitude_error_deg(&r, &i) - 30.0).abs() < 1e-12);
        assert_eq!(attitude_error_deg(&i, &i), 0.0);
    }

    /// A role killed and restarted under another pid, one gone, one new: each said once.
    #[test]
    fn role_changes_are_said() {
        let m = |v: &[(&str, u32)]| v.iter().map(|(r, p)| ((*r).to_owned(), *p)).collect();
        let before = m(&[("controller", 10), ("monitor", 11), ("plant", 12)]);
        let now = m(&[("controller", 20), ("plant", 12), ("reference", 13)]);
        assert_eq!(
            role_events(&before, &now),
            [
                "controller restarted (pid 10 -> 20)",
                "monitor (pid 11) gone",
                "reference (pid 13) up"
            ]
        );
        assert!(role_events(&now, &now).is_empty());
    }

    /// Loopback is served as it is; any other address only with the user's word, and the
    /// refusal names the address and the flag that gives it.
    #[test]
    fn an_address_beyond_loopback_needs_the_users_word() {
        for a in ["127.0.0.1:0", "[::1]:8765", "127.3.2.1:1"] {
            assert!(check_reach(a, false, "--flag").is_ok(), "{a}");
        }
        let e = check_reach("0.0.0.0:8765", false, "--flag").expect_err("every interface");
        assert!(e.0.contains("`0.0.0.0:8765`") && e.0.contains("--flag"), "{e}");
        assert!(check_reach("0.0.0.0:8765", true, "--flag").is_ok());
    }

    /// A port another listener holds is refused, naming the address.
    #[test]
    fn a_taken_port_is_refused_naming_it() {
        let held = std::net::TcpListener::bind("127.0.0.1:0").expect("a free port");
        let at = held.local_addr().expect("bound");
        let e = can_listen(at).expect_err("taken");
        assert!(e.0.contains(&at.to_string()) && e.0.contains("taken"), "{e}");
    }

    /// An address that is not `HOST:PORT` is refused with the field and an example.
    #[test]
    fn a_bad_address_is_refused_with_what_is_allowed() {
        let e = parse_addr("localhost").expect_err("no port");
        assert!(e.0.contains("HOST:PORT") && e.0.contains("localhost"), "{e}");
        assert_eq!(parse_addr("127.0.0.1:0").ok().map(|a| a.port()), Some(0));
    }
}
