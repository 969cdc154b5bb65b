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
    /// How much of the run `run.mcap` holds: `full` every tick's messages (about 1 MB a
    /// second of run at 1 kHz), `overview` one tick a tenth of a second, the extremes of
    /// every tenth of a second (`/rotorloop/window`) and the incidents' ticks at full rate
    /// (docs/foxglove.md); `auto` an overview for a run of an hour or more.
    #[arg(long, value_enum, default_value_t = mcap::Detail::Auto, requires = "mcap")]
    pub detail: mcap::Detail,
    /// Write `DIR/trace.csv` and `DIR/timing.csv` from the flight records (a run made
    /// with `run --no-csv`): the rows its report would have written, byte for byte.
    #[arg(long)]
    pub csv: bool,
}

/// Runs `rotorloop export`.
pub fn run(a: &ExportArgs) -> anyhow::Result<()> {
    if !a.mcap && !a.csv {
        return Err(rotorloop_common::role::UsageError(
            "export: name a format: --mcap or --csv (or both)".into(),
        )
        .into());
    }
    if a.csv {
        csv(&a.dir)?;
    }
    if !a.mcap {
        return Ok(());
    }
    let counts = mcap::write_with(&a.dir, a.detail)?;
    let n: u64 = counts.messages.values().sum();
    println!("{}: {n} messages, {}", counts.path, counts.said());
    for (topic, c) in &counts.messages {
        println!("  {topic:24} {c}");
    }
    Ok(())
}

/// Writes `DIR/trace.csv` and `DIR/timing.csv` from the run's records, a row at a time,
/// each through an exclusive temporary renamed when complete; refuses where either exists.
fn csv(dir: &std::path::Path) -> anyhow::Result<()> {
    use anyhow::Context;
    use rotorloop_monitor::derive::Csv;
    use std::io::Write;
    for c in [Csv::Trace, Csv::Timing] {
        if dir.join(c.name()).exists() {
            return Err(rotorloop_common::role::UsageError(format!(
                "export --csv: {} exists (the run wrote it); remove it to derive it again from \
                 the records",
                dir.join(c.name()).display()
            ))
            .into());
        }
    }
    let mut rows = rotorloop_monitor::derive::DerivedRows::of_run(dir)
        .with_context(|| format!("cannot derive the CSV files of {}", dir.display()))?;
    let out = rotorloop_common::outdir::OutDir::open(dir)?;
    let create = |c: Csv| -> anyhow::Result<_> {
        let path = dir.join(c.name());
        let f = out.atomic(c.name()).with_context(|| format!("cannot write {}", path.display()))?;
        let mut w = std::io::BufWriter::new(f);
        writeln!(w, "{}", c.header())?;
        Ok((w, path))
    };
    let (mut trace, mut timing) = (create(Csv::Trace)?, create(Csv::Timing)?);
    let mut n = 0u64;
    while let Some((t, m)) = rows.next_row() {
        writeln!(trace.0, "{t}")?;
        writeln!(timing.0, "{m}")?;
        n += 1;
    }
    for (w, path) in [trace, timing] {
        let file = w.into_inner().map_err(|e| e.into_error());
        file.and_then(|f| f.commit())
            .with_context(|| format!("cannot write {}", path.display()))?;
        println!("{}: {n} rows", path.display());
    }
    Ok(())
}

/// Writes `OUT/run.mcap` at the end of a run (`rotorloop run`, `rotorloop recover`); a
/// file that cannot be written is a warning, never a failed run.
pub fn mcap_after_run(out: &std::path::Path, quiet: bool) {
    match mcap::write(out) {
        Ok(c) if !quiet => {
            let n = c.messages.values().sum::<u64>();
            println!("mcap: {} ({n} messages, {})", c.path, c.said());
        }
        Ok(_) => {}
        Err(e) => eprintln!("warning: no run.mcap: {e:#}"),
    }
}
