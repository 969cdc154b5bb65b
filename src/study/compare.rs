//! `rotorloop compare A B`: two run or bench directories side by side. Two runs: their
//! figures and the ratio B / A, said to be single measurements (no interval). Two
//! benches: per cell and measurement, the median over repetitions of each side with its
//! interval ([`crate::study::stats`]) and whether the intervals are apart, and the
//! loop / baseline ratios each bench gave with their intervals.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use clap::Args;
use rotorloop_common::role::UsageError;
use rotorloop_monitor::latency::Hop;
use rotorloop_monitor::summary::{Summary, SummaryError};

use crate::study::bench::cell::{RATIOS, Row, ci_columns};
use crate::study::stats::{Interval, median_interval};

/// `rotorloop compare` arguments.
#[derive(Debug, Clone, Args)]
pub struct CompareArgs {
    /// The first run or bench directory (A).
    pub a: PathBuf,
    /// The second (B), of the same kind.
    pub b: PathBuf,
}

/// What a directory holds.
enum Side {
    Run(Box<Summary>),
    Bench(Vec<Row>),
}

fn side(dir: &Path) -> Result<Side, UsageError> {
    if let Ok(text) = std::fs::read_to_string(dir.join("bench.csv")) {
        return Ok(Side::Bench(text.lines().skip(1).filter_map(Row::parse).collect()));
    }
    match Summary::read(dir) {
        Ok(s) => Ok(Side::Run(Box::new(s))),
        Err(e @ SummaryError::NotASummary(..)) => Err(UsageError(format!("compare: {e}"))),
        Err(SummaryError::Read(..)) => Err(UsageError(format!(
            "compare: {} is not allowed: a run directory (summary.json) or a bench directory \
             (bench.csv)",
            dir.display()
        ))),
    }
}

/// `rotorloop compare`.
pub fn run(a: &CompareArgs) -> anyhow::Result<()> {
    let text = match (side(&a.a)?, side(&a.b)?) {
        (Side::Run(x), Side::Run(y)) => runs(&x, &y),
        (Side::Bench(x), Side::Bench(y)) => benches(&x, &y),
        _ => {
            return Err(UsageError(format!(
                "compare: {} and {} are not allowed together: two runs or two benches",
                a.a.display(),
                a.b.display()
            ))
            .into());
        }
    };
    print!("# rotorloop compare\n\nA: {}\nB: {}\n{text}", a.a.display(), a.b.display());
    Ok(())
}

/// Two runs' figures side by side.
fn runs(x: &Summary, y: &Summary) -> String {
    let mut md = String::from(
        "\nOne run on each side: no interval can be given, and a difference may be the \
         variation between two runs of one loop (`bench --repeat N` or `bench --before-after \
         … --pairs N` measure it).\n\n| figure | A | B | B / A |\n|---|---|---|---|\n",
    );
    type Figure = fn(&Summary) -> Option<f64>;
    let figures: [(&str, Figure, f64); 7] = [
        ("sense-to-actuate p50 (µs)", |s| s.hop(Hop::SenseToActuate).p50, 1e-3),
        ("sense-to-actuate p99 (µs)", |s| s.hop(Hop::SenseToActuate).p99, 1e-3),
        ("sense-to-actuate p99.9 (µs)", |s| s.hop(Hop::SenseToActuate).p99_9, 1e-3),
        ("tick lateness p50 (µs)", |s| s.hop(Hop::TickLateness).p50, 1e-3),
        ("tick lateness p99 (µs)", |s| s.hop(Hop::TickLateness).p99, 1e-3),
        ("misses", |s| s.misses.map(|m| m as f64), 1.0),
        ("achieved rate (Hz)", |s| s.achieved_rate_hz, 1.0),
    ];
    for (name, figure, scale) in figures {
        let get = |s: &Summary| figure(s).map_or(f64::NAN, |v| v * scale);
        let (a, b) = (get(x), get(y));
        let _ = writeln!(md, "| {name} | {a:.2} | {b:.2} | {:.3} |", b / a);
    }
    md
}

fn shown(i: &Option<Interval>) -> String {
    match i {
        Some(i) if i.n > 1 => {
            let (level, n) = (100.0 * i.level, i.n);
            format!("{:.2} [{:.2}, {:.2}] ({n} runs, {level:.1} %)", i.median, i.low, i.high)
        }
        Some(i) => format!("{:.2} (one run)", i.median),
        None => "—".to_owned(),
    }
}

/// Whether two medians' intervals say the two differ: apart, or overlapping; with a single
/// measurement on a side, that said plainly.
fn apart(x: &Option<Interval>, y: &Option<Interval>) -> &'static str {
    match (x, y) {
        (Some(a), Some(b)) if a.n > 1 && b.n > 1 => match (b.high < a.low, b.low > a.high) {
            (true, _) => "B lower (intervals apart)",
            (_, true) => "B higher (intervals apart)",
            _ => "indistinguishable (intervals overlap)",
        },
        (Some(_), Some(_)) => "no interval (a single measurement on a side)",
        _ => "",
    }
}

/// Two benches: each measurement of each cell both have, and the ratios with intervals.
fn benches(x: &[Row], y: &[Row]) -> String {
    let mut md = String::from(
        "\nEach measurement's median over its bench's repetitions with its interval \
         (`study::stats`), A beside B.\n\n| cell | kind | figure | A | B | B / A of medians | \
         intervals |\n|---|---|---|---|---|---|---|\n",
    );
    let mut keys: Vec<(String, String)> = Vec::new();
    for r in x.iter().filter(|r| r.skipped.is_empty()) {
        let k = (r.cell.clone(), r.kind.clone());
        if !keys.contains(&k)
            && y.iter().any(|s| s.cell == k.0 && s.kind == k.1 && s.skipped.is_empty())
        {
            keys.push(k);
        }
    }
    for (cell, kind) in &keys {
        for (fig, f) in
            [("p50 µs", (|r: &Row| r.p50) as fn(&Row) -> f64), ("p99 µs", |r: &Row| r.p99)]
        {
            let of = |rows: &[Row]| {
                let v: Vec<f64> = rows
                    .iter()
                    .filter(|r| &r.cell == cell && &r.kind == kind && r.skipped.is_empty())
                    .map(f)
                    .collect();
                median_interval(&v)
            };
            let (a, b) = (of(x), of(y));
            let ratio = match (&a, &b) {
                (Some(a), Some(b)) => format!("{:.3}", b.median / a.median),
                _ => String::new(),
            };
            let _ = writeln!(
                md,
                "| {cell} | {kind} | {fig} | {} | {} | {ratio} | {} |",
                shown(&a),
                shown(&b),
                apart(&a, &b)
            );
        }
    }
    md.push_str(&ratio_intervals(x, y));
    md
}

/// The loop / baseline ratios each bench gave (`--repeat`), with their intervals.
fn ratio_intervals(x: &[Row], y: &[Row]) -> String {
    let cols = ci_columns();
    let first = |rows: &[Row], cell: &str| {
        rows.iter().find(|r| r.cell == cell && r.kind == "loop").cloned()
    };
    let mut md = String::new();
    let mut cells: Vec<&str> =
        x.iter().filter(|r| r.kind == "loop").map(|r| r.cell.as_str()).collect();
    cells.dedup();
    for cell in cells {
        let (Some(a), Some(b)) = (first(x, cell), first(y, cell)) else { continue };
        for (name, _, _) in RATIOS {
            let of = |r: &Row| {
                let at = |s: &str| {
                    cols.iter()
                        .position(|c| *c == format!("{name}_{s}"))
                        .and_then(|i| r.ci.get(i))
                        .and_then(|v| v.parse::<f64>().ok())
                };
                match (at("median"), at("ci_low"), at("ci_high")) {
                    (Some(m), Some(l), Some(h)) => format!("{m:.2} [{l:.2}, {h:.2}]"),
                    _ => "no repetitions".to_owned(),
                }
            };
            let (sa, sb) = (of(&a), of(&b));
            if sa == "no repetitions" && sb == "no repetitions" {
                continue;
            }
            if md.is_empty() {
                md.push_str("\nRatios with their intervals (`bench --repeat`):\n\n| cell | ratio | A | B |\n|---|---|---|---|\n");
            }
            let _ = writeln!(md, "| {cell} | {name} | {sa} | {sb} |");
        }
    }
    md
}
