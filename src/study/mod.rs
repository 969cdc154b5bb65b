//! What is computed from many runs, in process or through the four processes:
//!
//! - [`gains`]: the paper's gain analysis (the linearised loop's poles);
//! - [`margin`]: the delay margin, measured against the computed one;
//! - [`montecarlo`]: almost-global convergence from near-π errors;
//! - [`paper`]: the paper's scenarios, in process and in real time, with one report;
//! - [`bench`](mod@bench): the latency bench, the loop against its baselines in one invocation.
//! - [`stats`]: the median of repeated paired ratios with its confidence interval and verdict;
//!   [`compare`]: two run or bench directories side by side with those intervals.

pub mod bench;
pub mod compare;
pub mod gains;
pub mod margin;
pub mod montecarlo;
pub mod paper;
pub mod stats;
