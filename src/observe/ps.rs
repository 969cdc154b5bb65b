//! `rotorloop ps`: the domains on this machine, their roles and their services, from
//! iceoryx2's listings and the roles' resume slots, without a node of its own.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::time::Duration;

use iceoryx2::prelude::*;
use rotorloop_common::clock::now_ns;
use rotorloop_common::graph::Role;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::role::UsageError;
use rotorloop_common::wire::FLAG_LAST;
use serde::Serialize;

use super::slots::Slots;
use super::{RoleView, out, refuse_unreachable, roles, unreachable};

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
#[derive(Debug, Clone, Default, Serialize)]
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
    Ok(DomainView { domain: name.to_owned(), unreachable: Some(why), ..Default::default() })
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
