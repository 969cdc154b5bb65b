//! The iceoryx2 side shared by the four roles and the link: run domains and their
//! services ([`domain`]), publishers that notify and subscribers that wait ([`ports`]),
//! how a process waits for its input ([`wait`]), and the QoS every service of a run is
//! opened with (`qos`). The algorithms never see any of this; the clock, signals and
//! real-time set-up are [`crate::clock`], [`crate::signals`] and [`crate::rt`].

pub mod domain;
pub mod ports;
mod qos;
pub mod wait;

use std::fmt::Debug;

use iceoryx2::prelude::*;

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
    /// A file or directory of the domain that is not this user's own and private
    /// ([`crate::private`]).
    #[error(transparent)]
    Private(#[from] crate::private::PrivateError),
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

impl IpcError {
    /// Whether this is a refusal of something another user (or a link) put where the
    /// run makes its own files: a usage error (exit 2), not a failure to retry.
    pub fn is_foreign(&self) -> bool {
        matches!(self, Self::Private(crate::private::PrivateError::Foreign(_)))
    }
}

/// The layout version at the end of a type name (`…_v3` → `3`), or `?`.
pub(crate) fn layout_version_of(type_name: &str) -> String {
    type_name
        .rsplit_once("_v")
        .map(|(_, v)| v)
        .filter(|v| !v.is_empty() && v.bytes().all(|b| b.is_ascii_digit()))
        .unwrap_or("?")
        .to_owned()
}

pub(crate) fn iox(what: impl Into<String>) -> impl FnOnce(&dyn Debug) -> IpcError {
    move |e| IpcError::Iceoryx { what: what.into(), detail: format!("{e:?}") }
}

/// Largest subscriber buffer a service allows (the monitor's).
pub const MAX_BUFFER: usize = 4096;

/// Quiets iceoryx2's own console logging unless `IOX2_LOG_LEVEL` says otherwise.
pub fn quiet_iceoryx_logs() {
    set_log_level_from_env_or(LogLevel::Error);
}
