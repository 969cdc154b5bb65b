//! A report's CSV files (`trace.csv`, `timing.csv`) read a row at a time, in tick order,
//! in bounded memory: the readers of a finished run (the replay, the export, the fault
//! report) walk the ticks in order and ask for each tick's row, so one row is held, never
//! the file. A run that wrote no CSV files (`run --no-csv`) has its rows derived from its
//! flight records instead ([`crate::derive::run_rows`]).

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};

use anyhow::Context;

/// A CSV file's lines after its header.
pub type Lines = Box<dyn Iterator<Item = std::io::Result<String>>>;

/// The rows of a CSV file with a `tick` column, in file order (module docs).
pub struct TickRows {
    lines: Lines,
    header: String,
    tick: usize,
    /// The next row not yet handed out: its tick and line.
    ahead: Option<(u64, String)>,
    /// Rows skipped because their tick was not after the row before (out of order or
    /// repeated) or did not parse.
    pub skipped: u64,
    last: Option<u64>,
}

impl std::fmt::Debug for TickRows {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TickRows")
            .field("header", &self.header)
            .field("last", &self.last)
            .field("skipped", &self.skipped)
            .finish_non_exhaustive()
    }
}

impl TickRows {
    /// Opens `path` and reads its header, which must have a `tick` column.
    pub fn open(path: &Path) -> anyhow::Result<Self> {
        let file =
            std::fs::File::open(path).with_context(|| format!("cannot read {}", path.display()))?;
        let mut lines = BufReader::new(file).lines();
        let header = lines
            .next()
            .transpose()
            .with_context(|| format!("cannot read {}", path.display()))?
            .unwrap_or_default();
        Self::of_lines(Box::new(lines), header, &path.display().to_string())
    }

    /// The rows of the lines `lines` under `header` (`what`: the file they stand for, as
    /// errors name it).
    pub fn of_lines(lines: Lines, header: String, what: &str) -> anyhow::Result<Self> {
        let tick = header
            .split(',')
            .position(|c| c == "tick")
            .with_context(|| format!("{what} has no tick column"))?;
        let mut rows = Self { lines, header, tick, ahead: None, skipped: 0, last: None };
        rows.advance();
        Ok(rows)
    }

    /// The header line.
    pub fn header(&self) -> &str {
        &self.header
    }

    /// The column names.
    pub fn columns(&self) -> Vec<String> {
        self.header.split(',').map(str::to_owned).collect()
    }

    /// Reads the next row whose tick comes after the last one's into `ahead`.
    fn advance(&mut self) {
        self.ahead = None;
        for line in self.lines.by_ref() {
            let Ok(line) = line else {
                self.skipped += 1;
                continue;
            };
            let tick = line.split(',').nth(self.tick).and_then(|t| t.parse::<u64>().ok());
            match tick {
                Some(k) if self.last.is_none_or(|l| k > l) => {
                    self.last = Some(k);
                    self.ahead = Some((k, line));
                    return;
                }
                _ => self.skipped += 1,
            }
        }
    }

    /// The next row: its tick and line.
    pub fn next_row(&mut self) -> Option<(u64, String)> {
        let row = self.ahead.take();
        if row.is_some() {
            self.advance();
        }
        row
    }

    /// The tick of the next row, without taking it.
    pub fn peek_tick(&self) -> Option<u64> {
        self.ahead.as_ref().map(|(k, _)| *k)
    }

    /// Passes over the rows of ticks up to `k`.
    pub fn skip_through(&mut self, k: u64) {
        while self.peek_tick().is_some_and(|t| t <= k) {
            self.next_row();
        }
    }

    /// The row of tick `k`, the rows before it passed over (a reader asks for ticks in
    /// increasing order; a tick asked for again after its row was taken gives `None`).
    pub fn row(&mut self, k: u64) -> Option<String> {
        if let Some(before) = k.checked_sub(1) {
            self.skip_through(before);
        }
        if self.peek_tick() == Some(k) { self.next_row().map(|(_, l)| l) } else { None }
    }
}

/// Where the flight records of the run in `dir` are: `dir/flight`, or where its summary
/// says they were left (`run --record DIR`).
pub fn records_dir(dir: &Path, summary: Option<&crate::summary::Summary>) -> PathBuf {
    use rotorloop_common::flight::Stream;
    let kept = dir.join("flight");
    if Stream::PlantState.path(&kept).exists() {
        return kept;
    }
    summary
        .and_then(|s| s.flight.as_ref())
        .map(|f| f.dir.clone())
        .filter(|d| Stream::PlantState.path(d).exists())
        .unwrap_or(kept)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_come_in_tick_order_one_at_a_time_and_disorder_is_skipped() {
        let dir = std::env::temp_dir().join(format!("rotorloop-rows-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("t.csv");
        std::fs::write(&path, "t,tick,x\n0,0,a\n0,1,b\n0,1,dup\n0,x,bad\n0,3,c\n0,2,late\n0,5,d\n")
            .expect("write");
        let mut rows = TickRows::open(&path).expect("open");
        assert_eq!(rows.header(), "t,tick,x");
        assert_eq!(rows.row(1).as_deref(), Some("0,1,b"));
        assert_eq!(rows.row(2), None);
        assert_eq!(rows.row(3).as_deref(), Some("0,3,c"));
        assert_eq!(rows.next_row(), Some((5, "0,5,d".to_owned())));
        assert_eq!(rows.next_row(), None);
        assert_eq!(rows.skipped, 3);
        assert!(TickRows::open(&dir.join("none.csv")).is_err());
        std::fs::write(&path, "a,b\n").expect("write");
        assert!(TickRows::open(&path).is_err_and(|e| e.to_string().contains("no tick column")));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
