//! How a process waits for its input ([`Wait`]), and a wait on several descriptors with
//! nanosecond resolution ([`wait_any_readable`]).

use std::fmt::Debug;

use super::IpcError;

/// The longest a listener waits before it looks again (signals, lost wake-ups).
pub(crate) const WAIT_BOUND_NS: u64 = 10_000_000;

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
