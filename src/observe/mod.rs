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
//!
//! - [`ps`]: `rotorloop ps`, the domains and their roles and services;
//! - [`watch`]: `rotorloop watch`, one loop live;
//! - what both read: each role's process ([`RoleView`]) and whether the domain is this
//!   user's to read ([`unreachable()`]).

pub mod charts;
pub mod foxglove;
pub mod front;
pub mod ps;
pub mod slots;
pub mod viewer;
pub mod watch;

use iceoryx2::prelude::*;
use rotorloop_common::graph::Role;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::role::UsageError;
use serde::Serialize;

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
    // The policies by number (`SCHED_OTHER` = 0 to `SCHED_DEADLINE` = 6; 4 is unused).
    const POLICIES: [&str; 7] = ["other", "fifo", "rr", "batch", "?", "idle", "deadline"];
    let policy = field(41).map(|p| POLICIES.get(p as usize).copied().unwrap_or("?").to_owned());
    (field(39), field(40), policy, crate::cpus::allowed_of(pid))
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

/// Writes `text` to stdout; a reader that went away (`| head`) is not an error.
fn out(text: &str) -> anyhow::Result<()> {
    use std::io::Write;
    match std::io::stdout().lock().write_all(text.as_bytes()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        r => Ok(r?),
    }
}
