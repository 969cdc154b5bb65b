//! The process side shared by the four roles: run domains and their iceoryx2 services,
//! publishers that notify, subscribers that wait (event, spin or hybrid), the monotonic
//! clock, absolute-deadline sleep, core pinning, SCHED_FIFO, mlock, and termination
//! signals. The algorithms never see any of this.

use std::cell::Cell;
use std::fmt::Debug;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;

use crate::graph::Topic;
use crate::wire::SendCost;

/// An IPC failure, with what was being done.
#[derive(Debug, thiserror::Error)]
pub enum IpcError {
    /// A bad domain name.
    #[error("--domain `{0}` is not allowed: 1 to 24 characters from A-Z a-z 0-9 -")]
    Domain(String),
    /// A bad host name, or one too long for its domain.
    #[error(
        "--host `{host}` is not allowed: 1 to 12 characters from a-z 0-9 -, and at most 23 \
         characters with the domain's name (`{domain}` has {})",
        .domain.len()
    )]
    Host {
        /// The host name given.
        host: String,
        /// The domain it was given for.
        domain: String,
    },
    /// iceoryx2 refused something.
    #[error("{what}: {detail}")]
    Iceoryx {
        /// What was being done.
        what: String,
        /// iceoryx2's error.
        detail: String,
    },
    /// The role already runs in the domain.
    #[error(
        "role `{role}` is already running in domain `{domain}` (pid {pid}); refusing to start a second one \
         (stop it first, or use another --domain)"
    )]
    DuplicateRole {
        /// The role.
        role: String,
        /// The domain.
        domain: String,
        /// The pid of the one that runs.
        pid: String,
    },
    /// The domain's services were made by a build with another sample layout.
    #[error(
        "the `{topic}` service of domain `{domain}` carries `{theirs}` (sample layout v{}) \
         but this build uses `{ours}` (layout v{}): every process of a run must be the same \
         build; stop the other processes of the domain or use another --domain",
        layout_version_of(.theirs),
        layout_version_of(.ours)
    )]
    LayoutSkew {
        /// The service.
        topic: &'static str,
        /// The domain.
        domain: String,
        /// The service's type name.
        theirs: String,
        /// This build's type name.
        ours: String,
    },
}

/// The layout version at the end of a type name (`…_v3` → `3`), or `?`.
fn layout_version_of(type_name: &str) -> String {
    type_name
        .rsplit_once("_v")
        .map(|(_, v)| v)
        .filter(|v| !v.is_empty() && v.bytes().all(|b| b.is_ascii_digit()))
        .unwrap_or("?")
        .to_owned()
}

fn iox(what: impl Into<String>) -> impl FnOnce(&dyn Debug) -> IpcError {
    move |e| IpcError::Iceoryx { what: what.into(), detail: format!("{e:?}") }
}

/// How many reference samples the generator may publish ahead of the newest state.
pub const REFERENCE_LEAD: u64 = 16;
/// Largest subscriber buffer a service allows (the monitor's).
pub const MAX_BUFFER: usize = 4096;

/// History kept for late subscribers: the reference keeps its whole lead.
fn history(topic: Topic) -> usize {
    match topic {
        Topic::Reference => 2 * REFERENCE_LEAD as usize,
        _ => 1,
    }
}

/// The QoS every publish-subscribe service of a run is opened with. Two publishers: the
/// role's and, when the topic crosses hosts, the link gateway's (a second role of the same
/// kind is refused by [`Domain::node`], not by the service).
struct PubSubQos {
    max_publishers: usize,
    max_subscribers: usize,
    max_nodes: usize,
    subscriber_max_buffer_size: usize,
    subscriber_max_borrowed_samples: usize,
    enable_safe_overflow: bool,
}

const PUBSUB_QOS: PubSubQos = PubSubQos {
    max_publishers: 2,
    max_subscribers: 8,
    max_nodes: 16,
    subscriber_max_buffer_size: MAX_BUFFER,
    subscriber_max_borrowed_samples: 2,
    enable_safe_overflow: true,
};

/// The QoS of every event service of a run.
struct EventQos {
    max_notifiers: usize,
    max_listeners: usize,
    max_nodes: usize,
    event_id_max_value: usize,
}

const EVENT_QOS: EventQos =
    EventQos { max_notifiers: 4, max_listeners: 8, max_nodes: 16, event_id_max_value: 8 };

/// A link gateway creates the mirror of a remote service with the local configuration's
/// defaults (iceoryx2-link 0.10), and a role then opens it with the QoS above, which
/// iceoryx2 checks as minimums. So the defaults of a domain's configuration are that QoS,
/// with the largest history of any topic: whoever creates a service first, every role
/// can open it.
fn set_mirror_defaults(config: &mut Config) {
    let ps = &mut config.defaults.publish_subscribe;
    ps.max_publishers = PUBSUB_QOS.max_publishers;
    ps.max_subscribers = PUBSUB_QOS.max_subscribers;
    ps.max_nodes = PUBSUB_QOS.max_nodes;
    ps.subscriber_max_buffer_size = PUBSUB_QOS.subscriber_max_buffer_size;
    ps.subscriber_max_borrowed_samples = PUBSUB_QOS.subscriber_max_borrowed_samples;
    ps.enable_safe_overflow = PUBSUB_QOS.enable_safe_overflow;
    ps.publisher_history_size = history(Topic::Reference);
    let ev = &mut config.defaults.event;
    ev.max_notifiers = EVENT_QOS.max_notifiers;
    ev.max_listeners = EVENT_QOS.max_listeners;
    ev.max_nodes = EVENT_QOS.max_nodes;
    ev.event_id_max_value = EVENT_QOS.event_id_max_value;
}

/// A run domain: every service and node name of a run lives under it, and its shared
/// memory files carry its own prefix, so two runs on one machine never see each other.
#[derive(Debug)]
pub struct Domain {
    name: String,
    /// The "host" this process belongs to (`--host`), or none: the machine is one host.
    host: Option<String>,
    /// The file prefix of the domain's shared memory and its directory under iceoryx2's
    /// root: `rl_<name>_`, or `rh_<host>_<name>_` on a host.
    prefix: String,
    config: Config,
}

impl Domain {
    /// A domain by name (1–24 of `A-Z a-z 0-9 -`). The limit keeps iceoryx2's event
    /// socket paths (`<root>/rl_<domain>_/rl_<domain>_<id>.event`) within the 107 bytes a
    /// Unix socket path may have. No `_`: the file prefix `rl_<domain>_` of one domain
    /// must never begin the prefix of another (`a` and `a_b`), since cleaning a domain
    /// removes files by prefix.
    pub fn new(name: &str) -> Result<Self, IpcError> {
        Self::on_host(name, None)
    }

    /// A domain as seen from `host` (`--host`): the same services by name, but its own
    /// iceoryx2 prefix and root (`rh_<host>_<name>_`), so two hosts on one machine share
    /// nothing but what a link gateway carries between them. Host names are 1–12 of
    /// `a-z 0-9 -`, at most 23 characters with the domain name (the socket path limit
    /// that bounds domain names). The prefix starts `rh_`, a domain's `rl_`: cleaning one
    /// never removes files of the other.
    pub fn on_host(name: &str, host: Option<&str>) -> Result<Self, IpcError> {
        let ok = !name.is_empty()
            && name.len() <= 24
            && name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-');
        if !ok {
            return Err(IpcError::Domain(name.to_owned()));
        }
        if let Some(h) = host {
            let ok = !h.is_empty()
                && h.len() <= 12
                && h.len() + name.len() <= 23
                && h.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-');
            if !ok {
                return Err(IpcError::Host { host: h.to_owned(), domain: name.to_owned() });
            }
        }
        let prefix = match host {
            None => format!("rl_{name}_"),
            Some(h) => format!("rh_{h}_{name}_"),
        };
        let mut config = Config::global_config().clone();
        // Static files under a root of the domain's own, shared memory with its prefix.
        let root = format!("{}{prefix}/", config.global.root_path());
        let root_path = Path::new(root.as_bytes()).map_err(|e| IpcError::Iceoryx {
            what: format!("root path `{root}`"),
            detail: format!("{e:?}"),
        })?;
        config.global.set_root_path(&root_path);
        config.global.prefix = FileName::new(prefix.as_bytes()).map_err(|e| IpcError::Iceoryx {
            what: format!("file prefix `{prefix}`"),
            detail: format!("{e:?}"),
        })?;
        set_mirror_defaults(&mut config);
        Ok(Self { name: name.to_owned(), host: host.map(str::to_owned), prefix, config })
    }

    /// The domain's shared-memory file prefix (`rl_<name>_` or `rh_<host>_<name>_`).
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// The host this domain is seen from, if any.
    pub fn host(&self) -> Option<&str> {
        self.host.as_deref()
    }

    /// The shared-memory file prefix of a domain on no host.
    pub fn prefix_of(name: &str) -> String {
        format!("rl_{name}_")
    }

    /// The domain's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The domain's iceoryx2 configuration.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// Writes the domain's iceoryx2 configuration (prefix, root path, the rest as iceoryx2's
    /// defaults) to `DIR/config/iceoryx2.toml`, where iceoryx2's own CLI looks for it, so
    /// that `cd DIR && iox2 service list` shows this domain's services.
    pub fn write_iox2_config(&self, dir: &std::path::Path) -> std::io::Result<std::path::PathBuf> {
        let text = toml::to_string(&self.config).map_err(std::io::Error::other)?;
        let path = dir.join("config").join("iceoryx2.toml");
        std::fs::create_dir_all(dir.join("config"))?;
        std::fs::write(&path, text)?;
        Ok(path)
    }

    /// The iceoryx2 root directory (static service and node files).
    pub fn root_path(&self) -> String {
        self.config.global.root_path().to_string()
    }

    /// A node for `role`, refused with [`IpcError::DuplicateRole`] when a live process
    /// already holds that role in this domain (the running one is not disturbed).
    pub fn node(&self, role: &str) -> Result<Node<ipc::Service>, IpcError> {
        use iceoryx2::node::NodeView;
        let name = format!("rotorloop/{}/{role}", self.name);
        let node_name = NodeName::new(&name).map_err(|e| iox(format!("node name {name}"))(&e))?;
        let node = NodeBuilder::new()
            .name(&node_name)
            .config(&self.config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|e| iox(format!("cannot create node {name}"))(&e))?;
        // Another live node of the same name: that role is taken. (Dead ones are a killed
        // predecessor: a restart, which is allowed.)
        let mine = node.id().value();
        let mut other = None;
        Node::<ipc::Service>::list(&self.config, |state| {
            if let NodeState::Alive(v) = &state {
                let same = v.details().as_ref().is_some_and(|d| d.name().as_str() == name);
                if same && v.id().value() != mine {
                    other = Some(
                        v.id()
                            .pid::<ipc::Service>()
                            .map_or("unknown".to_owned(), |p| p.to_string()),
                    );
                    return CallbackProgression::Stop;
                }
            }
            CallbackProgression::Continue
        })
        .map_err(|e| iox("cannot list nodes")(&e))?;
        self.restrict_global_segment();
        match other {
            Some(pid) => Err(IpcError::DuplicateRole {
                role: role.to_owned(),
                domain: self.name.clone(),
                pid,
            }),
            None => Ok(node),
        }
    }

    /// iceoryx2 creates its global management segment (a node counter) world-readable and
    /// -writable (mode 0666, `enable_global_access`). A domain belongs to one user: make
    /// it owner-only like every other file of the run. A file of another owner is left
    /// alone (chmod would fail anyway).
    fn restrict_global_segment(&self) {
        use std::os::unix::fs::{MetadataExt, PermissionsExt};
        let prefix = self.prefix.as_str();
        let Ok(dir) = std::fs::read_dir("/dev/shm") else { return };
        // SAFETY: plain getter.
        let me = unsafe { libc::geteuid() };
        for e in dir.flatten() {
            let name = e.file_name();
            let name = name.to_string_lossy();
            if name.starts_with(prefix) && name.ends_with(".global_mgmt") {
                if let Ok(meta) = e.metadata() {
                    if meta.uid() == me && meta.mode() & 0o077 != 0 {
                        let _ = std::fs::set_permissions(
                            e.path(),
                            std::fs::Permissions::from_mode(0o600),
                        );
                    }
                }
            }
        }
    }

    /// Removes what dead nodes of this domain left behind and, when no process of the
    /// domain is alive any more, everything else of it: its directory under iceoryx2's
    /// root, and every `/dev/shm` file with its prefix (the global management segment,
    /// service segments, resume slots). Returns `(dead nodes cleaned, nodes still alive)`.
    ///
    /// iceoryx2's own cleanup sees only the nodes it lists, and it lists a node by its
    /// monitor token. A node killed between writing its details and creating its token
    /// (a restart killed early) is never listed, and a node killed while it was being
    /// torn down can leave token files that no cleanup removes. Those are found here by
    /// the process id inside the node id: an entry whose process is gone is stale.
    pub fn cleanup(&self) -> Result<(usize, usize), IpcError> {
        use iceoryx2::node::NodeView;
        // The domain has a root directory of its own, so every node listed here is of this
        // domain; one without readable details was killed while it was being created.
        let ours = format!("rotorloop/{}/", self.name);
        let mine = |d: &Option<iceoryx2::node::NodeDetails>| {
            d.as_ref().is_none_or(|d| d.name().as_str().starts_with(&ours))
        };
        let (mut cleaned, mut alive) = (0, 0);
        Node::<ipc::Service>::list(&self.config, |state| {
            match state {
                NodeState::Alive(v) if mine(v.details()) => alive += 1,
                NodeState::Dead(v) if mine(v.details()) => {
                    cleaned += usize::from(v.try_remove_stale_resources().is_ok());
                }
                _ => {}
            }
            CallbackProgression::Continue
        })
        .map_err(|e| iox("cannot list nodes")(&e))?;
        // What iceoryx2 left. An id whose process still runs is a live node, or one being
        // created right now (not listed yet): that keeps the domain.
        let nodes = self.node_entries();
        let live = nodes.keys().filter(|&&id| node_process_alive(id)).count();
        for (&id, entries) in &nodes {
            let has_token = entries.iter().any(|p| p.is_file());
            if !has_token && !node_process_alive(id) {
                // Details only: the token was never created, so no port was either.
                for p in entries {
                    let _ = std::fs::remove_dir_all(p);
                }
                cleaned += 1;
            }
        }
        if alive == 0 && live == 0 {
            // No process of the domain is left: whatever remains is stale.
            let root = std::path::PathBuf::from(self.root_path());
            if root.exists() {
                std::fs::remove_dir_all(&root).map_err(|e| IpcError::Iceoryx {
                    what: format!("cannot remove {}", root.display()),
                    detail: e.to_string(),
                })?;
            }
            let prefix = self.prefix.as_str();
            for e in std::fs::read_dir("/dev/shm").into_iter().flatten().flatten() {
                if e.file_name().to_string_lossy().starts_with(prefix) {
                    std::fs::remove_file(e.path()).map_err(|err| IpcError::Iceoryx {
                        what: format!("cannot remove {}", e.path().display()),
                        detail: err.to_string(),
                    })?;
                }
            }
        }
        Ok((cleaned, alive.max(live)))
    }

    /// The entries under the domain's node directory, by node id: the node's directory
    /// (`<id>/`, its details and port tags) and its monitor token files
    /// (`<prefix><id>.node_monitor…`).
    fn node_entries(&self) -> std::collections::BTreeMap<u128, Vec<std::path::PathBuf>> {
        let prefix = self.prefix.as_str();
        let dir = std::path::PathBuf::from(self.root_path()).join("nodes");
        let mut out = std::collections::BTreeMap::<u128, Vec<_>>::new();
        for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            let name = e.file_name();
            let name = name.to_string_lossy();
            let bare = name.strip_prefix(prefix).unwrap_or(&name);
            let id = bare.split('.').next().and_then(|s| s.parse::<u128>().ok());
            if let Some(id) = id {
                out.entry(id).or_default().push(e.path());
            }
        }
        out
    }

    /// What every service name of the domain starts with (`rotorloop/<name>/`): what a
    /// link gateway bridges.
    pub fn service_prefix(&self) -> String {
        format!("rotorloop/{}/", self.name)
    }

    /// The node ids of the domain's live link gateways (node `rotorloop/<name>/link`).
    pub fn link_node_ids(&self) -> Vec<u128> {
        use iceoryx2::node::NodeView;
        let name = format!("rotorloop/{}/link", self.name);
        let mut ids = Vec::new();
        let _ = Node::<ipc::Service>::list(&self.config, |state| {
            if let NodeState::Alive(v) = &state {
                if v.details().as_ref().is_some_and(|d| d.name().as_str() == name) {
                    ids.push(v.id().value());
                }
            }
            CallbackProgression::Continue
        });
        ids
    }

    /// Whether `topic`'s publish-subscribe service exists in this domain (made by a role,
    /// or mirrored by a link gateway from another host).
    pub fn topic_exists(&self, topic: Topic) -> bool {
        self.service_name(topic).is_ok_and(|name| {
            matches!(
                ipc::Service::does_exist(&name, &self.config, MessagingPattern::PublishSubscribe),
                Ok(true)
            )
        })
    }

    /// A listener and a notifier on `topic`'s event service for `node`, if the service
    /// exists (a link gateway wakes on the domain's events, and re-wakes the receivers of
    /// samples it brought in, without creating any service).
    pub fn event_ports_if_exists(
        &self,
        node: &Node<ipc::Service>,
        topic: Topic,
    ) -> Result<Option<EventPorts>, IpcError> {
        let name = self.service_name(topic)?;
        let exists = ipc::Service::does_exist(&name, &self.config, MessagingPattern::Event)
            .map_err(|e| iox(format!("cannot look up {name}"))(&e))?;
        if !exists {
            return Ok(None);
        }
        let Ok(service) = node.service_builder(&name).event().open() else { return Ok(None) };
        let listener = service
            .listener_builder()
            .create()
            .map_err(|e| iox(format!("cannot listen to {name}"))(&e))?;
        let notifier = service
            .notifier_builder()
            .create()
            .map_err(|e| iox(format!("cannot notify {name}"))(&e))?;
        Ok(Some((listener, notifier)))
    }

    fn service_name(&self, topic: Topic) -> Result<ServiceName, IpcError> {
        let name = format!("rotorloop/{}/{}", self.name, topic.name());
        ServiceName::new(&name).map_err(|e| iox(format!("service name {name}"))(&e))
    }

    fn pubsub<T: ZeroCopySend + Debug + Copy + 'static>(
        &self,
        node: &Node<ipc::Service>,
        topic: Topic,
    ) -> Result<PubSubFactory<ipc::Service, T, ()>, IpcError> {
        let name = self.service_name(topic)?;
        // Every role opens with the same QoS, so the start order does not matter.
        node.service_builder(&name)
            .publish_subscribe::<T>()
            .max_publishers(PUBSUB_QOS.max_publishers)
            .max_subscribers(PUBSUB_QOS.max_subscribers)
            .max_nodes(PUBSUB_QOS.max_nodes)
            .history_size(history(topic))
            .subscriber_max_buffer_size(PUBSUB_QOS.subscriber_max_buffer_size)
            .subscriber_max_borrowed_samples(PUBSUB_QOS.subscriber_max_borrowed_samples)
            .enable_safe_overflow(PUBSUB_QOS.enable_safe_overflow)
            .open_or_create()
            .map_err(|e| {
                self.layout_skew::<T>(&name, topic).unwrap_or_else(|| {
                    iox(format!("cannot open service {name} ({})", topic.name()))(&e)
                })
            })
    }

    /// When `topic`'s service exists with another payload type than `T`: the skew.
    fn layout_skew<T: ZeroCopySend>(&self, name: &ServiceName, topic: Topic) -> Option<IpcError> {
        let details = ipc::Service::details(name, &self.config, MessagingPattern::PublishSubscribe)
            .ok()??;
        let theirs =
            details.static_details.publish_subscribe().message_type_details().payload.type_name();
        let theirs = theirs.to_string();
        // SAFETY: type_name only returns the static name.
        let ours = unsafe { <T as ZeroCopySend>::type_name() }.to_owned();
        (theirs != ours).then(|| IpcError::LayoutSkew {
            topic: topic.name(),
            domain: self.name.clone(),
            theirs,
            ours,
        })
    }

    fn event(
        &self,
        node: &Node<ipc::Service>,
        topic: Topic,
    ) -> Result<iceoryx2::service::port_factory::event::PortFactory<ipc::Service>, IpcError> {
        let name = self.service_name(topic)?;
        node.service_builder(&name)
            .event()
            .max_notifiers(EVENT_QOS.max_notifiers)
            .max_listeners(EVENT_QOS.max_listeners)
            .max_nodes(EVENT_QOS.max_nodes)
            .event_id_max_value(EVENT_QOS.event_id_max_value)
            .open_or_create()
            .map_err(|e| iox(format!("cannot open event service {name}"))(&e))
    }

    /// The publishing end of `topic`. Fails when its two publisher slots (the role's and a
    /// link gateway's) are taken; a second role of the same kind is refused earlier, by
    /// [`Domain::node`].
    pub fn outbox<T: ZeroCopySend + Debug + Copy + 'static>(
        &self,
        node: &Node<ipc::Service>,
        topic: Topic,
    ) -> Result<Outbox<T>, IpcError> {
        let service = self.pubsub::<T>(node, topic)?;
        let publisher =
            service.publisher_builder().max_loaned_samples(2).create().map_err(|e| {
                iox(format!(
                    "cannot publish `{}` in domain `{}` (its publisher slots are taken)",
                    topic.name(),
                    self.name
                ))(&e)
            })?;
        let notifier = self
            .event(node, topic)?
            .notifier_builder()
            .create()
            .map_err(|e| iox(format!("cannot notify `{}`", topic.name()))(&e))?;
        Ok(Outbox { service, publisher, notifier })
    }

    /// The receiving end of `topic` with a buffer of `buffer` samples (newest overwrite
    /// oldest). `listen` adds an event listener for [`Wait::Event`] and [`Wait::Hybrid`].
    pub fn inbox<T: ZeroCopySend + Debug + Copy + 'static>(
        &self,
        node: &Node<ipc::Service>,
        topic: Topic,
        buffer: usize,
        listen: bool,
    ) -> Result<Inbox<T>, IpcError> {
        let service = self.pubsub::<T>(node, topic)?;
        let subscriber = service
            .subscriber_builder()
            .buffer_size(buffer.clamp(1, MAX_BUFFER))
            .history_request(history(topic))
            .create()
            .map_err(|e| iox(format!("cannot subscribe to `{}`", topic.name()))(&e))?;
        let listener = if listen {
            Some(
                self.event(node, topic)?
                    .listener_builder()
                    .create()
                    .map_err(|e| iox(format!("cannot listen to `{}`", topic.name()))(&e))?,
            )
        } else {
            None
        };
        Ok(Inbox { subscriber, listener, unnotified: Cell::new(0) })
    }
}

/// A listener and a notifier on one event service.
pub type EventPorts = (Listener<ipc::Service>, Notifier<ipc::Service>);

/// A role's iceoryx2 node: it must outlive the role's ports.
pub type RoleNode = Node<ipc::Service>;

/// A publisher and the notifier that wakes its subscribers.
#[derive(Debug)]
pub struct Outbox<T: ZeroCopySend + Debug + Copy + 'static> {
    service: PubSubFactory<ipc::Service, T, ()>,
    publisher: Publisher<ipc::Service, T, ()>,
    notifier: Notifier<ipc::Service>,
}

impl<T: ZeroCopySend + Debug + Copy + 'static> Outbox<T> {
    /// Waits until at least `n` subscribers are connected (those that must see the first
    /// sample), polling every millisecond; false on a termination signal.
    pub fn wait_for_subscribers(&self, n: usize) -> bool {
        while self.subscribers() < n {
            if shutdown_requested() {
                return false;
            }
            self.update_connections();
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        self.update_connections();
        true
    }

    /// Publishes `value` (written in place into shared memory) and notifies listeners.
    /// `stamp` is called just before the send to set the publish timestamp. Returns what
    /// each step cost (for the stage breakdown; four clock reads).
    #[inline]
    pub fn send(&self, value: T, stamp: impl FnOnce(&mut T)) -> Result<SendCost, IpcError> {
        self.send_then(value, stamp, |_| ())
    }

    /// [`Outbox::send`], then `after` with the sample as published (its flight record),
    /// once the listeners are notified: off the hop it starts.
    #[inline]
    pub fn send_then(
        &self,
        mut value: T,
        stamp: impl FnOnce(&mut T),
        after: impl FnOnce(&T),
    ) -> Result<SendCost, IpcError> {
        let t0 = now_ns();
        let sample = self.publisher.loan_uninit().map_err(|e| iox("cannot loan a sample")(&e))?;
        let t1 = now_ns();
        stamp(&mut value);
        sample.write_payload(value).send().map_err(|e| iox("cannot send a sample")(&e))?;
        let t2 = now_ns();
        self.notifier.notify().map_err(|e| iox("cannot notify")(&e))?;
        let cost = SendCost { loan_ns: t1 - t0, send_ns: t2 - t1, notify_ns: now_ns() - t2 };
        after(&value);
        Ok(cost)
    }

    /// Loans a sample and never sends it, until a termination signal: a test hook for
    /// "killed while holding a loan" (iceoryx2 must reclaim the loan after the kill).
    pub fn stall_holding_a_loan(&self) -> Result<(), IpcError> {
        let sample = self.publisher.loan_uninit().map_err(|e| iox("cannot loan a sample")(&e))?;
        while !shutdown_requested() {
            std::thread::sleep(Duration::from_millis(5));
        }
        drop(sample);
        Ok(())
    }

    /// Connects subscribers that appeared since the last send (and gives them history).
    pub fn update_connections(&self) {
        let _ = self.publisher.update_connections();
    }

    /// Subscribers currently connected to this topic.
    pub fn subscribers(&self) -> usize {
        self.service.dynamic_config().number_of_subscribers()
    }

    /// Subscribers of this topic that belong to none of `nodes` (a link gateway's).
    pub fn subscribers_except(&self, nodes: &[u128]) -> usize {
        let mut n = 0;
        self.service.dynamic_config().list_subscribers(|d| {
            n += usize::from(!nodes.contains(&d.node_id.value()));
            CallbackProgression::Continue
        });
        n
    }
}

/// A subscriber and, optionally, the listener that wakes it.
#[derive(Debug)]
pub struct Inbox<T: ZeroCopySend + Debug + Copy + 'static> {
    subscriber: Subscriber<ipc::Service, T, ()>,
    listener: Option<Listener<ipc::Service>>,
    /// See [`Inbox::unnotified`].
    unnotified: Cell<u64>,
}

impl<T: ZeroCopySend + Debug + Copy + 'static> Inbox<T> {
    /// Takes every waiting sample, oldest first, handing each to `f`.
    #[inline]
    pub fn drain(&self, mut f: impl FnMut(T)) -> Result<(), IpcError> {
        while let Some(x) = self.take()? {
            f(x);
        }
        Ok(())
    }

    /// Takes the oldest waiting sample, if any.
    #[inline]
    pub fn take(&self) -> Result<Option<T>, IpcError> {
        match self.subscriber.receive() {
            Ok(Some(s)) => Ok(Some(*s.payload())),
            Ok(None) => Ok(None),
            Err(e) => Err(iox("cannot receive")(&e)),
        }
    }

    /// Lost wake-ups: how often [`Inbox::wait_for`] found what it waited for only after a
    /// whole bounded wait (10 ms) passed with no notification. Every publisher notifies
    /// after it sends, so on one host this stays 0; a sample that comes in through a link
    /// gateway without a wake-up after it counts here (and costs its receiver up to 10 ms).
    /// (A sample that lands in the microsecond between the bound's end and the look after
    /// it counts too, falsely; that needs a 10 ms silence first.)
    pub fn unnotified(&self) -> u64 {
        self.unnotified.get()
    }

    /// Waits until `ready()` returns something, the monotonic deadline passes, or a
    /// termination signal arrives. `ready` is polled first, after every wake-up, and in
    /// spin mode continuously; it should drain the inbox.
    #[inline]
    pub fn wait_for<R>(
        &self,
        wait: Wait,
        deadline_ns: u64,
        mut ready: impl FnMut(&Self) -> Result<Option<R>, IpcError>,
    ) -> Result<Option<R>, IpcError> {
        let start = now_ns();
        let mut slept_through = false;
        loop {
            if let Some(r) = ready(self)? {
                if slept_through {
                    self.unnotified.set(self.unnotified.get() + 1);
                }
                return Ok(Some(r));
            }
            let now = now_ns();
            if now >= deadline_ns || shutdown_requested() {
                return Ok(None);
            }
            let spin = match wait {
                Wait::Spin => true,
                Wait::Event => false,
                Wait::Hybrid { spin_ns } => now - start < spin_ns,
                Wait::Poll { period_ns } => {
                    let nap = period_ns.min(deadline_ns - now).min(10_000_000);
                    std::thread::sleep(Duration::from_nanos(nap));
                    continue;
                }
            };
            let left = deadline_ns - now;
            slept_through = match (&self.listener, spin || left < 2_000) {
                // Bounded so that signals are seen; wake-ups merge, so drain after. A
                // silent wait counts only when the bound, not the deadline, ended it.
                (Some(l), false) => {
                    !wait_readable(l, left.min(WAIT_BOUND_NS))? && left > WAIT_BOUND_NS
                }
                _ => {
                    std::hint::spin_loop();
                    false
                }
            };
        }
    }
}

/// Blocks until `listener` has an event or `timeout_ns` passes, then drains its events.
///
/// Not iceoryx2's `Listener::timed_wait`: it sets the timeout as `SO_RCVTIMEO`, which Linux
/// counts in jiffies (4 ms at `HZ=250`), so a 1 ms timeout blocked 4–8 ms here (found as
/// real-time ticks late by up to 8 ms whenever a torque did not come; and a timeout under
/// 1 µs becomes `{0, 0}`: wait forever). `ppoll` on the listener's socket has an hrtimer
/// timeout with nanosecond resolution; the listener is drained with `try_wait` after.
/// Returns whether a notification (or a signal) came.
fn wait_readable(listener: &Listener<ipc::Service>, timeout_ns: u64) -> Result<bool, IpcError> {
    use iceoryx2_bb_posix::file_descriptor::FileDescriptorBased;
    // SAFETY: the listener owns the descriptor and outlives this call; it is only polled.
    let fd = unsafe { listener.file_descriptor().native_handle() };
    wait_any_readable(&[fd], timeout_ns)?;
    let mut notified = false;
    match listener.try_wait(|_| notified = true) {
        Ok(_) => Ok(notified),
        // A signal (SIGTERM to stop, say) is a wake-up like any other.
        Err(iceoryx2::port::listener::ListenerWaitError::InterruptSignal) => Ok(true),
        Err(e) => Err(iox("cannot drain events")(&e)),
    }
}

/// The longest a listener waits before it looks again (signals, lost wake-ups).
const WAIT_BOUND_NS: u64 = 10_000_000;

/// Blocks until one of `fds` (at most 8) is readable, `timeout_ns` passes or a signal
/// arrives: `ppoll`, whose timeout is an hrtimer with nanosecond resolution (unlike
/// iceoryx2's `SO_RCVTIMEO`; see `wait_readable`). The caller drains what woke it.
pub fn wait_any_readable(fds: &[i32], timeout_ns: u64) -> Result<(), IpcError> {
    let mut pfds: [libc::pollfd; 8] = [libc::pollfd { fd: -1, events: 0, revents: 0 }; 8];
    assert!(fds.len() <= pfds.len(), "at most {} descriptors", pfds.len());
    for (p, &fd) in pfds.iter_mut().zip(fds) {
        *p = libc::pollfd { fd, events: libc::POLLIN, revents: 0 };
    }
    let ts = libc::timespec {
        tv_sec: (timeout_ns / 1_000_000_000) as libc::time_t,
        tv_nsec: (timeout_ns % 1_000_000_000) as libc::c_long,
    };
    // SAFETY: valid pollfds (the first fds.len()), a valid timespec, no signal mask change.
    let r =
        unsafe { libc::ppoll(pfds.as_mut_ptr(), fds.len() as libc::nfds_t, &ts, std::ptr::null()) };
    if r < 0 && std::io::Error::last_os_error().kind() != std::io::ErrorKind::Interrupted {
        return Err(IpcError::Iceoryx {
            what: "cannot wait for an event".into(),
            detail: std::io::Error::last_os_error().to_string(),
        });
    }
    Ok(())
}

/// How a process waits for its input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wait {
    /// Block on an event (the default: four processes can share two cores).
    Event,
    /// Busy-poll (for dedicated cores).
    Spin,
    /// Spin for `spin_ns`, then block.
    Hybrid {
        /// How long to spin before blocking (ns).
        spin_ns: u64,
    },
    /// Sleep `period_ns` between looks, with no listener (nobody has to wake this process:
    /// the real-time reference, which works ahead of the loop).
    Poll {
        /// Time between looks (ns).
        period_ns: u64,
    },
}

impl Wait {
    /// Whether this strategy needs an event listener.
    pub fn listens(self) -> bool {
        !matches!(self, Self::Spin | Self::Poll { .. })
    }
}

impl std::str::FromStr for Wait {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "event" => Ok(Self::Event),
            "spin" => Ok(Self::Spin),
            "hybrid" => Ok(Self::Hybrid { spin_ns: 50_000 }),
            other => Err(format!("`{other}` is not allowed: event, spin or hybrid")),
        }
    }
}

impl std::fmt::Display for Wait {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Event => f.write_str("event"),
            Self::Spin => f.write_str("spin"),
            Self::Hybrid { .. } => f.write_str("hybrid"),
            Self::Poll { period_ns } => write!(f, "poll every {} µs", period_ns / 1000),
        }
    }
}

/// Whether the process that created node `id` still runs. iceoryx2's node id is its
/// `UniqueSystemId`: `repr(C)` `{ seconds, nanoseconds, pid, counter }` as a `u128`, the
/// time from `CLOCK_MONOTONIC` (checked against a real node by a test). A process with
/// that pid that started after the node was created has only reused the pid.
fn node_process_alive(id: u128) -> bool {
    let pid = (id >> 64) as u32;
    let Ok(pid) = libc::pid_t::try_from(pid) else { return false };
    if pid <= 0 {
        return false;
    }
    // SAFETY: signal 0 only checks that the process exists.
    let exists = unsafe { libc::kill(pid, 0) } == 0
        || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM);
    if !exists {
        return false;
    }
    // The node's creation on the boot clock (the clock of /proc's start times). Suspend
    // since then only moves it later, never making the creator look like a newcomer.
    let created_mono_s = (id & 0xffff_ffff) as f64;
    let boot_minus_mono = clock_s(libc::CLOCK_BOOTTIME) - clock_s(libc::CLOCK_MONOTONIC);
    process_start_s(pid).is_none_or(|start| start <= created_mono_s + boot_minus_mono + 2.0)
}

fn clock_s(clock: libc::clockid_t) -> f64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: valid pointer to a timespec.
    unsafe { libc::clock_gettime(clock, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// When process `pid` started, in seconds since boot (`/proc/<pid>/stat`, field 22).
fn process_start_s(pid: libc::pid_t) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name (which may hold spaces) start at field 3.
    let ticks: f64 = stat.rsplit_once(')')?.1.split_whitespace().nth(19)?.parse().ok()?;
    // SAFETY: plain getter.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    (hz > 0).then(|| ticks / hz as f64)
}

/// `CLOCK_MONOTONIC` in nanoseconds.
#[inline]
pub fn now_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes into the timespec we own.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Sleeps until the absolute `CLOCK_MONOTONIC` time `deadline_ns` (no drift from
/// relative sleeps). With `spin_last_ns > 0`, sleeps until that much before the deadline
/// and spins the rest.
#[inline]
pub fn sleep_until_ns(deadline_ns: u64, spin_last_ns: u64) {
    let wake = deadline_ns.saturating_sub(spin_last_ns);
    let ts = libc::timespec {
        tv_sec: (wake / 1_000_000_000) as libc::time_t,
        tv_nsec: (wake % 1_000_000_000) as libc::c_long,
    };
    loop {
        // SAFETY: ts is a valid timespec; the remaining-time pointer may be null with
        // TIMER_ABSTIME.
        let rc = unsafe {
            libc::clock_nanosleep(
                libc::CLOCK_MONOTONIC,
                libc::TIMER_ABSTIME,
                &ts,
                std::ptr::null_mut(),
            )
        };
        if rc != libc::EINTR || shutdown_requested() {
            break;
        }
    }
    while now_ns() < deadline_ns {
        std::hint::spin_loop();
    }
}

static SHUTDOWN: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_: libc::c_int) {
    SHUTDOWN.store(true, Ordering::SeqCst);
}

/// Installs SIGINT/SIGTERM handlers that set the flag read by [`shutdown_requested`].
pub fn install_signal_handlers() {
    for sig in [libc::SIGINT, libc::SIGTERM] {
        // SAFETY: the handler only stores to an atomic, which is async-signal-safe.
        unsafe {
            let mut sa: libc::sigaction = std::mem::zeroed();
            sa.sa_sigaction = on_signal as *const () as usize;
            libc::sigemptyset(&mut sa.sa_mask);
            libc::sigaction(sig, &sa, std::ptr::null_mut());
        }
    }
}

/// Whether SIGINT or SIGTERM arrived.
#[inline]
pub fn shutdown_requested() -> bool {
    SHUTDOWN.load(Ordering::Relaxed)
}

/// Requests shutdown from inside the process (as a signal would).
pub fn request_shutdown() {
    SHUTDOWN.store(true, Ordering::SeqCst);
}

/// Real-time set-up of a process. Each step that the OS refuses gives a one-line warning
/// and the process runs on.
#[derive(Debug, Clone, Copy, Default)]
pub struct RtSetup {
    /// Pin to this core.
    pub core: Option<usize>,
    /// SCHED_FIFO priority (1–99).
    pub rt_priority: Option<i32>,
    /// Lock all memory (mlockall).
    pub mlock: bool,
}

impl RtSetup {
    /// Applies the set-up; returns the warnings.
    pub fn apply(&self, role: &str) -> Vec<String> {
        let mut warnings = Vec::new();
        // Timer slack (50 µs by default) delays every timed wake-up; ask for 1 ns.
        // SAFETY: plain prctl on the calling thread.
        unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong, 0, 0, 0) };
        if let Some(core) = self.core {
            let ids = core_affinity::get_core_ids().unwrap_or_default();
            match ids.into_iter().find(|c| c.id == core) {
                Some(id) if core_affinity::set_for_current(id) => {}
                _ => warnings.push(format!("{role}: cannot pin to core {core}; running unpinned")),
            }
        }
        if let Some(p) = self.rt_priority {
            let param = libc::sched_param { sched_priority: p };
            // SAFETY: plain syscall on the calling thread with a valid param.
            if unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) } != 0 {
                warnings.push(format!(
                    "{role}: SCHED_FIFO priority {p} not permitted ({}); running with the default policy",
                    std::io::Error::last_os_error()
                ));
            }
        }
        if self.mlock {
            // SAFETY: plain syscall.
            if unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) } != 0 {
                warnings.push(format!(
                    "{role}: mlockall failed ({}); memory may be paged",
                    std::io::Error::last_os_error()
                ));
            }
        }
        warnings
    }
}

/// Quiets iceoryx2's own console logging unless `IOX2_LOG_LEVEL` says otherwise.
pub fn quiet_iceoryx_logs() {
    set_log_level_from_env_or(LogLevel::Error);
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    /// The pid of a process that has exited (and been reaped).
    fn dead_pid() -> u32 {
        let mut c = std::process::Command::new("true").spawn().expect("spawn true");
        let pid = c.id();
        c.wait().expect("wait");
        pid
    }

    fn node_id(secs: u32, pid: u32, counter: u32) -> u128 {
        u128::from(secs) | (u128::from(pid) << 64) | (u128::from(counter) << 96)
    }

    fn shm_files(domain: &Domain) -> Vec<String> {
        let prefix = Domain::prefix_of(domain.name());
        std::fs::read_dir("/dev/shm")
            .expect("/dev/shm")
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with(&prefix))
            .collect()
    }

    #[test]
    fn a_node_id_carries_the_pid_of_its_creator() {
        let domain = Domain::new(&format!("ipc-id{}", std::process::id())).expect("domain");
        let node = domain.node("plant").expect("node");
        let id = node.id().value();
        assert_eq!((id >> 64) as u32, std::process::id());
        assert!(node_process_alive(id));
        assert!(!node_process_alive(node_id(id as u32, dead_pid(), 1)));
        // The same pid, taken by a process that started long after the node: reused.
        assert!(!node_process_alive(node_id(0, std::process::id(), 1)));
        drop(node);
        domain.cleanup().expect("cleanup");
    }

    #[test]
    fn cleanup_removes_nodes_killed_mid_creation_and_keeps_live_ones() {
        let domain = Domain::new(&format!("ipc-cl{}", std::process::id())).expect("domain");
        let node = domain.node("plant").expect("node");
        let nodes = PathBuf::from(domain.root_path()).join("nodes");
        let prefix = Domain::prefix_of(domain.name());
        // A restart killed between writing its details and creating its monitor token.
        let orphan = nodes.join(node_id(1, dead_pid(), 3).to_string());
        std::fs::create_dir_all(&orphan).expect("mkdir");
        std::fs::write(orphan.join(format!("{prefix}node.details")), b"x").expect("write");
        // A node being created right now by a live process: not touched.
        let creating = nodes.join(node.id().value().wrapping_add(1 << 96).to_string());
        std::fs::create_dir_all(&creating).expect("mkdir");

        let (cleaned, alive) = domain.cleanup().expect("cleanup");
        assert!(!orphan.exists(), "the orphan's details stay");
        assert!(creating.exists(), "a node of a live process was removed");
        assert_eq!((cleaned, alive), (1, 2));
        std::fs::remove_dir(&creating).expect("rmdir");

        // Token files of a dead node without details, and no process left: all of the
        // domain goes, in /tmp/iceoryx2 and in /dev/shm.
        let ghost = node_id(1, dead_pid(), 4);
        for suffix in ["node_monitor", "node_monitor_owner_lock", "node_monitor_context"] {
            std::fs::write(nodes.join(format!("{prefix}{ghost}.{suffix}")), b"").expect("write");
        }
        drop(node);
        let (_, alive) = domain.cleanup().expect("cleanup");
        assert_eq!(alive, 0);
        assert!(!PathBuf::from(domain.root_path()).exists(), "the domain's root stays");
        assert_eq!(shm_files(&domain), Vec::<String>::new());
    }

    #[test]
    fn a_domain_name_never_begins_another_domains_prefix() {
        for bad in ["a_b", "", "a/b", "a b", "this-name-is-25-chars-xxx"] {
            assert!(Domain::new(bad).is_err(), "{bad:?} was accepted");
        }
        assert!(Domain::new("Run-1").is_ok());
    }
}
