//! The monitor's library part: per-tick tracking metrics and invariant checks
//! ([`metrics`]), the trace file ([`trace`]) and the figures ([`plot`]) of a run.
//! The in-process simulator and the monitor process use the same code, so their traces
//! are comparable column for column.

pub mod figures;
pub mod latency;
pub mod metrics;
pub mod plot;
pub mod trace;

pub use figures::Recorder;
pub use metrics::{Metrics, TraceRow};
pub use trace::TraceWriter;
