//! `rotorloop doctor`: what this machine allows a real-time loop. Each item says what it
//! is here, what it means for a loop at a given rate, and the command that changes it:
//! CPUs, scheduling (whether `SCHED_FIFO` works, tried in a child, and why not), timers
//! and idle states, memory, interference. `run` and `bench` write its JSON
//! (`doctor.json`) into their output directory, so every figure says on what machine
//! state it was taken.
//!
//! - [`probe`]: what only a system call can say (the CPU set, a `SCHED_FIFO` tried in a
//!   child, the limits, `/dev/cpu_dma_latency`, `/dev/shm`'s free space): a plain
//!   struct, so that tests give it refusals of their own;
//! - [`checks`]: the items, from a [`probe::Probe`] and the `/proc` and `/sys` files under
//!   a root (`/` here; a fixture in tests).

pub mod checks;
pub mod probe;

use std::path::{Path, PathBuf};

use clap::Args;

/// `rotorloop doctor` arguments.
#[derive(Debug, Clone, Args)]
pub struct DoctorArgs {
    /// Print JSON (what `run` and `bench` write as `doctor.json`).
    #[arg(long)]
    pub json: bool,
    /// The loop's tick rate the meanings are stated for (Hz), 1 to 100000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 1000.0,
          value_parser = rotorloop_common::role::args::rate_hz())]
    pub rate: f64,
    /// The run's length the `/dev/shm` need is stated for (seconds), 0.001 to 86400.
    #[arg(long, allow_hyphen_values = true, default_value_t = 60.0,
          value_parser = rotorloop_common::role::args::duration_s())]
    pub seconds: f64,
    /// The CPUs a run would use (`run --cpus`), whose IRQs are counted (default: the
    /// process's CPU set).
    #[arg(long, allow_hyphen_values = true, value_name = "LIST")]
    pub cpus: Option<String>,
}

/// One finding.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Item {
    /// `cpus`, `scheduling`, `timers`, `memory` or `interference`.
    pub group: &'static str,
    /// What is looked at (`sched_fifo`, `cpuidle`, …).
    pub name: &'static str,
    /// What it is on this machine.
    pub value: String,
    /// What it means for a loop at the rate asked.
    pub meaning: String,
    /// The command that changes it (empty: nothing to change).
    pub fix: String,
    /// Whether it is as a real-time loop wants it.
    pub ok: bool,
}

/// Everything the doctor found.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Report {
    /// The rate the meanings are stated for (Hz).
    pub rate_hz: f64,
    /// The findings, grouped in order.
    pub items: Vec<Item>,
}

impl Report {
    /// The item named `name`.
    pub fn item(&self, name: &str) -> Option<&Item> {
        self.items.iter().find(|i| i.name == name)
    }

    /// Text: a line per item, what it means and the fix indented below.
    pub fn text(&self) -> String {
        let mut s = format!("rotorloop doctor: this machine for a loop at {} Hz\n", self.rate_hz);
        let mut group = "";
        for i in &self.items {
            if i.group != group {
                group = i.group;
                s.push_str(&format!("\n{group}\n"));
            }
            let mark = if i.ok { "ok " } else { "!! " };
            s.push_str(&format!("  {mark}{}: {}\n      {}\n", i.name, i.value, i.meaning));
            if !i.fix.is_empty() {
                s.push_str(&format!("      change: {}\n", i.fix));
            }
        }
        s
    }
}

/// The doctor of this machine for a run at `rate_hz` of `seconds` on `cpus` (the
/// process's CPU set when `None`).
pub fn examine(rate_hz: f64, seconds: f64, cpus: Option<&[usize]>) -> Report {
    let probe = probe::Probe::this_process(rate_hz, seconds, cpus);
    checks::report(Path::new("/"), &probe, rate_hz)
}

/// Writes `doctor.json` of a run at `rate_hz` of `seconds` on `cpus` into `out`; a
/// failure is a warning (the run goes on).
pub fn write_into(out: &Path, rate_hz: f64, seconds: f64, cpus: Option<&[usize]>) -> PathBuf {
    let path = out.join("doctor.json");
    let report = examine(rate_hz, seconds, cpus);
    let text = serde_json::to_string_pretty(&report).unwrap_or_default() + "\n";
    if let Err(e) = rotorloop_common::outdir::write_file(&path, text) {
        eprintln!("warning: cannot write {}: {e}", path.display());
    }
    path
}

/// `rotorloop doctor`.
pub fn run(a: &DoctorArgs) -> anyhow::Result<()> {
    let cpus = a
        .cpus
        .as_deref()
        .map(|l| crate::cpus::run_topology(Some(l)).map(|t| t.allowed))
        .transpose()?;
    let report = examine(a.rate, a.seconds, cpus.as_deref());
    match a.json {
        true => println!("{}", serde_json::to_string_pretty(&report)?),
        false => print!("{}", report.text()),
    }
    Ok(())
}

/// The lines of a `doctor.json` that matter to a measurement (the items not as a
/// real-time loop wants them), for bench.md.
pub fn quoted_lines(path: &Path) -> Vec<String> {
    let Ok(text) = std::fs::read_to_string(path) else { return Vec::new() };
    let Ok(j) = serde_json::from_str::<serde_json::Value>(&text) else { return Vec::new() };
    j["items"]
        .as_array()
        .into_iter()
        .flatten()
        .filter(|i| i["ok"].as_bool() == Some(false))
        .map(|i| {
            format!(
                "{}: {} ({})",
                i["name"].as_str().unwrap_or("?"),
                i["value"].as_str().unwrap_or("?"),
                i["meaning"].as_str().unwrap_or("")
            )
        })
        .collect()
}
