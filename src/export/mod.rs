//! `rotorloop export`: a finished run in the formats other tools read. `--mcap` writes
//! `run.mcap` ([`mcap`]), which `rotorloop run` also writes at the end of every run.

pub mod mcap;
pub mod topics;
pub mod wire;

use std::path::PathBuf;

use clap::Args;

/// `rotorloop export` arguments.
#[derive(Debug, Clone, Args)]
pub struct ExportArgs {
    /// The run directory (the `--out` of `rotorloop run`), also of a run made before
    /// `run.mcap` existed.
    pub dir: PathBuf,
    /// Write `DIR/run.mcap` (Foxglove, Lichtblick: docs/foxglove.md).
    #[arg(long)]
    pub mcap: bool,
}

/// Runs `rotorloop export`.
pub fn run(a: &ExportArgs) -> anyhow::Result<()> {
    if !a.mcap {
        return Err(rotorloop_common::role::UsageError(
            "export: name a format: --mcap (the only one so far)".into(),
        )
        .into());
    }
    let counts = mcap::write(&a.dir)?;
    let n: u64 = counts.messages.values().sum();
    println!("{}: {n} messages", counts.path);
    for (topic, c) in &counts.messages {
        println!("  {topic:24} {c}");
    }
    Ok(())
}

/// Writes `OUT/run.mcap` at the end of a run (`rotorloop run`, `rotorloop recover`); a
/// file that cannot be written is a warning, never a failed run.
pub fn mcap_after_run(out: &std::path::Path, quiet: bool) {
    match mcap::write(out) {
        Ok(c) if !quiet => {
            println!("mcap: {} ({} messages)", c.path, c.messages.values().sum::<u64>());
        }
        Ok(_) => {}
        Err(e) => eprintln!("warning: no run.mcap: {e:#}"),
    }
}
