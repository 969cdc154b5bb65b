//! The `timer` baseline: what the kernel allows a thread that sleeps to the plant's grid.
//! A bare thread sleeps to the same absolute grid as the plant, with the same clock
//! (`CLOCK_MONOTONIC`, `TIMER_ABSTIME`), the same timer slack (1 ns), scheduling class,
//! priority, core and spin before each tick, through the same function
//! ([`sleep_until_ns`]), and records how late it woke: cyclictest's measurement, in the
//! bench's own invocation. The plant's tick lateness is judged against it.

use std::path::PathBuf;

use anyhow::Context;
use hdrhistogram::Histogram;
use rotorloop_common::clock::{TickGrid, now_ns, sleep_until_ns};
use rotorloop_common::role::args::{
    core, dma_latency_us, duration_s, rate_hz, rt_priority, spin_us,
};
use rotorloop_common::rt::RtSetup;
use rotorloop_common::signals::shutdown_requested;

/// `rotorloop role timer` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct TimerArgs {
    /// Ticks per second, 1 to 100000 Hz.
    #[arg(long, allow_hyphen_values = true, value_parser = rate_hz())]
    pub rate: f64,
    /// Seconds to sleep to the grid, 0.001 to 86400.
    #[arg(long, allow_hyphen_values = true, value_parser = duration_s())]
    pub seconds: f64,
    /// Pin to this core (the plant's), 0 to 4095.
    #[arg(long, allow_hyphen_values = true, value_parser = core())]
    pub core: Option<usize>,
    /// SCHED_FIFO priority (the plant's), 1 to 99.
    #[arg(long, allow_hyphen_values = true, value_parser = rt_priority())]
    pub rt_priority: Option<i32>,
    /// Sleep until this many µs before each tick and spin the rest (the plant's), 0 to
    /// 1000000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 0, value_parser = spin_us())]
    pub spin_before_tick_us: u64,
    /// Hold `/dev/cpu_dma_latency` at this many µs while measuring (cyclictest's default
    /// is 0; the bench holds it itself for the whole invocation instead), 0 to 1000000.
    #[arg(long, allow_hyphen_values = true, value_parser = dma_latency_us())]
    pub cpu_dma_latency: Option<u32>,
    /// Writes `OUT.json` (count, p50, p99, p99.9, max of the lateness, ns) and `OUT.hgrm`.
    #[arg(long)]
    pub out: PathBuf,
}

/// The lateness of every wake-up to the grid (ns, at least 1: a histogram cell), and the
/// `/dev/cpu_dma_latency` limit in force while it was measured (µs; `None`: not readable).
pub fn lateness(a: &TimerArgs) -> anyhow::Result<(Histogram<u64>, Option<u32>)> {
    let rt = RtSetup { core: a.core, rt_priority: a.rt_priority, mlock: false };
    for w in rt.apply("timer") {
        eprintln!("warning: {w}");
    }
    let _idle = rotorloop_common::rt::CpuDmaLatency::hold_or_warn(a.cpu_dma_latency);
    let idle = rotorloop_common::rt::cpu_dma_latency_now();
    let mut h = Histogram::<u64>::new_with_bounds(1, 3_600_000_000_000, 3)?;
    let ticks = (a.seconds * a.rate).round() as u64;
    // As the plant: the grid starts 20 ms from now.
    let grid = TickGrid::new(now_ns() + 20_000_000, 0, a.rate);
    let spin_ns = a.spin_before_tick_us * 1000;
    for k in 0..=ticks {
        if shutdown_requested() {
            break;
        }
        let deadline = grid.at(k);
        sleep_until_ns(deadline, spin_ns);
        h.saturating_record(now_ns().saturating_sub(deadline).max(1));
    }
    Ok((h, idle))
}

/// `rotorloop role timer`: measures and writes `OUT.json` and `OUT.hgrm`.
pub fn run(a: &TimerArgs) -> anyhow::Result<()> {
    let (h, idle) = lateness(a)?;
    let q = |p: f64| h.value_at_quantile(p);
    let j = serde_json::json!({
        "lateness": {
            "count": h.len(),
            "min": h.min(),
            "p50": q(0.5),
            "p99": q(0.99),
            "p99_9": q(0.999),
            "max": h.max(),
        },
        "rate_hz": a.rate,
        "core": a.core,
        "rt_priority": a.rt_priority,
        "cpu_dma_latency_us": idle,
    });
    let json = a.out.with_extension("json");
    std::fs::write(&json, serde_json::to_string_pretty(&j)? + "\n")
        .with_context(|| format!("cannot write {}", json.display()))?;
    rotorloop_common::hgrm::write_hgrm_file(&a.out.with_extension("hgrm"), &h)?;
    Ok(())
}
