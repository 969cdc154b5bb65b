//! `bench --repeat N`: the median of each ratio over the cell's repetitions, with its
//! confidence interval and verdict ([`crate::study::stats`]), on the loop rows of
//! bench.csv and in bench.md's "Repetitions".

use std::fmt::Write as _;

use super::cell::{RATIOS, Row, ci_columns};
use crate::study::stats::{Interval, Verdict, goal, median_interval};

/// The ratio `name` of repetition `loop_row.repeat`: the loop's p50 or p99 over the
/// baseline's of the same repetition (the timer: the plant's tick lateness over the
/// timer's wake-up lateness).
fn ratio(rows: &[Row], l: &Row, base: &str, q: &str) -> Option<f64> {
    let b = rows.iter().find(|r| r.kind == base && r.repeat == l.repeat && r.skipped.is_empty())?;
    let (num, den) = match (base, q) {
        ("timer", "p50") => (l.lateness_p50, b.p50),
        ("timer", _) => (l.lateness_p99, b.p99),
        (_, "p50") => (l.p50, b.p50),
        _ => (l.p99, b.p99),
    };
    Some(num / den).filter(|r| r.is_finite())
}

/// Each ratio's interval over the repetitions of one cell's `rows`.
pub(super) fn intervals(rows: &[Row]) -> Vec<(&'static str, Option<Interval>)> {
    let loops: Vec<&Row> =
        rows.iter().filter(|r| r.kind == "loop" && r.skipped.is_empty()).collect();
    RATIOS
        .iter()
        .map(|(name, base, q)| {
            let v: Vec<f64> = loops.iter().filter_map(|l| ratio(rows, l, base, q)).collect();
            (*name, median_interval(&v))
        })
        .collect()
}

/// Fills the interval columns of the loop rows of one cell measured more than once.
pub(super) fn fill(rows: &mut [Row]) {
    let reps = rows.iter().filter(|r| r.kind == "loop" && r.skipped.is_empty()).count();
    if reps < 2 {
        return;
    }
    let found = intervals(rows);
    let mut ci = Vec::with_capacity(ci_columns().len());
    let mut level = f64::NAN;
    for (_, i) in &found {
        match i {
            Some(i) => {
                level = if level.is_nan() { i.level } else { level.min(i.level) };
                ci.extend([i.median, i.low, i.high].map(|x| format!("{x:.4}")));
                ci.push(Verdict::of(i).name().to_owned());
            }
            None => ci.extend(std::iter::repeat_n(String::new(), 4)),
        }
    }
    ci.extend([format!("{level:.4}"), reps.to_string()]);
    for r in rows.iter_mut().filter(|r| r.kind == "loop") {
        r.ci = ci.clone();
    }
}

/// The goal a ratio is held to (docs/measurements.md): the loop at most bare iceoryx2,
/// the plant's tick lateness at most 1.2 × the timer's.
fn goal_of(name: &str) -> Option<f64> {
    match name {
        n if n.starts_with("loop_over_iceoryx2") => Some(1.0),
        n if n.starts_with("plant_over_timer") => Some(1.2),
        _ => None,
    }
}

/// bench.md's "Repetitions": per cell and ratio, the median, the interval, its level, the
/// verdict and the goal's.
pub(super) fn repeat_md(rows: &[Row]) -> String {
    let cols = ci_columns();
    let mut md = String::new();
    let mut seen: Vec<&str> = Vec::new();
    for l in rows.iter().filter(|r| r.kind == "loop" && !r.ci.is_empty()) {
        if seen.contains(&l.cell.as_str()) {
            continue;
        }
        seen.push(&l.cell);
        if md.is_empty() {
            md.push_str(
                "\n## Repetitions: each ratio's median with its confidence interval\n\n\
                 The loop and each baseline measured in turn (loop, baselines, loop, …); each \
                 ratio is taken within a repetition, then the median over repetitions with a \
                 distribution-free interval from order statistics (`study::stats`: 95 % from 6 \
                 repetitions; with fewer, the range, at the level said). Verdict: `faster` or \
                 `slower` when the whole interval is below or above 1. Goal: `met` or `missed` \
                 when the whole interval is at or below, or above it; else `undecided`.\n\n\
                 | cell | ratio | median | interval | level | repetitions | verdict | goal |\n\
                 |---|---|---|---|---|---|---|---|\n",
            );
        }
        let at = |c: &str| cols.iter().position(|x| x == c).and_then(|i| l.ci.get(i)).cloned();
        let (level, reps) =
            (at("ci_level").unwrap_or_default(), at("repetitions").unwrap_or_default());
        let level: f64 = level.parse().unwrap_or(f64::NAN);
        for (name, _, _) in RATIOS {
            let num = |s: &str| at(&format!("{name}_{s}")).and_then(|v| v.parse::<f64>().ok());
            let (Some(m), Some(lo), Some(hi)) = (num("median"), num("ci_low"), num("ci_high"))
            else {
                continue;
            };
            let verdict = at(&format!("{name}_verdict")).unwrap_or_default();
            let g = goal_of(name).map_or(String::new(), |g| {
                let i = Interval { median: m, low: lo, high: hi, level, n: 0 };
                format!("≤ {g}: {}", goal(&i, g))
            });
            let _ = writeln!(
                md,
                "| {} | {name} | {m:.2} | [{lo:.2}, {hi:.2}] | {:.1} % | {reps} | {verdict} | {g} |",
                l.cell,
                100.0 * level
            );
        }
    }
    md
}
