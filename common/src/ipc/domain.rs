//! A run domain: its iceoryx2 configuration, nodes (one per role, a second refused), the
//! services of its topics, and the clean-up of what dead processes left.

use std::cell::Cell;
use std::fmt::Debug;

use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;

use super::ports::{EventPorts, Inbox, Outbox};
use super::qos::{EVENT_QOS, PUBSUB_QOS, history, set_mirror_defaults};
use super::{IpcError, MAX_BUFFER, iox};
use crate::clock::clock_s;
use crate::graph::Topic;
use crate::wire::{ReferenceSample, StateSample, TorqueSample};
use iceoryx2::service::static_config::messaging_pattern::MessagingPattern as StaticPattern;

/// Where every domain keeps iceoryx2's static files (node details, service configurations):
/// a directory of its own directly in `/dev/shm`, `/dev/shm/.<prefix>/` (this string, then
/// the domain's prefix; a tmpfs, not iceoryx2's default `/tmp/iceoryx2`). iceoryx2 0.10
/// `fsync`s each of these files as it writes it (`iceoryx2-cal` `static_storage/file.rs`);
/// on a disk with other writes pending that waited for the disk, and a role (re)started
/// beside a busy disk took up to 3.6 s to create its node (measured: the far-host
/// controller restart that brought control back only after seconds). On a tmpfs the
/// `fsync` does not wait.
///
/// Each domain's directory is its user's alone (made 0700 by [`Domain::make_private`]),
/// in the sticky `/dev/shm`: no directory shared by every user's domains, which would
/// belong to whoever made it first (an earlier `/dev/shm/iox2/` did: root owning it
/// locked every other user out, and another user owning it could rename a live domain's
/// directory). Its name starts with a `.`: iceoryx2 lists `/dev/shm` by the domain's
/// prefix, and an entry named the bare prefix stops it ("Stripping the prefix … leads to
/// invalid content"). The event services' Unix sockets live under it, a socket path has
/// at most 108 bytes, and that bounds the domain and host names ([`Domain::on_host`]).
pub const ICEORYX2_ROOT: &str = "/dev/shm/.";

/// The file iceoryx2 0.10 makes for a domain's global management segment (a node
/// counter), `/dev/shm/<prefix><type hash>_node.<version>.global_mgmt`
/// (`iceoryx2` `node/global_management_segment.rs`, `iceoryx2-cal`
/// `dynamic_storage_configuration.rs`: the SHA-1 of the stored type's name, the name
/// `node`, the package version, the suffix `.global_mgmt`). The unit test
/// `the_global_segment_is_made_private_before_iceoryx2_can_make_it_open` fails if a new
/// iceoryx2 names it otherwise.
fn global_segment_path(prefix: &str) -> std::path::PathBuf {
    use iceoryx2_bb_container::semantic_string::SemanticString;
    use iceoryx2_cal::hash::Hash;
    const STATE_TYPE: &str = "iceoryx2::node::global_management_segment::State";
    let hash = iceoryx2_cal::hash::sha1::Sha1::new(STATE_TYPE.as_bytes()).value();
    let hash = String::from_utf8_lossy(hash.as_base64url().as_bytes()).into_owned();
    let v = iceoryx2_bb_elementary::package_version::PackageVersion::get();
    let name = format!("{prefix}{hash}_node.{}_{}_{}.global_mgmt", v.major(), v.minor(), v.patch());
    std::path::Path::new("/dev/shm").join(name)
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
        let root = format!("{ICEORYX2_ROOT}{prefix}/");
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

    /// The file of the domain's iceoryx2 global management segment (a node counter), which
    /// [`Domain::make_private`] makes.
    pub fn global_segment(&self) -> std::path::PathBuf {
        global_segment_path(&self.prefix)
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
        let out = crate::outdir::OutDir::open(dir).map_err(crate::outdir::to_io)?;
        let config = out.subdir("config").map_err(crate::outdir::to_io)?;
        config.write("iceoryx2.toml", text.as_bytes())?;
        Ok(path)
    }

    /// The domain's iceoryx2 directory, without a trailing `/` ([`ICEORYX2_ROOT`]).
    pub fn root_dir(&self) -> std::path::PathBuf {
        std::path::PathBuf::from(format!("{ICEORYX2_ROOT}{}", self.prefix))
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
        self.make_private()?;
        let node = NodeBuilder::new()
            .name(&node_name)
            .config(&self.config)
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(|e| {
                let full = crate::private::shm_full(None).map(|f| format!(" ({f})"));
                iox(format!("cannot create node {name}{}", full.unwrap_or_default()))(&e)
            })?;
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
        match other {
            Some(pid) => Err(IpcError::DuplicateRole {
                role: role.to_owned(),
                domain: self.name.clone(),
                pid,
            }),
            None => Ok(node),
        }
    }

    /// Makes what iceoryx2 would otherwise make open to every user, before any node
    /// exists, privately, or checks that it is this user's own (`crate::private`):
    /// - the domain's directory under [`ICEORYX2_ROOT`] (mode 0700);
    /// - the global management segment (a node counter), which iceoryx2 creates
    ///   world-readable and -writable on purpose (0666, `enable_global_access`): another
    ///   user who opened it in the moment before a `chmod` kept a writable descriptor
    ///   (and, filled with 0xff, every node creation failed). Made here exclusively,
    ///   0600, as iceoryx2 would initialise it (its package version, a node counter of
    ///   0), so iceoryx2 only ever opens it.
    ///
    /// Anything else already there (another user's, a link, a file others may open) is
    /// refused with [`IpcError::Private`], naming the path and its owner.
    pub fn make_private(&self) -> Result<(), IpcError> {
        crate::private::dir(&self.root_dir())?;
        let path = global_segment_path(&self.prefix);
        let (file, created) = crate::private::open_or_create_file(&path)?;
        if created {
            use std::os::unix::fs::FileExt;
            // iceoryx2-cal's `Data<State>`: the package version (u64), then the counter
            // (u32), padded to 16 bytes. The version is written last: a node that opens
            // the segment while it is 0 waits for it, as for iceoryx2's own creation.
            let version = iceoryx2_bb_elementary::package_version::PackageVersion::get();
            let io = |e: std::io::Error| crate::private::PrivateError::Io {
                path: path.clone(),
                source: e,
            };
            file.set_len(16).map_err(io)?;
            file.write_all_at(&version.to_u64().to_ne_bytes(), 0).map_err(io)?;
        }
        Ok(())
    }

    /// The files and directories in `/dev/shm` with this domain's prefix that are not
    /// this user's own: never used, never removed.
    pub fn foreign_files(&self) -> Vec<crate::private::Foreign> {
        let mut out = Vec::new();
        let shm = std::fs::read_dir("/dev/shm").into_iter().flatten().flatten().map(|e| e.path());
        let ours = shm.filter(|p| {
            p.file_name().is_some_and(|n| n.to_string_lossy().starts_with(&self.prefix))
        });
        for path in std::iter::once(self.root_dir()).chain(ours) {
            let Ok(meta) = std::fs::symlink_metadata(&path) else { continue };
            let dir = meta.is_dir();
            if let Err(f) = crate::private::check(&path, &meta, dir) {
                // Ours with a looser mode (iceoryx2's static files are 0400, its own
                // directories 0750) is ours: only another owner or a link is foreign.
                use std::os::unix::fs::MetadataExt;
                if meta.uid() != crate::private::euid() || meta.file_type().is_symlink() {
                    out.push(f);
                }
            }
        }
        out
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
    ///
    /// Another user's file with the domain's prefix (or a link in the domain directory's
    /// place) is never read, followed or removed: the clean-up refuses with
    /// [`IpcError::Private`] naming the first.
    pub fn cleanup(&self) -> Result<(usize, usize), IpcError> {
        use iceoryx2::node::NodeView;
        if let Some(f) = self.foreign_files().into_iter().next() {
            return Err(crate::private::PrivateError::from(f).into());
        }
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
            let root = self.root_dir();
            if root.exists() {
                std::fs::remove_dir_all(&root).map_err(|e| IpcError::Iceoryx {
                    what: format!("cannot remove {}", root.display()),
                    detail: e.to_string(),
                })?;
            }
            let prefix = self.prefix.as_str();
            for e in std::fs::read_dir("/dev/shm").into_iter().flatten().flatten() {
                // The domain's directory is gone above; nothing else of it is a directory.
                let file = e.file_type().is_ok_and(|t| !t.is_dir());
                if file && e.file_name().to_string_lossy().starts_with(prefix) {
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
        self.node_ids("link", false)
    }

    /// The node name (`rotorloop/<domain>/foxglove`) of a live view's server
    /// (`rotorloop foxglove`): a reader the roles do not wait for when they end.
    pub const VIEWER_NODE: &'static str = "foxglove";

    /// The node ids of the domain's live nodes of `role` (node `rotorloop/<name>/<role>`),
    /// and with `dead` also of its dead ones not cleaned up yet.
    pub fn node_ids(&self, role: &str, dead: bool) -> Vec<u128> {
        use iceoryx2::node::NodeView;
        let name = format!("rotorloop/{}/{role}", self.name);
        let mut ids = Vec::new();
        let _ = Node::<ipc::Service>::list(&self.config, |state| {
            let (id, details) = match &state {
                NodeState::Alive(v) => (v.id().value(), v.details()),
                NodeState::Dead(v) if dead => (v.id().value(), v.details()),
                _ => return CallbackProgression::Continue,
            };
            if details.as_ref().is_some_and(|d| d.name().as_str() == name) {
                ids.push(id);
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

    /// Whether a live node of a role of this host (not a link gateway's) is attached to
    /// `topic`'s publish-subscribe service: the topic is this host's, not only a mirror of
    /// the other host's.
    pub fn used_by_a_role_here(&self, topic: Topic) -> bool {
        use iceoryx2::node::NodeView;
        let Ok(name) = self.service_name(topic) else { return false };
        let gateway = format!("rotorloop/{}/link", self.name);
        let mut used = false;
        let _ = ipc::Service::list(&self.config, |details| {
            let s = &details.static_details;
            if s.name() == &name
                && matches!(s.messaging_pattern(), StaticPattern::PublishSubscribe(_))
            {
                let nodes =
                    details.dynamic_details.as_ref().map(|d| d.nodes.as_slice()).unwrap_or(&[]);
                used |= nodes.iter().any(|n| match n {
                    NodeState::Alive(v) => v
                        .details()
                        .as_ref()
                        .is_some_and(|d| !d.name().as_str().starts_with(&gateway)),
                    _ => false,
                });
            }
            CallbackProgression::Continue
        });
        used
    }

    /// Holds `topic`'s publish-subscribe and event services open for `node`, without a
    /// port, if both exist. A link gateway holds every topic of its host from a node of
    /// its own (not the link's): a service is offered to the other host while a node other
    /// than the link's is attached to it, so a role killed and restarted here no longer
    /// withdraws and re-offers its topics (see `link/src/gateway.rs`). No port: the
    /// subscriber and publisher counts the roles wait for do not change.
    pub fn hold_if_exists(
        &self,
        node: &Node<ipc::Service>,
        topic: Topic,
    ) -> Result<Option<HeldTopic>, IpcError> {
        let name = self.service_name(topic)?;
        for pattern in [MessagingPattern::Event, MessagingPattern::PublishSubscribe] {
            let exists = ipc::Service::does_exist(&name, &self.config, pattern)
                .map_err(|e| iox(format!("cannot look up {name}"))(&e))?;
            if !exists {
                return Ok(None);
            }
        }
        let Ok(event) = node.service_builder(&name).event().open() else { return Ok(None) };
        let ps = node.service_builder(&name);
        fn held<T: 'static>(f: T) -> Box<dyn std::any::Any> {
            Box::new(f)
        }
        let pubsub = match topic {
            Topic::State => ps.publish_subscribe::<StateSample>().open().map(held),
            Topic::Reference => ps.publish_subscribe::<ReferenceSample>().open().map(held),
            Topic::Torque => ps.publish_subscribe::<TorqueSample>().open().map(held),
        };
        Ok(pubsub.ok().map(|pubsub| HeldTopic { _event: event, _pubsub: pubsub }))
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
        Ok(Outbox {
            service,
            publisher,
            notifier,
            preloaned: super::ports::Preloaned(Cell::new(None)),
        })
    }

    /// The receiving end of `topic` with a buffer of `buffer` samples (newest overwrite
    /// oldest). `listen` adds an event listener for [`Wait::Event`](super::wait::Wait::Event) and [`Wait::Hybrid`](super::wait::Wait::Hybrid).
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

/// When process `pid` started, in seconds since boot (`/proc/<pid>/stat`, field 22).
fn process_start_s(pid: libc::pid_t) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name (which may hold spaces) start at field 3.
    let ticks: f64 = stat.rsplit_once(')')?.1.split_whitespace().nth(19)?.parse().ok()?;
    // SAFETY: plain getter.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    (hz > 0).then(|| ticks / hz as f64)
}

/// One topic's services held open without ports ([`Domain::hold_if_exists`]); dropped,
/// the hold ends.
pub struct HeldTopic {
    _event: iceoryx2::service::port_factory::event::PortFactory<ipc::Service>,
    /// The typed publish-subscribe service's port factory, kept for its `Drop`.
    _pubsub: Box<dyn std::any::Any>,
}

impl std::fmt::Debug for HeldTopic {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("HeldTopic")
    }
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
    fn the_global_segment_is_made_private_before_iceoryx2_can_make_it_open() {
        use std::os::unix::fs::{MetadataExt, PermissionsExt};
        let domain = Domain::new(&format!("ipc-gm{}", std::process::id())).expect("domain");
        domain.cleanup().expect("clean");
        let node = domain.node("plant").expect("node");
        let second = domain.node("controller").expect("a second node counts on from it");
        assert_ne!(node.id().value(), second.id().value());
        let segments: Vec<String> =
            shm_files(&domain).into_iter().filter(|n| n.ends_with(".global_mgmt")).collect();
        // Exactly the one made here: iceoryx2 opened it instead of making its own (0666).
        let ours = global_segment_path(domain.prefix());
        let ours = ours.file_name().expect("name").to_string_lossy().into_owned();
        assert_eq!(segments, vec![ours.clone()], "iceoryx2 made a segment of its own");
        let meta = std::fs::metadata(std::path::Path::new("/dev/shm").join(&ours)).expect("meta");
        assert_eq!(meta.permissions().mode() & 0o777, 0o600);
        let root = std::fs::metadata(domain.root_path()).expect("root");
        assert_eq!(root.mode() & 0o777, 0o700);
        drop((node, second));
        domain.cleanup().expect("clean");
        assert!(shm_files(&domain).is_empty(), "{:?}", shm_files(&domain));
    }

    #[test]
    fn another_users_file_in_the_domains_place_is_refused_and_kept() {
        let domain = Domain::new(&format!("ipc-fo{}", std::process::id())).expect("domain");
        domain.cleanup().expect("clean");
        // A link where the domain's directory goes: "another user's" for the check.
        let root = domain.root_dir().to_string_lossy().into_owned();
        // It points at a scratch directory of the test's own: a bug that followed the link
        // and made its target private must not touch anything else.
        let target = std::env::temp_dir().join(format!("rl-link-target-{}", std::process::id()));
        std::fs::create_dir_all(&target).expect("target");
        std::fs::set_permissions(&target, std::os::unix::fs::PermissionsExt::from_mode(0o1777))
            .expect("chmod");
        std::os::unix::fs::symlink(&target, &root).expect("link");
        let e = domain.node("plant").expect_err("refused");
        assert!(e.is_foreign(), "{e}");
        assert!(e.to_string().contains(&root) && e.to_string().contains("symbolic link"), "{e}");
        let e = domain.cleanup().expect_err("clean-up refuses too");
        assert!(e.is_foreign(), "{e}");
        assert!(std::fs::symlink_metadata(&root).is_ok(), "the link was removed");
        let mode = std::fs::metadata(&target).expect("target").permissions();
        assert_eq!(std::os::unix::fs::PermissionsExt::mode(&mode) & 0o7777, 0o1777, "followed");
        std::fs::remove_file(&root).expect("unlink");
        std::fs::remove_dir(&target).expect("target");
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
        // domain goes, under its root and in /dev/shm.
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

    /// The cause of restarts that took seconds: a node's details file, which iceoryx2
    /// `fsync`s, sat on the disk (`/tmp/iceoryx2`, ext4 here), and with other writes
    /// pending the `fsync` waited for them. Every file iceoryx2 writes for a domain, the
    /// node's details and a new service's configuration, must be on a tmpfs. (Fails
    /// with iceoryx2's default root where `/tmp` is a disk, as on the machine this was
    /// found on.)
    #[test]
    fn iceoryx2s_fsynced_files_of_a_domain_are_on_a_tmpfs() {
        const TMPFS_MAGIC: i64 = 0x0102_1994;
        let domain = Domain::new(&format!("ipc-fs{}", std::process::id())).expect("domain");
        let node = domain.node("plant").expect("node");
        let outbox = domain.outbox::<StateSample>(&node, Topic::State).expect("service");
        let mut files = Vec::new();
        let mut dirs = vec![PathBuf::from(domain.root_path())];
        while let Some(d) = dirs.pop() {
            for e in std::fs::read_dir(&d).expect("readable").flatten() {
                match e.file_type().expect("type").is_dir() {
                    true => dirs.push(e.path()),
                    false => files.push(e.path()),
                }
            }
        }
        assert!(files.len() >= 2, "the node's and the service's files: {files:?}");
        for f in &files {
            let c = std::ffi::CString::new(f.as_os_str().as_encoded_bytes()).expect("path");
            // SAFETY: statfs writes into the struct it is given; the path is NUL-ended.
            let mut st: libc::statfs = unsafe { std::mem::zeroed() };
            assert_eq!(unsafe { libc::statfs(c.as_ptr(), &mut st) }, 0, "{}", f.display());
            assert_eq!(
                st.f_type as i64,
                TMPFS_MAGIC,
                "{} is not on a tmpfs: iceoryx2's fsync of it waits for the disk",
                f.display()
            );
        }
        drop((outbox, node));
        domain.cleanup().expect("cleanup");
    }

    /// A sample loaned ahead ([`Outbox::preloan`]) is the one the next send writes and
    /// sends, once: a second preloan keeps it, the send carries what its loan cost, and a
    /// send with none held loans its own. A sample written ahead ([`Outbox::prewrite`])
    /// is sent with its patch.
    #[test]
    fn a_preloaned_sample_is_the_next_one_sent() {
        let domain = Domain::new(&format!("ipc-pl{}", std::process::id())).expect("domain");
        let node = domain.node("plant").expect("node");
        let outbox = domain.outbox::<u64>(&node, Topic::State).expect("outbox");
        let inbox = domain.inbox::<u64>(&node, Topic::State, 8, false).expect("inbox");
        outbox.update_connections();
        let held = |o: &Outbox<u64>| format!("{o:?}").contains("Preloaned(a sample)");
        assert!(!held(&outbox));
        outbox.preloan().expect("loan");
        outbox.preloan().expect("keeps the one held");
        assert!(held(&outbox));
        let cost = outbox.send(7, |_| ()).expect("send");
        assert!(!held(&outbox), "the held sample was sent");
        assert!(cost.loan_ns > 0, "{cost:?}");
        outbox.send(8, |_| ()).expect("a send loans its own");
        // Written ahead: only the patch is applied at the send, to the sample and to what
        // `after` sees, with the same publish stamp.
        outbox.prewrite(100).expect("write ahead");
        assert!(format!("{outbox:?}").contains("Preloaned(a written sample)"));
        let mut seen = 0;
        let patch = |v: &mut u64, stamp: u64| *v += u64::from(stamp > 0);
        outbox.send_prewritten(100, patch, |v| seen = *v).expect("send");
        assert_eq!(seen, 101);
        // Nothing written ahead: the value patched, sent the plain way.
        outbox.send_prewritten(200, patch, |v| seen = *v).expect("send");
        assert_eq!(seen, 201);
        // Loaned ahead but not written (a placeholder): the value written, then patched.
        outbox.preloan().expect("loan");
        outbox.send_prewritten(300, patch, |v| seen = *v).expect("send");
        assert_eq!(seen, 301);
        let mut got = Vec::new();
        inbox.drain(|v| got.push(v)).expect("receive");
        assert_eq!(got, [7, 8, 101, 201, 301]);
        drop((inbox, outbox, node));
        domain.cleanup().expect("cleanup");
    }

    /// Event listeners are Unix sockets under the domain's root, whose paths have at most
    /// 108 bytes: the longest domain name, alone and beside the longest host name, can
    /// listen. (Fails with a root longer than iceoryx2's default `/tmp/iceoryx2/`.)
    #[test]
    fn the_longest_domain_and_host_names_can_listen() {
        let pid = std::process::id().to_string();
        let longest = format!("{pid}{}", "x".repeat(24 - pid.len()));
        let host = "h".repeat(12);
        for (name, host) in [(longest.as_str(), None), (&longest[..11], Some(host.as_str()))] {
            let domain = Domain::on_host(name, host).expect("domain");
            let node = domain.node("plant").expect("node");
            let inbox = domain.inbox::<StateSample>(&node, Topic::State, 1, true);
            let inbox = inbox.unwrap_or_else(|e| panic!("{name} on {host:?}: {e}"));
            drop((inbox, node));
            domain.cleanup().expect("cleanup");
        }
    }

    #[test]
    fn a_domain_name_never_begins_another_domains_prefix() {
        for bad in ["a_b", "", "a/b", "a b", "this-name-is-25-chars-xxx"] {
            assert!(Domain::new(bad).is_err(), "{bad:?} was accepted");
        }
        assert!(Domain::new("Run-1").is_ok());
    }
}
