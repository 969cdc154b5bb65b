//! Seeing a loop that runs, without touching it: `rotorloop ps` lists the domains on this
//! machine and their roles, `rotorloop watch` shows one loop live.
//!
//! Both are passive in the strongest sense: they create no iceoryx2 node and open no port
//! (so no subscriber on any service, and no publisher ever waits for or wakes them). What
//! they know comes from iceoryx2's node and service listings (names, pids, alive or dead,
//! which nodes are attached to which service) and from the roles' resume slots, which each
//! role rewrites every tick (the plant: its last state sample with its grid time, wake-up,
//! misses, safe mode, and the torques that took effect and when; the controller: its last
//! answer; the reference: its window of samples; the monitor: its rows). `watch` samples
//! the slots a few hundred times a second, so its per-second figures are of a sample of the
//! ticks (it says how many), not of every tick: the monitor's report is the full record.
//!
//! A run is its user's alone (owner-only files, docs/security.md). Another user's `watch`,
//! `ps --domain D` or `foxglove` of it is refused (exit 2) naming the domain, the file
//! refused and its owner's uid ([`unreachable()`]), rather than showing a loop of zeros; a
//! listing of every domain (`ps`) says which it cannot read.

pub mod charts;
pub mod foxglove;
pub mod front;
pub mod slots;
pub mod viewer;

use std::collections::{BTreeMap, VecDeque};
use std::fmt::Write as _;
use std::io::IsTerminal;
use std::time::Duration;

use hdrhistogram::Histogram;
use iceoryx2::prelude::*;
use rotorloop_common::clock::now_ns;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::signals::shutdown_requested;
use rotorloop_common::so3::rotation_angle;
use rotorloop_common::wire::{FLAG_LAST, FLAG_SAFE_MODE, StateSample, effect_delay_s};
use serde::Serialize;

use rotorloop_common::graph::Role;
use rotorloop_common::role::UsageError;
use slots::Slots;

/// `rotorloop ps` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct PsArgs {
    /// Only this domain (default: every domain on this machine).
    #[arg(long)]
    pub domain: Option<String>,
    /// JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    /// How long to watch the plant's tick to measure its rate (ms), 10 to 10000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 1000,
          value_parser = rotorloop_common::input::whole_in(10u64, 10_000, "ms"))]
    pub sample_ms: u64,
}

/// One role of a domain, as iceoryx2 and `/proc` see it.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct RoleView {
    /// `plant`, `reference`, `controller`, `monitor` (or another node's name).
    pub role: String,
    /// Its process.
    pub pid: u32,
    /// `alive`, or `dead` (not yet cleaned up), `inaccessible`, `undefined`.
    pub state: String,
    /// The core it last ran on.
    pub core: Option<u32>,
    /// The cores it may run on (its affinity).
    pub cores_allowed: Option<String>,
    /// `other`, `fifo`, `rr`, `batch`, `idle`, `deadline`.
    pub policy: Option<String>,
    /// Its real-time priority (0 for `other`).
    pub rt_priority: Option<u32>,
}

/// One service of a domain.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ServiceView {
    /// The service name (`rotorloop/<domain>/<topic>`).
    pub name: String,
    /// `publish_subscribe` or `event`.
    pub pattern: String,
    /// Nodes attached (their ports: publishers, subscribers, notifiers, listeners).
    pub nodes: Vec<String>,
}

/// A domain's roles, progress and services.
#[derive(Debug, Clone, Serialize)]
pub struct DomainView {
    /// The domain.
    pub domain: String,
    /// Its nodes.
    pub roles: Vec<RoleView>,
    /// Progress marks from the resume slots: the plant's newest tick, the controller's
    /// newest answer, the reference's next tick, the monitor's next row.
    pub ticks: BTreeMap<String, u64>,
    /// The plant's tick rate over the sampling time (Hz), if it ticked.
    pub rate_hz: Option<f64>,
    /// The plant has published its last tick.
    pub completed: bool,
    /// Its services.
    pub services: Vec<ServiceView>,
    /// Why the calling user cannot read this domain (another user's run), if it cannot:
    /// then nothing else of it is known. Only in a listing of every domain: `--domain D`
    /// of such a domain is an error.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unreachable: Option<String>,
}

/// The domains that have files on this machine (their iceoryx2 directory
/// `/dev/shm/.rl_<domain>_/` or `/dev/shm/rl_<domain>_…`).
pub fn domains_on_machine() -> Vec<String> {
    let mut found = std::collections::BTreeSet::new();
    let names = |dir: &str| -> Vec<String> {
        std::fs::read_dir(dir)
            .into_iter()
            .flatten()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect()
    };
    for n in names("/dev/shm") {
        // Domain names have no `_`, so the first `_` after `rl_` ends the name.
        if let Some(d) = n
            .strip_prefix('.')
            .unwrap_or(&n)
            .strip_prefix("rl_")
            .and_then(|r| r.split_once('_'))
            .map(|(d, _)| d)
        {
            if Domain::new(d).is_ok() {
                found.insert(d.to_owned());
            }
        }
    }
    found.into_iter().collect()
}

/// Why the calling user cannot read `domain`, if it cannot: its files are another user's,
/// owner-only. Looked at directly (the domain's directory, then its shared-memory files,
/// each listed or opened read-only and closed), because iceoryx2 and the resume slots take
/// a refused file for one that is not there, and an observer would show a loop of zeros.
/// `None` also where the domain has no files yet.
pub fn unreachable(domain: &Domain) -> Option<String> {
    use std::os::unix::fs::MetadataExt;
    let shm = std::fs::read_dir("/dev/shm").into_iter().flatten().flatten().map(|e| e.path());
    let prefix = domain.prefix();
    let files =
        shm.filter(|p| p.file_name().is_some_and(|n| n.to_string_lossy().starts_with(prefix)));
    for path in std::iter::once(domain.root_dir()).chain(files) {
        let tried = match path.is_dir() {
            true => std::fs::read_dir(&path).map(drop),
            false => std::fs::File::open(&path).map(drop),
        };
        let Err(e) = tried else { continue };
        if e.kind() != std::io::ErrorKind::PermissionDenied {
            continue; // gone since it was listed, or not there at all
        }
        let owner =
            std::fs::metadata(&path).map_or("another user".into(), |m| format!("uid {}", m.uid()));
        // SAFETY: plain getter.
        let me = unsafe { libc::geteuid() };
        return Some(format!(
            "domain `{}` is not readable by uid {me}: {} is owned by {owner}, open to its \
             owner only (permission denied); a run belongs to the user who started it \
             (docs/security.md): watch it as that user",
            domain.name(),
            path.display()
        ));
    }
    None
}

/// [`unreachable()`] as a usage error (exit 2): an observer never shows a loop it cannot read.
pub fn refuse_unreachable(domain: &Domain) -> Result<(), UsageError> {
    unreachable(domain).map_or(Ok(()), |why| Err(UsageError(why)))
}

/// `/proc/<pid>/stat`: the core it last ran on, its real-time priority and policy.
fn proc_sched(pid: u32) -> (Option<u32>, Option<u32>, Option<String>, Option<String>) {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    // Fields after the parenthesised command name: state is field 3, so index = field − 3.
    let f: Vec<&str> = stat.rsplit_once(')').map_or("", |(_, r)| r).split_whitespace().collect();
    let field = |n: usize| f.get(n - 3).and_then(|v| v.parse::<u32>().ok());
    let policy = field(41).map(|p| {
        match p {
            0 => "other",
            1 => "fifo",
            2 => "rr",
            3 => "batch",
            5 => "idle",
            6 => "deadline",
            _ => "?",
        }
        .to_owned()
    });
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let allowed = status
        .lines()
        .find_map(|l| l.strip_prefix("Cpus_allowed_list:"))
        .map(|v| v.trim().to_owned());
    (field(39), field(40), policy, allowed)
}

/// The nodes of `domain`.
fn roles(domain: &Domain) -> Result<Vec<RoleView>, UsageError> {
    use iceoryx2::node::NodeView;
    let ours = format!("rotorloop/{}/", domain.name());
    let mut out = Vec::new();
    Node::<ipc::Service>::list(domain.config(), |state| {
        let (view_state, id, details) = match &state {
            NodeState::Alive(v) => ("alive", v.id().value(), v.details().clone()),
            NodeState::Dead(v) => ("dead", v.id().value(), v.details().clone()),
            NodeState::Inaccessible(id) => ("inaccessible", id.value(), None),
            NodeState::Undefined(id) => ("undefined", id.value(), None),
        };
        let name = details.map(|d| d.name().as_str().to_owned()).unwrap_or_default();
        let role = match name.strip_prefix(&ours).unwrap_or(&name) {
            "" => "(unnamed: being created or cleaned up)".to_owned(),
            r => r.to_owned(),
        };
        let pid = (id >> 64) as u32;
        let (core, rt_priority, policy, cores_allowed) =
            if view_state == "alive" { proc_sched(pid) } else { (None, None, None, None) };
        out.push(RoleView {
            role,
            pid,
            state: view_state.into(),
            core,
            cores_allowed,
            policy,
            rt_priority,
        });
        CallbackProgression::Continue
    })
    .map_err(|e| {
        UsageError(format!("cannot list the nodes of domain `{}`: {e:?}", domain.name()))
    })?;
    out.sort_by_key(|r| (Role::ALL.iter().position(|x| x.name() == r.role).unwrap_or(9), r.pid));
    Ok(out)
}

/// The services of `domain` and the nodes attached to each.
fn services(domain: &Domain) -> Vec<ServiceView> {
    let mut ids: BTreeMap<u128, String> = BTreeMap::new();
    let _ = Node::<ipc::Service>::list(domain.config(), |state| {
        use iceoryx2::node::NodeView;
        let (id, details) = match &state {
            NodeState::Alive(v) => (v.id().value(), v.details().clone()),
            NodeState::Dead(v) => (v.id().value(), v.details().clone()),
            NodeState::Inaccessible(id) | NodeState::Undefined(id) => (id.value(), None),
        };
        let name = details.map(|d| d.name().as_str().to_owned()).unwrap_or_default();
        let dead = if matches!(state, NodeState::Alive(_)) { "" } else { " (dead)" };
        ids.insert(id, format!("{}{dead}", name.rsplit('/').next().unwrap_or("")));
        CallbackProgression::Continue
    });
    let mut out = Vec::new();
    let _ = ipc::Service::list(domain.config(), |s| {
        use iceoryx2::service::static_config::messaging_pattern::MessagingPattern as Static;
        let pattern = match s.static_details.messaging_pattern() {
            Static::PublishSubscribe(_) => "publish_subscribe",
            Static::Event(_) => "event",
            _ => "other",
        };
        let nodes = s
            .dynamic_details
            .as_ref()
            .map(|d| {
                d.nodes
                    .iter()
                    .map(|n| {
                        use iceoryx2::node::NodeView;
                        let id = match n {
                            NodeState::Alive(v) => v.id().value(),
                            NodeState::Dead(v) => v.id().value(),
                            NodeState::Inaccessible(id) | NodeState::Undefined(id) => id.value(),
                        };
                        ids.get(&id).cloned().unwrap_or_else(|| format!("{:x}", id))
                    })
                    .collect()
            })
            .unwrap_or_default();
        out.push(ServiceView {
            name: s.static_details.name().as_str().to_owned(),
            pattern: pattern.into(),
            nodes,
        });
        CallbackProgression::Continue
    });
    out.sort_by(|a, b| (&a.name, &a.pattern).cmp(&(&b.name, &b.pattern)));
    out
}

/// A snapshot of `domain`, its plant's rate measured over `sample_ms`; a domain the caller
/// cannot read is refused, saying why.
pub fn snapshot(name: &str, sample_ms: u64) -> Result<DomainView, UsageError> {
    let domain = Domain::new(name).map_err(|e| UsageError(e.to_string()))?;
    refuse_unreachable(&domain)?;
    let slots = Slots::observe(&domain);
    let first = slots.plant().map(|s| (s.tick, now_ns()));
    std::thread::sleep(Duration::from_millis(sample_ms));
    let last = slots.plant();
    let rate_hz = match (first, last) {
        (Some((k0, t0)), Some(s)) if s.tick > k0 => {
            Some((s.tick - k0) as f64 / ((now_ns() - t0) as f64 / 1e9))
        }
        _ => None,
    };
    Ok(DomainView {
        domain: name.to_owned(),
        roles: roles(&domain)?,
        ticks: slots.ticks(),
        rate_hz,
        completed: last.is_some_and(|s| s.flags & FLAG_LAST != 0),
        services: services(&domain),
        unreachable: None,
    })
}

/// One domain of a listing: its snapshot, or, where the caller cannot read it, only why.
fn listed(name: &str, sample_ms: u64) -> Result<DomainView, UsageError> {
    let domain = Domain::new(name).map_err(|e| UsageError(e.to_string()))?;
    let Some(why) = unreachable(&domain) else { return snapshot(name, sample_ms) };
    Ok(DomainView {
        domain: name.to_owned(),
        roles: Vec::new(),
        ticks: BTreeMap::new(),
        rate_hz: None,
        completed: false,
        services: Vec::new(),
        unreachable: Some(why),
    })
}

/// Writes `text` to stdout; a reader that went away (`| head`) is not an error.
fn out(text: &str) -> anyhow::Result<()> {
    use std::io::Write;
    match std::io::stdout().lock().write_all(text.as_bytes()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        r => Ok(r?),
    }
}

/// `rotorloop ps`.
pub fn ps(a: &PsArgs) -> anyhow::Result<()> {
    // One domain asked for by name must be readable; a listing of all says which are not.
    let views = match &a.domain {
        Some(d) => vec![snapshot(d, a.sample_ms)?],
        None => domains_on_machine()
            .iter()
            .map(|d| listed(d, a.sample_ms))
            .collect::<Result<Vec<_>, _>>()?,
    };
    if a.json {
        return out(&(serde_json::to_string_pretty(&views)? + "\n"));
    }
    let mut t = String::new();
    if views.is_empty() {
        t.push_str("no rotorloop domain on this machine\n");
    }
    for v in &views {
        if let Some(why) = &v.unreachable {
            let _ = writeln!(t, "domain {}: not shown: {why}", v.domain);
            continue;
        }
        let rate = v.rate_hz.map_or("not ticking".to_owned(), |r| format!("{r:.1} Hz"));
        let done = if v.completed { ", completed" } else { "" };
        let tick = v.ticks.get(Role::Plant.name()).map_or("-".into(), |t| t.to_string());
        let _ = writeln!(t, "domain {}: plant at tick {tick}, {rate}{done}", v.domain);
        let _ = writeln!(
            t,
            "  {:<11} {:>8} {:<12} {:>4} {:<8} {:<6} {:>5} {:>10}",
            "ROLE", "PID", "STATE", "CORE", "ALLOWED", "POLICY", "PRIO", "TICK"
        );
        for r in &v.roles {
            let opt = |x: Option<u32>| x.map_or("-".into(), |v| v.to_string());
            let _ = writeln!(
                t,
                "  {:<11} {:>8} {:<12} {:>4} {:<8} {:<6} {:>5} {:>10}",
                r.role,
                r.pid,
                r.state,
                opt(r.core),
                r.cores_allowed.as_deref().unwrap_or("-"),
                r.policy.as_deref().unwrap_or("-"),
                opt(r.rt_priority),
                v.ticks.get(&r.role).map_or("-".into(), |t| t.to_string())
            );
        }
        for s in v.services.iter().filter(|s| s.pattern == "publish_subscribe") {
            let _ = writeln!(t, "  service {:<32} nodes attached: {}", s.name, s.nodes.join(", "));
        }
    }
    out(&t)
}

/// `rotorloop watch` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct WatchArgs {
    /// The domain to watch.
    #[arg(long)]
    pub domain: String,
    /// Print one JSON snapshot after `--seconds` of watching and exit (for scripts and tests).
    #[arg(long)]
    pub once: bool,
    /// With `--once`: JSON (the default for `--once`).
    #[arg(long)]
    pub json: bool,
    /// How long to watch before the snapshot of `--once` (s), 0 to 86400 (a day, the
    /// longest run).
    #[arg(long, allow_hyphen_values = true, default_value_t = 2.0,
          value_parser = rotorloop_common::input::number_in(0.0, 86_400.0, "seconds"))]
    pub seconds: f64,
    /// Slot samples per second, 1 to 2000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 250,
          value_parser = rotorloop_common::input::whole_in(1u64, 2000, "samples a second"))]
    pub sample_hz: u64,
}

/// p50, p99 and max of a set of values (µs), and how many.
#[derive(Debug, Clone, Copy, Serialize, Default, PartialEq)]
pub struct Spread {
    /// Values.
    pub count: usize,
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Largest.
    pub max: f64,
}

impl Spread {
    fn of(values: impl Iterator<Item = f64>) -> Self {
        let mut v: Vec<f64> = values.filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return Self::default();
        }
        v.sort_by(f64::total_cmp);
        let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        Self { count: v.len(), p50: q(0.5), p99: q(0.99), max: v[v.len() - 1] }
    }
}

/// The spread of every value since watching began, in memory that does not grow with the
/// watch: an HdrHistogram of nanoseconds (3 significant digits, 1 ns to an hour; a longer
/// value counts as an hour), its largest value exact. A day of watching at 2000 samples a
/// second is 173 M values; a list of them would be 1.4 GB, and sorting it four times a
/// second would stall the screen long before.
struct SinceStart {
    ns: Histogram<u64>,
    max_us: f64,
}

impl SinceStart {
    const MAX_NS: u64 = 3_600_000_000_000;

    fn new() -> Self {
        let ns = Histogram::new_with_bounds(1, Self::MAX_NS, 3).expect("1 ns to an hour, 3 digits");
        Self { ns, max_us: f64::NEG_INFINITY }
    }

    /// One value (µs); NaN (no value this tick) is not counted, as in [`Spread::of`].
    fn record(&mut self, us: f64) {
        if !us.is_finite() {
            return;
        }
        self.max_us = self.max_us.max(us);
        // Below 0 (`as` saturates) counts as 0, above an hour as an hour.
        self.ns.saturating_record((us * 1e3).round() as u64);
    }

    fn spread(&self) -> Spread {
        if self.ns.is_empty() {
            return Spread::default();
        }
        // A bucket's highest value can lie above the largest value recorded in it.
        let q = |p: f64| (self.ns.value_at_quantile(p) as f64 / 1e3).min(self.max_us);
        Spread { count: self.ns.len() as usize, p50: q(0.5), p99: q(0.99), max: self.max_us }
    }
}

/// The events `watch` shows (the newest); older ones are let go.
const EVENTS_SHOWN: usize = 12;

/// One sampled tick.
#[derive(Debug, Clone, Copy)]
struct Seen {
    at_ns: u64,
    tick: u64,
    lateness_us: f64,
    delay_us: f64,
    err_deg: f64,
}

/// What `watch` shows.
#[derive(Debug, Clone, Default, Serialize)]
pub struct WatchView {
    /// The domain.
    pub domain: String,
    /// Simulated time of the newest state (s).
    pub t_s: f64,
    /// The plant's newest tick.
    pub tick: u64,
    /// Ticks per second over the last second.
    pub rate_hz: f64,
    /// Tick lateness (wake-up − grid time), last second (µs), of the sampled ticks.
    pub tick_lateness_1s: Spread,
    /// The same since watching began.
    pub tick_lateness_all: Spread,
    /// Actuation delay of the torques that took effect (µs): the loop's sense-to-actuate
    /// seen by the plant, last second, of the sampled ticks.
    pub actuation_delay_1s: Spread,
    /// The same since watching began.
    pub actuation_delay_all: Spread,
    /// Deadline misses: total, and in the last second.
    pub misses: u64,
    /// Misses in the last second.
    pub misses_1s: u64,
    /// Ticks in safe mode, total.
    pub safe_mode_ticks: u64,
    /// The plant is in safe mode now.
    pub safe_mode: bool,
    /// Attitude error now (deg), if the reference sample of the tick is in its window.
    pub err_deg: Option<f64>,
    /// Attitude error one second ago (deg): the trend.
    pub err_deg_1s_ago: Option<f64>,
    /// Roles and their state.
    pub roles: Vec<RoleView>,
    /// What happened while watching (a role died or restarted, safe mode, control back).
    pub events: Vec<String>,
    /// The charts' points: one a second of watching, the last minute.
    pub history: Vec<charts::Point>,
}

/// The watcher's state between refreshes.
struct Watcher {
    domain: Domain,
    slots: Slots,
    seen: VecDeque<Seen>,
    all_lateness: SinceStart,
    all_delay: SinceStart,
    last_tick: Option<u64>,
    misses_at: VecDeque<(u64, u64, u64)>,
    pids: BTreeMap<String, (u32, String)>,
    safe: bool,
    events: VecDeque<String>,
    started_ns: u64,
    dt: f64,
    history: charts::History,
}

impl Watcher {
    fn new(name: &str) -> Result<Self, UsageError> {
        let domain = Domain::new(name).map_err(|e| UsageError(e.to_string()))?;
        refuse_unreachable(&domain)?;
        let slots = Slots::observe(&domain);
        Ok(Self {
            domain,
            slots,
            seen: VecDeque::new(),
            all_lateness: SinceStart::new(),
            all_delay: SinceStart::new(),
            last_tick: None,
            misses_at: VecDeque::new(),
            pids: BTreeMap::new(),
            safe: false,
            events: VecDeque::new(),
            started_ns: now_ns(),
            dt: 1e-3,
            history: Default::default(),
        })
    }

    fn event(&mut self, what: String) {
        let at = (now_ns() - self.started_ns) as f64 / 1e9;
        if self.events.len() == EVENTS_SHOWN {
            self.events.pop_front();
        }
        self.events.push_back(format!("{at:7.2} s  {what}"));
    }

    /// One look at the plant's slot (and the reference's, for the error).
    fn sample(&mut self) {
        self.slots.reopen_missing(&self.domain);
        let Some(s) = self.slots.plant() else { return };
        if self.last_tick == Some(s.tick) {
            return;
        }
        if s.tick > 0 {
            self.dt = s.t_s / s.tick as f64;
        }
        self.last_tick = Some(s.tick);
        let lateness_us = if s.deadline_ns > 0 {
            s.wake_ns.saturating_sub(s.deadline_ns) as f64 / 1e3
        } else {
            f64::NAN
        };
        let delay_us = match s.effects {
            0 => f64::NAN,
            _ => {
                effect_delay_s(
                    s.tick.saturating_sub(1),
                    s.effect_ticks[0],
                    s.effect_offsets_s[0],
                    self.dt,
                ) * 1e6
            }
        };
        let err_deg = self.error(&s);
        self.seen.push_back(Seen { at_ns: now_ns(), tick: s.tick, lateness_us, delay_us, err_deg });
        self.all_lateness.record(lateness_us);
        self.all_delay.record(delay_us);
        self.misses_at.push_back((now_ns(), s.misses, s.safe_mode_ticks));
        let safe = s.flags & FLAG_SAFE_MODE != 0;
        if safe != self.safe {
            self.safe = safe;
            self.event(if safe {
                format!("plant in safe mode at tick {}", s.tick)
            } else {
                format!("control resumed at tick {}", s.tick)
            });
        }
        let horizon = now_ns().saturating_sub(2_000_000_000);
        while self.seen.front().is_some_and(|x| x.at_ns < horizon) {
            self.seen.pop_front();
        }
        while self.misses_at.front().is_some_and(|x| x.0 < horizon) {
            self.misses_at.pop_front();
        }
    }

    fn error(&self, s: &StateSample) -> f64 {
        let r = self.slots.reference.as_ref().and_then(ResumeSlot::load);
        let Some(rd) = r.and_then(|w| w.sample(s.tick)) else { return f64::NAN };
        rotation_angle(&(rd.reference_state().r_d * s.body_state().r.transpose())).to_degrees()
    }

    /// Roles: note deaths and restarts (a new pid for a role).
    fn roles(&mut self) -> Vec<RoleView> {
        let roles: Vec<RoleView> = roles(&self.domain)
            .unwrap_or_default()
            .into_iter()
            .filter(|r| !r.role.starts_with('('))
            .collect();
        for r in &roles {
            match self.pids.get(&r.role) {
                Some((pid, _)) if *pid != r.pid && r.state == "alive" => {
                    let what = format!("{} restarted (pid {} → {})", r.role, pid, r.pid);
                    self.event(what);
                }
                Some((pid, st)) if *pid == r.pid && st != &r.state => {
                    let what = format!("{} {} (pid {})", r.role, r.state, r.pid);
                    self.event(what);
                }
                None if !self.pids.is_empty() => {
                    self.event(format!("{} started (pid {})", r.role, r.pid))
                }
                _ => {}
            }
        }
        for (role, (pid, _)) in self.pids.clone() {
            if !roles.iter().any(|r| r.role == role) {
                self.event(format!("{role} gone (pid {pid})"));
            }
        }
        self.pids = roles.iter().map(|r| (r.role.clone(), (r.pid, r.state.clone()))).collect();
        roles
    }

    fn view(&mut self) -> WatchView {
        let roles = self.roles();
        let now = now_ns();
        let last_s: Vec<&Seen> =
            self.seen.iter().filter(|x| x.at_ns + 1_000_000_000 >= now).collect();
        let ago = self.seen.iter().find(|x| x.at_ns + 1_000_000_000 >= now).map(|x| x.err_deg);
        let s = self.slots.plant();
        let first_1s = self.misses_at.iter().find(|x| x.0 + 1_000_000_000 >= now).copied();
        let rate_hz = match (last_s.first(), last_s.last()) {
            (Some(a), Some(b)) if b.at_ns > a.at_ns => {
                (b.tick - a.tick) as f64 / ((b.at_ns - a.at_ns) as f64 / 1e9)
            }
            _ => 0.0,
        };
        let v = WatchView {
            domain: self.domain.name().to_owned(),
            t_s: s.map_or(0.0, |s| s.t_s),
            tick: s.map_or(0, |s| s.tick),
            rate_hz,
            tick_lateness_1s: Spread::of(last_s.iter().map(|x| x.lateness_us)),
            tick_lateness_all: self.all_lateness.spread(),
            actuation_delay_1s: Spread::of(last_s.iter().map(|x| x.delay_us)),
            actuation_delay_all: self.all_delay.spread(),
            misses: s.map_or(0, |s| s.misses),
            misses_1s: match (first_1s, s) {
                (Some(f), Some(s)) => s.misses.saturating_sub(f.1),
                _ => 0,
            },
            safe_mode_ticks: s.map_or(0, |s| s.safe_mode_ticks),
            safe_mode: self.safe,
            err_deg: last_s.last().map(|x| x.err_deg).filter(|e| e.is_finite()),
            err_deg_1s_ago: ago.filter(|e| e.is_finite()),
            roles,
            events: self.events.iter().cloned().collect(),
            history: Vec::new(),
        };
        self.history.push_if_due(now, &v);
        WatchView { history: self.history.points(), ..v }
    }
}

/// Samples for `seconds` (or until a signal), at `hz`.
fn sample_for(w: &mut Watcher, seconds: f64, hz: u64) {
    let until = now_ns() + (seconds * 1e9) as u64;
    while now_ns() < until && !shutdown_requested() {
        w.sample();
        std::thread::sleep(Duration::from_nanos(1_000_000_000 / hz));
    }
}

fn spread_line(name: &str, one: &Spread, all: &Spread) -> String {
    format!(
        "{name:<18} last 1 s: p50 {:>8.1}  p99 {:>8.1}  max {:>8.1} µs ({:>3} seen)   since start: p50 {:>8.1}  p99 {:>8.1}  max {:>8.1} µs",
        one.p50, one.p99, one.max, one.count, all.p50, all.p99, all.max
    )
}

/// The view as text lines (the screen, or plain lines when stdout is not a terminal).
pub fn render(v: &WatchView) -> Vec<String> {
    let trend = match (v.err_deg, v.err_deg_1s_ago) {
        (Some(e), Some(a)) if e < a => "falling",
        (Some(e), Some(a)) if e > a => "rising",
        (Some(_), Some(_)) => "steady",
        _ => "",
    };
    let mut l = vec![
        format!(
            "domain {}   t = {:.3} s   tick {}   {:.1} Hz   {}",
            v.domain,
            v.t_s,
            v.tick,
            v.rate_hz,
            if v.safe_mode { "SAFE MODE" } else { "controlling" }
        ),
        spread_line("tick lateness", &v.tick_lateness_1s, &v.tick_lateness_all),
        spread_line("actuation delay", &v.actuation_delay_1s, &v.actuation_delay_all),
        format!(
            "misses {} ({} in the last second)   safe-mode ticks {}   attitude error {} ({trend})",
            v.misses,
            v.misses_1s,
            v.safe_mode_ticks,
            v.err_deg.map_or("-".to_owned(), |e| format!("{e:.4}°"))
        ),
        String::new(),
    ];
    for r in &v.roles {
        l.push(format!(
            "  {:<11} pid {:>8}  {:<12} core {:>2}  {}",
            r.role,
            r.pid,
            r.state,
            r.core.map_or("-".into(), |c| c.to_string()),
            r.policy.as_deref().unwrap_or("")
        ));
    }
    l.push(String::new());
    l.push("events:".into());
    l.extend(v.events.iter().map(|e| format!("  {e}")));
    l
}

/// `rotorloop watch`.
pub fn watch(a: &WatchArgs) -> anyhow::Result<()> {
    rotorloop_common::signals::install_signal_handlers();
    let mut w = Watcher::new(&a.domain)?;
    w.roles();
    if a.once {
        sample_for(&mut w, a.seconds, a.sample_hz);
        // A loop that appeared while watching may be another user's.
        refuse_unreachable(&w.domain)?;
        return out(&(serde_json::to_string_pretty(&w.view())? + "\n"));
    }
    if !std::io::stdout().is_terminal() {
        // Plain lines, one block a second, for a pipe or a log.
        while !shutdown_requested() {
            sample_for(&mut w, 1.0, a.sample_hz);
            out(&(render(&w.view()).join("\n") + "\n\n"))?;
        }
        return Ok(());
    }
    let mut terminal = ratatui::init();
    let result = (|| -> anyhow::Result<()> {
        while !shutdown_requested() {
            sample_for(&mut w, 0.25, a.sample_hz);
            let lines = render(&w.view());
            terminal.draw(|f| {
                use ratatui::layout::{Constraint, Layout};
                use ratatui::widgets::{Block, Borders, Paragraph};
                let text: Vec<ratatui::text::Line> =
                    lines.iter().map(|l| ratatui::text::Line::from(l.as_str())).collect();
                let title = " rotorloop watch (q or Ctrl-C quits) ";
                let rows = u16::try_from(lines.len() + 2).unwrap_or(u16::MAX);
                let [top, bottom] =
                    Layout::vertical([Constraint::Length(rows), Constraint::Min(8)])
                        .areas(f.area());
                f.render_widget(
                    Paragraph::new(text).block(Block::default().title(title).borders(Borders::ALL)),
                    top,
                );
                charts::draw(f, bottom, &w.history);
            })?;
            if ratatui::crossterm::event::poll(Duration::ZERO)? {
                if let ratatui::crossterm::event::Event::Key(k) = ratatui::crossterm::event::read()?
                {
                    let ctrl_c = k.code == ratatui::crossterm::event::KeyCode::Char('c')
                        && k.modifiers.contains(ratatui::crossterm::event::KeyModifiers::CONTROL);
                    if k.code == ratatui::crossterm::event::KeyCode::Char('q') || ctrl_c {
                        break;
                    }
                }
            }
        }
        Ok(())
    })();
    ratatui::restore();
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic values from 0.5 µs to about 5 ms, skewed like lateness (many small,
    /// a long tail), with NaNs (ticks without a value) among them.
    fn values(n: usize, seed: u64) -> Vec<f64> {
        let mut x = seed;
        (0..n)
            .map(|i| {
                x = x
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                let u = (x >> 11) as f64 / (1u64 << 53) as f64;
                if i % 97 == 0 { f64::NAN } else { 0.5 + 5000.0 * u.powi(6) }
            })
            .collect()
    }

    #[test]
    fn the_spread_since_start_follows_the_values_in_memory_that_does_not_grow() {
        let mut since = SinceStart::new();
        assert_eq!(since.spread(), Spread::default());
        let first = values(100_000, 1);
        first.iter().for_each(|&v| since.record(v));
        let (exact, kept) = (Spread::of(first.iter().copied()), since.spread());
        assert_eq!(kept.count, exact.count);
        assert_eq!(kept.max, exact.max);
        for (k, e) in [(kept.p50, exact.p50), (kept.p99, exact.p99)] {
            // 3 significant digits, and a rank apart at most.
            assert!((k - e).abs() <= 2e-3 * e + 1e-3, "{k} against {e}");
        }
        let buckets = since.ns.distinct_values();
        // Ten times as many values, the same memory.
        values(1_000_000, 2).iter().for_each(|&v| since.record(v));
        assert_eq!(since.ns.distinct_values(), buckets);
        assert_eq!(since.spread().count, exact.count + 1_000_000 - 1_000_000 / 97 - 1);
        // Out of range: counted at the ends, the max still exact.
        since.record(-3.0);
        since.record(7.2e9);
        assert_eq!(since.spread().max, 7.2e9);
        assert_eq!(since.ns.distinct_values(), buckets);
    }

    #[test]
    fn watch_keeps_only_the_events_it_shows() {
        let mut w = Watcher::new("events-test").expect("a domain name");
        for i in 0..100 {
            w.event(format!("event {i}"));
        }
        assert_eq!(w.events.len(), EVENTS_SHOWN);
        assert!(
            w.events.iter().zip(88..100).all(|(kept, i)| kept.ends_with(&format!("event {i}")))
        );
    }
}
