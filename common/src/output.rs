//! Writing a run's output files: JSON written whole or not at all.

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
