//! Writing a run's output files: JSON written whole or not at all, and the summary patched
//! after the run.

use std::path::Path;

use anyhow::Context;
use serde::Serialize;

/// Writes `value` as pretty JSON (a summary), with a trailing newline. All or nothing: it
/// is written to an exclusive temporary beside `path` and renamed into place
/// ([`crate::outdir::OutDir`]: never through a link), so a full disk never leaves a
/// truncated file where a reader expects a whole one.
pub fn write_json(path: &Path, value: &impl Serialize) -> anyhow::Result<()> {
    let text = serde_json::to_string_pretty(value).context("cannot serialise summary")?;
    crate::outdir::write_file(path, text + "\n")
        .with_context(|| format!("cannot write {}", path.display()))
}

/// Changes `out/summary.json` with `change`; nothing when there is no summary (the
/// monitor was stopped early: nothing to add to).
pub fn patch_summary(
    out: &std::path::Path,
    change: impl FnOnce(&mut serde_json::Value),
) -> anyhow::Result<()> {
    let path = out.join("summary.json");
    let Ok(text) = std::fs::read_to_string(&path) else { return Ok(()) };
    let mut j: serde_json::Value = serde_json::from_str(&text)?;
    change(&mut j);
    write_json(&path, &j)
}
