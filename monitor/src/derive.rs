//! A run's `trace.csv` and `timing.csv` derived from its flight records, a row at a time:
//! the rows the monitor's report would have written ([`crate::assemble::report`]: the same
//! joining, metrics and formatting), for a run that wrote none (`rotorloop run --no-csv`,
//! a long run's output). `sim --replay`, `export --mcap` and the fault report read them so
//! ([`run_rows`], [`timing_rows`]); `rotorloop export OUT --csv` writes them out.
//! Memory: the records' few blocks and the joiner's ring, whatever the run's length.

use std::path::Path;

use anyhow::Context;

use rotorloop_common::flight::FlightError;
use rotorloop_common::scenario::{Actuation, Scenario};

use crate::assemble::FlightRecords;
use crate::metrics::{Metrics, TraceRow};
use crate::policy::{JoinedRow, RowJoiner};
use crate::recording::{new_metrics, trace_row};
use crate::rows::TickRows;
use crate::timing::{TimingRow, TimingRows};
use crate::trace::TraceWriter;

/// One of a run's two CSV files.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Csv {
    /// `trace.csv`.
    Trace,
    /// `timing.csv`.
    Timing,
}

impl Csv {
    /// The file's name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Trace => "trace.csv",
            Self::Timing => "timing.csv",
        }
    }

    /// The file's header line.
    pub fn header(self) -> String {
        match self {
            Self::Trace => crate::trace::HEADER.to_owned(),
            Self::Timing => crate::timing::header(),
        }
    }
}

/// The rows of a run's trace and timing files from its records (module docs).
#[derive(Debug)]
pub struct DerivedRows {
    records: FlightRecords,
    joiner: RowJoiner,
    metrics: Metrics,
    actuation: Actuation,
    dt: f64,
    /// The next tick to hand to the joiner.
    next: u64,
    /// The newest tick recorded.
    last: u64,
    /// Every tick handed over: what is still open is settled.
    fed: bool,
    line: Vec<u8>,
}

impl DerivedRows {
    /// The rows of the run of `scenario` whose records are in `dir`.
    pub fn open(dir: &Path, scenario: &Scenario) -> Result<Self, FlightError> {
        let records = FlightRecords::read(dir, scenario.ticks())?;
        let start = records.start_ns();
        let last = records.last_tick();
        let (metrics, actuation) = new_metrics(scenario);
        Ok(Self {
            joiner: RowJoiner::for_scenario(scenario, start),
            records,
            metrics,
            actuation,
            dt: scenario.dt(),
            next: 0,
            last,
            fed: false,
            line: Vec::with_capacity(1024),
        })
    }

    /// The rows of the run in `dir`: its records ([`crate::rows::records_dir`]) for the
    /// scenario its `summary.json` says it ran.
    pub fn of_run(dir: &Path) -> anyhow::Result<Self> {
        let summary = crate::summary::Summary::read(dir)
            .context("no summary.json to say what the run's records are of")?;
        let scenario = summary
            .scenario()
            .map_err(anyhow::Error::msg)
            .context("no scenario in its summary.json")?;
        let records = crate::rows::records_dir(dir, Some(&summary));
        Self::open(&records, &scenario).context("its flight records cannot be read")
    }

    /// The records it reads: [`FlightRecords::shared`] gives readers that share its blocks.
    pub fn records(&self) -> &FlightRecords {
        &self.records
    }

    /// The next row: its `trace.csv` line and its `timing.csv` line (without their line
    /// ends), in tick order; `None` after the last.
    pub fn next_row(&mut self) -> Option<(String, String)> {
        let (row, timing) = self.next_pair()?;
        self.line.clear();
        let _ = TraceWriter::append(&mut self.line).write(&row);
        let trace = String::from_utf8_lossy(&self.line).trim_end().to_owned();
        self.line.clear();
        let _ = timing.write(&mut self.line);
        let timing = String::from_utf8_lossy(&self.line).trim_end().to_owned();
        Some((trace, timing))
    }

    /// The next `trace.csv` row as its values, unformatted (the same bits as the line of
    /// [`DerivedRows::next_row`] parsed back: its floats are written round-trip exact), in
    /// tick order; `None` after the last. For a reader of every row that keeps few of
    /// them as text (`export --mcap`).
    pub fn next_trace(&mut self) -> Option<TraceRow> {
        self.next_pair().map(|(row, _)| row)
    }

    /// The next row unformatted: its `trace.csv` values and its `timing.csv` row (as
    /// [`DerivedRows::next_row`]'s lines parse back), in tick order; `None` after the last.
    pub fn next_pair(&mut self) -> Option<(TraceRow, TimingRow)> {
        let j = self.next_joined()?;
        Some((trace_row(&mut self.metrics, self.actuation, self.dt, &j), TimingRow::of(&j.state)))
    }

    fn next_joined(&mut self) -> Option<JoinedRow> {
        loop {
            if let Some(j) = self.joiner.next_row(self.fed) {
                return Some(j);
            }
            if self.fed {
                return None;
            }
            self.records.feed(self.next, &mut self.joiner);
            self.fed = self.next >= self.last;
            self.next += 1;
        }
    }
}

/// The rows of `csv` of the run in `dir`: its file, or, where the run wrote none
/// (`run --no-csv`), the rows derived from its records ([`DerivedRows::of_run`]).
pub fn run_rows(dir: &Path, csv: Csv) -> anyhow::Result<TickRows> {
    let path = dir.join(csv.name());
    if path.exists() {
        return TickRows::open(&path);
    }
    let mut derived = DerivedRows::of_run(dir)
        .with_context(|| format!("no {} in {}", csv.name(), dir.display()))?;
    let lines = std::iter::from_fn(move || {
        derived.next_row().map(|(trace, timing)| match csv {
            Csv::Trace => Ok(trace),
            Csv::Timing => Ok(timing),
        })
    });
    TickRows::of_lines(Box::new(lines), csv.header(), &format!("{} (derived)", path.display()))
}

/// The timing rows of the run in `dir`, from its file or its records ([`run_rows`]).
pub fn timing_rows(dir: &Path) -> anyhow::Result<TimingRows> {
    let csv = Csv::Timing;
    TimingRows::of_rows(run_rows(dir, csv)?, &dir.join(csv.name()))
}
