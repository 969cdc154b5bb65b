//! How a role ends without losing data, and learns that the run is over.
//!
//! When a role has done its last tick it first drops its subscribers, then keeps its
//! publisher until nobody subscribes to it any more (at most [`LINGER_S`] seconds), so
//! every sample it published can still be read. A role that follows the plant's states
//! learns from the plant's resume slot that the run is over ([`PlantEnd`], [`PlantWatch`]).

use std::time::Duration;

use anyhow::Context;

use crate::clock::now_ns;
use crate::graph::Role;
use crate::ipc::domain::Domain;
use crate::resume::ResumeSlot;
use crate::signals::shutdown_requested;
use crate::wire::{FLAG_LAST, StateSample};

use super::args::RoleArgs;

/// Longest a finished role waits for its subscribers to leave (s).
pub const LINGER_S: u64 = 10;

/// Whether the plant has published its last tick, read from its resume slot (written just
/// before each publish, kept after the plant exits). A role restarted after the run's end
/// gets no more states: with this it learns that it has nothing left to do, instead of
/// waiting for a plant that is gone.
#[derive(Debug)]
pub struct PlantEnd(ResumeSlot<StateSample>);

impl PlantEnd {
    /// Opens the plant's slot of `domain` (created empty if the plant has not yet).
    pub fn open(domain: &Domain) -> anyhow::Result<Self> {
        Ok(Self(ResumeSlot::open(domain, Role::Plant.name()).context("the plant's resume slot")?))
    }

    /// The plant published its last tick.
    pub fn ended(&self) -> bool {
        self.0.load().is_some_and(|s| s.flags & FLAG_LAST != 0)
    }
}

/// How a role that follows the plant's states (controller, reference) notices that the
/// plant is gone: after 1 s without a state it says so once (and says when the plant is
/// back); if the plant's resume slot then says the run is over, the role stops (a role
/// restarted after the end gets no more states and would otherwise wait forever).
#[derive(Debug)]
pub struct PlantWatch {
    role: &'static str,
    end: PlantEnd,
    last_state_ns: u64,
    gone: bool,
}

impl PlantWatch {
    /// Watches the plant of `domain` for `role` (named in its messages).
    pub fn open(domain: &Domain, role: &'static str) -> anyhow::Result<Self> {
        Ok(Self { role, end: PlantEnd::open(domain)?, last_state_ns: now_ns(), gone: false })
    }

    /// A state of tick `tick` arrived, received at `recv_ns` (the receiver's own clock
    /// read: no second one on the hot path).
    #[inline]
    pub fn saw_state(&mut self, tick: u64, recv_ns: u64) {
        self.last_state_ns = recv_ns;
        if std::mem::take(&mut self.gone) {
            self.back(tick);
        }
    }

    /// The plant is back (its line, out of the tick's code).
    #[cold]
    fn back(&self, tick: u64) {
        eprintln!("{}: plant back at tick {tick}", self.role);
    }

    /// A wait ended without a state: whether the run is over (stop).
    pub fn run_over(&mut self) -> bool {
        if now_ns() - self.last_state_ns <= 1_000_000_000 {
            return false;
        }
        if self.end.ended() {
            eprintln!("{}: the plant has ended the run; nothing left to do", self.role);
            return true;
        }
        if !std::mem::replace(&mut self.gone, true) {
            eprintln!("{}: no state from the plant for 1 s (plant gone?)", self.role);
        }
        false
    }
}

/// Waits until `done()` or [`LINGER_S`] seconds or a termination signal.
pub fn linger(mut done: impl FnMut() -> bool) {
    let until = now_ns() + LINGER_S * 1_000_000_000;
    while !done() && now_ns() < until && !shutdown_requested() {
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// How long a finished publisher gives a link gateway's subscriber (which never leaves:
/// it lives as long as the gateway) to take its last samples.
pub const LINK_GRACE_NS: u64 = 300_000_000;

/// [`linger`] for a publisher: until every subscriber but a link gateway's and a live
/// viewer server's has left, and,
/// when a gateway carries the topic to another host, at least [`LINK_GRACE_NS`].
pub fn linger_publisher<T>(out: &crate::ipc::ports::Outbox<T>, role: &RoleArgs)
where
    T: iceoryx2::prelude::ZeroCopySend + std::fmt::Debug + Copy + 'static,
{
    let domain = role.open_domain();
    let links = domain.as_ref().map(|d| d.link_node_ids()).unwrap_or_default();
    // A live viewer's server (`rotorloop foxglove`) reads on as long as the loop runs, and
    // one killed leaves its subscriber until cleaned: neither is waited for.
    let mut others = links.clone();
    others.extend(
        domain
            .as_ref()
            .map(|d| d.node_ids(crate::ipc::domain::Domain::VIEWER_NODE, true))
            .unwrap_or_default(),
    );
    let start = now_ns();
    linger(|| {
        out.subscribers_except(&others) == 0
            && (links.is_empty() || now_ns() - start > LINK_GRACE_NS)
    });
}
