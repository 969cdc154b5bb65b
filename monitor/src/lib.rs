//! The monitor's library part: per-tick tracking metrics and invariant checks
//! ([`metrics`]), the trace file ([`trace`]) and the figures ([`plot`]) of a run.
//! The in-process simulator and the monitor process use the same code, so their traces
//! are comparable column for column.
//!
//! [`policy`] holds what the monitor decides (joining rows, settling, losses, gaps),
//! [`recording`] what it writes, [`report`] its summary ([`summary`] reads it back), and
//! [`process`] the `monitor` process around them.

pub mod assemble;
pub mod derive;
pub mod figures;
pub mod filer;
pub mod hosts;
pub mod latency;
pub mod metrics;
pub mod plot;
pub mod policy;
pub mod process;
pub mod recording;
pub mod report;
pub mod rows;
pub mod stages;
pub mod summary;
pub mod timing;
pub mod trace;

/// This crate's role in the loop, by name (its node, resume slot and flight record).
pub const ROLE: &str = rotorloop_common::graph::Role::Monitor.name();

/// An empty vector with room for `n` elements whose pages are already resident: the
/// elements are written once and dropped. `Vec::with_capacity` only reserves address
/// space, so a long run would otherwise fault its buffers in page by page as they fill
/// (resident memory creeping up by a few hundred bytes a second, and a page fault in the
/// monitor's loop now and then), which looks like a leak in a soak and is not one.
pub(crate) fn prefaulted<T: Clone + Default>(n: usize) -> Vec<T> {
    let mut v = Vec::with_capacity(n);
    v.resize(n, T::default());
    v.clear();
    v
}
