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
//! Topics: those of `run.mcap` ([`crate::export::mcap`]), with the same schemas
//! ([`crate::export::topics`]) and log times (the loop's `CLOCK_MONOTONIC` stamps), all
//! advertised from the start: `/rotorloop/state`, `/rotorloop/torque`,
//! `/rotorloop/reference`, `/rotorloop/latency` (per tick in tick order, once its answer
//! came or two ticks later without it), `/rotorloop/tracking` (`err_deg`: the angle of
//! `R_d Rᵀ`, the torque in force, `in_incident`; what only `trace.csv` knows is `null`),
//! `/rotorloop/incidents` (the windows this server sees abnormal, without cause or cost),
//! `/rotorloop/log` (safe mode entered and left; a role lost during the run a fault, an
//! error; up, restarted, or ended with the run, seen five times a second) and `/tf`
//! (`world → body`, `world → reference`). Viewers connect to [`super::front`], which relays
//! them to the SDK's server.
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
use foxglove::{Channel, ChannelBuilder, Context, RawChannel, Schema, WebSocketServer};
use rotorloop_common::clock::now_ns;
use rotorloop_common::graph::Topic;
use rotorloop_common::ipc::MAX_BUFFER;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::ipc::ports::Inbox;
use rotorloop_common::role::UsageError;
use rotorloop_common::signals::{install_signal_handlers, shutdown_requested};
use rotorloop_common::wire::{
    FLAG_LAST, FLAG_SAFE_MODE, ReferenceSample, StateSample, TorqueSample,
};

use crate::export::mcap::{latency, log_message, safe_mode_message, transform};
use crate::export::topics::{self, JsonTopic};

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

/// Parses `HOST:PORT` given as `option` (`--foxglove`, or `rotorloop foxglove`'s `ADDR`), or
/// says what is allowed.
pub fn parse_addr(addr: &str, option: &str) -> Result<SocketAddr, UsageError> {
    addr.to_socket_addrs().ok().and_then(|mut a| a.next()).ok_or_else(|| {
        UsageError(format!(
            "{option} address `{addr}` is not allowed: HOST:PORT, e.g. {DEFAULT_ADDR}"
        ))
    })
}

/// Parses `addr` (given as `option`) and applies the rule of who may watch: the server has
/// no authentication, so it serves on loopback only (where every local user may watch)
/// unless `allowed`, the user's `flag` saying they mean it (as `rotorloop link` refuses a
/// non-loopback endpoint without authentication).
pub fn check_reach(
    addr: &str,
    option: &str,
    allowed: bool,
    flag: &str,
) -> Result<SocketAddr, UsageError> {
    let at = parse_addr(addr, option)?;
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

/// A live JSON channel of [`topics`], declared (advertised to viewers) when made, with the
/// same schema as in `run.mcap`.
struct JsonChannel {
    channel: Arc<RawChannel>,
}

impl JsonChannel {
    fn new(ctx: &Arc<Context>, t: &JsonTopic) -> anyhow::Result<Self> {
        let channel = ChannelBuilder::new(t.topic)
            .context(ctx)
            .message_encoding("json")
            .schema(Schema::new(t.schema_name, "jsonschema", t.schema_bytes()))
            .build_raw()
            .with_context(|| format!("cannot make the channel {}", t.topic))?;
        Ok(Self { channel })
    }

    /// Logs `value` as JSON at `log_time` (serialized only when a viewer is subscribed).
    fn log(&self, value: &serde_json::Value, log_time: u64) -> anyhow::Result<()> {
        if self.channel.has_sinks() {
            let bytes = serde_json::to_vec(value)?;
            self.channel
                .log_with_meta(&bytes, foxglove::PartialMetadata { log_time: Some(log_time) });
        }
        Ok(())
    }
}

/// A state waiting for its answer, and the answer once it came.
type Pending = (StateSample, Option<TorqueSample>);

/// The live channels and what they need to remember between ticks.
struct Live {
    state: JsonChannel,
    torque: JsonChannel,
    reference: JsonChannel,
    latency: JsonChannel,
    tracking: JsonChannel,
    incidents: JsonChannel,
    tf: Channel<FrameTransform>,
    log: Channel<Log>,
    /// Recent states by tick, waiting for their answer (at most a few ticks): their latency
    /// is sent in tick order.
    pending: BTreeMap<u64, Pending>,
    /// Recent references by tick (the reference leads the state).
    references: BTreeMap<u64, ReferenceSample>,
    safe: bool,
    /// The run's last tick was seen: a role gone after it ended with the run.
    ended: bool,
    window: Window,
}

impl Live {
    fn new(ctx: &Arc<Context>) -> anyhow::Result<Self> {
        Ok(Self {
            state: JsonChannel::new(ctx, &topics::STATE)?,
            torque: JsonChannel::new(ctx, &topics::TORQUE)?,
            reference: JsonChannel::new(ctx, &topics::REFERENCE)?,
            latency: JsonChannel::new(ctx, &topics::LATENCY)?,
            tracking: JsonChannel::new(ctx, &topics::TRACKING)?,
            incidents: JsonChannel::new(ctx, &topics::INCIDENTS)?,
            tf: ChannelBuilder::new(topics::TF).context(ctx).build(),
            log: ChannelBuilder::new(topics::LOG).context(ctx).build(),
            pending: BTreeMap::new(),
            references: BTreeMap::new(),
            safe: false,
            ended: false,
            window: Window::default(),
        })
    }

    fn on_reference(&mut self, r: ReferenceSample) -> anyhow::Result<()> {
        self.reference.log(&topics::reference_json(&r), r.publish_ns)?;
        self.references.insert(r.tick, r);
        while self.references.len() > 256 {
            self.references.pop_first();
        }
        Ok(())
    }

    fn on_state(&mut self, s: StateSample) -> anyhow::Result<()> {
        let ns = s.publish_ns;
        self.state.log(&topics::state_json(&s), ns)?;
        self.tf.log_with_time(&transform("world", "body", &s.r_row_major, ns), ns);
        let r = self.references.get(&s.tick).copied();
        if let Some(r) = r {
            self.tf.log_with_time(&transform("world", "reference", &r.r_d_row_major, ns), ns);
        }
        let safe = s.flags & FLAG_SAFE_MODE != 0;
        let abnormal = self.window.abnormal(&s, safe);
        let err_deg = r.map(|r| attitude_error_deg(&s.r_row_major, &r.r_d_row_major));
        let u = s.applied_rotor_torque_nm;
        // What trace.csv has after the run and a live view cannot know is null.
        let row = serde_json::json!({
            "t": s.t_s, "tick": s.tick, "err_deg": err_deg, "werr": null, "h_drift_rel": null,
            "energy_residual": null, "delay_s": null, "u1": u[0], "u2": u[1], "u3": u[2],
            "in_incident": u8::from(abnormal),
        });
        self.tracking.log(&row, ns)?;
        if let Some(incident) = self.window.closed(&s, abnormal) {
            self.incidents.log(&incident.0, incident.1)?;
        }
        if safe != self.safe {
            let (level, what) = safe_mode_message(safe, s.tick);
            let plant = rotorloop_common::graph::Role::Plant.name();
            self.log.log_with_time(&log_message(ns, level, plant, what), ns);
            self.safe = safe;
        }
        self.ended |= s.flags & FLAG_LAST != 0;
        self.pending.insert(s.tick, (s, None));
        self.send_latency(s.tick)
    }

    fn on_torque(&mut self, t: TorqueSample) -> anyhow::Result<()> {
        self.torque.log(&topics::torque_json(&t), t.publish_ns)?;
        if let Some(p) = self.pending.get_mut(&t.tick) {
            p.1 = Some(t);
        }
        let newest = self.pending.last_key_value().map_or(0, |(k, _)| *k);
        self.send_latency(newest)
    }

    /// Sends the latency of the pending states in tick order: each once answered, or once
    /// two ticks old without an answer (`newest`: the newest state's tick). A tick waits
    /// for the one before it, so the topic's log times never go backwards.
    fn send_latency(&mut self, newest: u64) -> anyhow::Result<()> {
        while let Some(e) = self.pending.first_entry() {
            if e.get().1.is_none() && e.key() + 2 > newest {
                break;
            }
            let (s, t) = e.remove();
            let r = self.references.get(&s.tick);
            self.latency.log(&latency(&s, t.as_ref(), r), s.publish_ns)?;
        }
        Ok(())
    }

    /// A role came, went or restarted (seen at `ns`, this process's clock, the same
    /// `CLOCK_MONOTONIC` as the loop's stamps on one machine).
    fn log_event(&mut self, ns: u64, e: &RoleEvent) {
        let (level, text) = e.said(self.ended);
        if e.is_fault(self.ended) {
            self.window.fault = true;
        }
        self.log.log_with_time(&log_message(ns, level, &e.role, text), ns);
    }
}

/// The live view's incidents: windows of ticks it saw abnormal (a miss counted, safe mode,
/// a tick missing from the stream, a role gone), at most [`GAP`] normal ticks apart, sent
/// once closed. Their cause and cost are `rotorloop explain`'s, after the run (`null` here).
#[derive(Debug, Default)]
struct Window {
    /// The previous state (misses counted, tick).
    last: Option<(u64, u64)>,
    /// The open window: first state, last abnormal state, flags in words, misses.
    open: Option<(StateSample, StateSample, std::collections::BTreeSet<&'static str>, u64)>,
    /// A role was lost since the last state.
    fault: bool,
    /// What made the current tick abnormal.
    why: Vec<&'static str>,
}

/// Abnormal windows at most this many normal ticks apart are one incident (as after the
/// run: `pipeline::incidents::GAP`).
const GAP: u64 = 2;

impl Window {
    /// Whether state `s` is abnormal (and why, kept for [`Window::closed`]).
    fn abnormal(&mut self, s: &StateSample, safe: bool) -> bool {
        self.why.clear();
        if let Some((misses, tick)) = self.last {
            if s.misses > misses {
                self.why.push("miss");
            }
            if s.tick > tick + 1 {
                self.why.push("ticks not seen");
            }
        }
        if safe {
            self.why.push("safe mode");
        }
        if std::mem::take(&mut self.fault) {
            self.why.push("fault");
        }
        self.why.sort_unstable();
        !self.why.is_empty()
    }

    /// The incident that `s` closes (its message and log time), if any: more than [`GAP`]
    /// normal ticks after its last abnormal one, or the run's last tick.
    fn closed(&mut self, s: &StateSample, abnormal: bool) -> Option<(serde_json::Value, u64)> {
        let misses = s.misses.saturating_sub(self.last.map_or(s.misses, |l| l.0));
        self.last = Some((s.misses, s.tick));
        if abnormal {
            match &mut self.open {
                Some((_, end, flags, n)) => {
                    *end = *s;
                    flags.extend(self.why.iter().copied());
                    *n += misses;
                }
                None => self.open = Some((*s, *s, self.why.iter().copied().collect(), misses)),
            }
        }
        let end = self.open.as_ref()?.1.tick;
        if s.tick <= end + GAP && !is_last(s) {
            return None;
        }
        let (first, end, flags, misses) = self.open.take()?;
        // The loop's tick (s), from the state's own time.
        let dt = if s.tick > 0 { s.t_s / s.tick as f64 } else { 0.0 };
        let kind = ["fault", "safe mode", "miss", "ticks not seen"]
            .into_iter()
            .find(|k| flags.contains(k))
            .unwrap_or("miss");
        let words: Vec<&str> = flags.into_iter().collect();
        let message = serde_json::json!({
            "start_tick": first.tick,
            "end_tick": end.tick,
            "start_s": first.t_s,
            "duration_s": (end.tick + 1 - first.tick) as f64 * dt,
            "kind": kind,
            "cause_role": null,
            "cause_stage": null,
            "evidence": null,
            "flags": words.join(", "),
            "misses": misses,
            "peak_deviation_deg": null,
            "recovery_s": null,
            "analysed": false,
        });
        Some((message, first.publish_ns))
    }
}

fn is_last(s: &StateSample) -> bool {
    s.flags & FLAG_LAST != 0
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

/// A role seen gone, back, or restarted (another pid) between two looks at the roles.
#[derive(Debug, Clone, PartialEq, Eq)]
struct RoleEvent {
    role: String,
    /// The pid it had, if it was there.
    before: Option<u32>,
    /// The pid it has now, if it is there.
    now: Option<u32>,
}

impl RoleEvent {
    /// Whether it is a fault: a role lost before the run's last tick.
    fn is_fault(&self, ended: bool) -> bool {
        !ended && self.before.is_some() && self.before != self.now
    }

    /// Its log line: a role lost during the run is an error ("fault: …", as `run.mcap`
    /// says a fault), its restart and its start are information, and a role that ends
    /// after the run's last tick is the run's end, not an error.
    fn said(&self, ended: bool) -> (foxglove::messages::log::Level, String) {
        use foxglove::messages::log::Level;
        match (self.before, self.now) {
            (Some(a), Some(b)) if ended => (Level::Info, format!("restarted (pid {a} -> {b})")),
            (Some(a), Some(b)) => {
                (Level::Error, format!("fault: gone (pid {a}); restarted (pid {a} -> {b})"))
            }
            (Some(a), None) if ended => (Level::Info, format!("ended with the run (pid {a})")),
            (Some(a), None) => (Level::Error, format!("fault: gone (pid {a})")),
            (None, Some(b)) => (Level::Info, format!("up (pid {b})")),
            (None, None) => (Level::Info, String::new()),
        }
    }
}

/// What changed between two looks at the roles: a role gone, back, or restarted.
fn role_events(before: &BTreeMap<String, u32>, now: &BTreeMap<String, u32>) -> Vec<RoleEvent> {
    let mut said = Vec::new();
    for (role, pid) in before {
        if now.get(role) != Some(pid) {
            said.push(RoleEvent {
                role: role.clone(),
                before: Some(*pid),
                now: now.get(role).copied(),
            });
        }
    }
    for (role, pid) in now.iter().filter(|(r, _)| !before.contains_key(*r)) {
        said.push(RoleEvent { role: role.clone(), before: None, now: Some(*pid) });
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

/// Messages kept for a viewer that falls behind before the oldest are dropped: every
/// channel of a 1 kHz loop is eight messages a tick, 3.1 kB (measured by the live tests),
/// so about 2 s of it, about 6.5 MB a viewer (the SDK's default, 1024, was 0.13 s: a
/// busy machine's scheduling hiccup lost a viewer the log of a fault).
const BACKLOG: usize = 16_384;

/// Runs `rotorloop foxglove`: serves until the loop has ended (no role alive for a
/// second), or SIGINT/SIGTERM.
pub fn run(a: &FoxgloveArgs) -> anyhow::Result<()> {
    let addr = check_reach(&a.addr, "ADDR", a.allow_network, "--allow-network")?;
    let domain = Domain::new(&a.domain).map_err(|e| UsageError(e.to_string()))?;
    super::refuse_unreachable(&domain)?;
    install_signal_handlers();
    // The viewers' port is the front's (`super::front`: the WebSocket's close handshake and
    // close codes, both names of the protocol); the SDK's server is behind it on loopback.
    let listener = std::net::TcpListener::bind(addr).map_err(|e| match e.kind() {
        std::io::ErrorKind::AddrInUse => UsageError(taken(addr)),
        _ => UsageError(format!("cannot serve the Foxglove WebSocket on {addr}: {e}")),
    })?;
    let port = listener.local_addr()?.port();
    let ctx = Context::new();
    // Every channel exists before a viewer can connect: the SDK's server (0.30.3) sends a
    // connected viewer the advertisement of a channel made later before it records the
    // channel as advertised to it, and refuses a subscription that comes back in between
    // ("Unknown channel ID"); under load a viewer attached before the loop appeared once
    // got no states for the whole run. Channels there when a viewer connects are recorded
    // before its requests are read.
    let live = Live::new(&ctx)?;
    let server = WebSocketServer::new()
        .name(format!("rotorloop {}", a.domain))
        .message_backlog_size(BACKLOG)
        .bind("127.0.0.1", 0)
        .context(&ctx)
        .start_blocking()
        .with_context(|| format!("cannot start the Foxglove server for {addr}"))?;
    let sdk = SocketAddr::from(([127, 0, 0, 1], server.port()));
    let front = super::front::Front::start(listener, sdk)
        .with_context(|| format!("cannot serve the Foxglove WebSocket on {addr}"))?;
    let bound = SocketAddr::new(addr.ip(), port);
    if let Some(f) = &a.addr_file {
        // Renamed into place: whoever waits for the file never reads half of it.
        rotorloop_common::outdir::write_file(f, format!("{bound}\n"))
            .with_context(|| format!("cannot write {}", f.display()))?;
    }
    eprintln!(
        "foxglove: domain {} on ws://{bound} (subprotocols {})",
        a.domain,
        super::front::SUBPROTOCOLS.join(", ")
    );
    let result = serve(a, &domain, live);
    // The SDK's server closes its connections; the front says so to each viewer (1001).
    server.stop().wait_blocking();
    front.stop(Duration::from_secs(2));
    // Its node is gone: if it was the domain's last, what iceoryx2 keeps after the nodes
    // (the domain's folder, `global_mgmt`, the resume slots) goes too, as the launcher
    // removes it after the roles. A domain with a node alive is left as it is.
    let _ = domain.cleanup();
    result
}

fn serve(a: &FoxgloveArgs, domain: &Domain, mut live: Live) -> anyhow::Result<()> {
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
    let mut last_alive = now_ns();
    let mut seen_roles = BTreeMap::new();
    let mut next_check = 0;
    while !shutdown_requested() {
        open_when_there::<StateSample>(domain, &node, Topic::State, &mut states)?;
        open_when_there::<ReferenceSample>(domain, &node, Topic::Reference, &mut references)?;
        open_when_there::<TorqueSample>(domain, &node, Topic::Torque, &mut torques)?;
        // The roles are looked at before the samples are read: whatever a role published
        // before it went (the run's last tick among them) is read before its going is said.
        let now = now_ns();
        let roles = (now >= next_check).then(|| live_roles(domain));
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
        if let Some(roles) = roles {
            next_check = now + 200_000_000;
            for e in role_events(&seen_roles, &roles) {
                live.log_event(now, &e);
            }
            if !roles.is_empty() {
                last_alive = now;
            } else if now - last_alive > 1_000_000_000 {
                eprintln!("foxglove: the loop in domain `{}` has ended", a.domain);
                return Ok(());
            }
            seen_roles = roles;
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    eprintln!("foxglove: stopped by a signal");
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
        let at = parse_addr(addr, "--foxglove")?;
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
        let at = parse_addr(addr, "--foxglove")?;
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
    /// by hand) or never listened is said, and was no matter to the loop: the warning is
    /// returned, for `summary.json`'s `warnings`.
    pub fn stop(self) -> Option<String> {
        let Some(mut child) = self.child else {
            let w = not_served(&self.addr);
            eprintln!("warning: {w}");
            return Some(w);
        };
        if let Ok(Some(status)) = child.try_wait() {
            let w =
                format!("the Foxglove server ended during the run ({status}); the loop went on");
            eprintln!("warning: {w}");
            return Some(w);
        }
        let pid = child.id() as libc::pid_t;
        // SAFETY: signals our own child, which has not been reaped (try_wait said so).
        unsafe { libc::kill(pid, libc::SIGTERM) };
        let until = now_ns() + 3_000_000_000;
        while now_ns() < until {
            if let Ok(Some(_)) = child.try_wait() {
                return None;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = child.kill();
        let _ = child.wait();
        None
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

    /// A role killed and restarted under another pid, one gone, one new: each said once,
    /// a loss during the run as an error, and after the run's last tick as its end.
    #[test]
    fn role_changes_are_said() {
        let m = |v: &[(&str, u32)]| v.iter().map(|(r, p)| ((*r).to_owned(), *p)).collect();
        let before = m(&[("controller", 10), ("monitor", 11), ("plant", 12)]);
        let now = m(&[("controller", 20), ("plant", 12), ("reference", 13)]);
        let said = |ended| {
            role_events(&before, &now)
                .iter()
                .map(|e| (e.role.clone(), e.said(ended).0, e.said(ended).1))
                .collect::<Vec<_>>()
        };
        use foxglove::messages::log::Level;
        let s = |r: &str, l, t: &str| (r.to_owned(), l, t.to_owned());
        assert_eq!(
            said(false),
            [
                s("controller", Level::Error, "fault: gone (pid 10); restarted (pid 10 -> 20)"),
                s("monitor", Level::Error, "fault: gone (pid 11)"),
                s("reference", Level::Info, "up (pid 13)"),
            ]
        );
        // After the run's last tick a role that goes is the run's end, not an error.
        assert_eq!(said(true)[1], s("monitor", Level::Info, "ended with the run (pid 11)"));
        assert!(role_events(&now, &now).is_empty());
    }

    /// Loopback is served as it is; any other address only with the user's word, and the
    /// refusal names the address and the flag that gives it.
    #[test]
    fn an_address_beyond_loopback_needs_the_users_word() {
        for a in ["127.0.0.1:0", "[::1]:8765", "127.3.2.1:1"] {
            assert!(check_reach(a, "ADDR", false, "--flag").is_ok(), "{a}");
        }
        let e = check_reach("0.0.0.0:8765", "ADDR", false, "--flag").expect_err("every interface");
        assert!(e.0.contains("`0.0.0.0:8765`") && e.0.contains("--flag"), "{e}");
        assert!(check_reach("0.0.0.0:8765", "ADDR", true, "--flag").is_ok());
    }

    /// A port another listener holds is refused, naming the address.
    #[test]
    fn a_taken_port_is_refused_naming_it() {
        let held = std::net::TcpListener::bind("127.0.0.1:0").expect("a free port");
        let at = held.local_addr().expect("bound");
        let e = can_listen(at).expect_err("taken");
        assert!(e.0.contains(&at.to_string()) && e.0.contains("taken"), "{e}");
    }

    /// An address that is not `HOST:PORT` is refused with the option the user gave (the
    /// positional `ADDR` of `rotorloop foxglove`, never a flag they did not use) and an
    /// example.
    #[test]
    fn a_bad_address_is_refused_with_what_is_allowed() {
        let e = parse_addr("localhost", "ADDR").expect_err("no port");
        assert!(e.0.contains("HOST:PORT") && e.0.contains("localhost"), "{e}");
        assert!(e.0.starts_with("ADDR address") && !e.0.contains("--foxglove"), "{e}");
        assert_eq!(parse_addr("127.0.0.1:0", "ADDR").ok().map(|a| a.port()), Some(0));
    }
}
