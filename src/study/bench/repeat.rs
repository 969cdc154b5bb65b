//! `bench --repeat N`: the median of each ratio over the cell's repetitions, with its
//! confidence interval and verdict ([`crate::study::stats`]), on the loop rows of
//! bench.csv and in bench.md's "Repetitions".

use std::fmt::Write as _;

use super::cell::{RATIOS, Row, ci_columns};
use crate::study::stats::{Interval, Verdict, goal, median_interval};

/// The ratio `name` of repetition `loop_row.repeat`: the loop's p50 or p99 over the
/// baseline's of the same repetition (the timer: the plant's tick lateness over the
/// timer's wake-up lateness; `p50-law`: the loop's p50 less its law's, [`LAWLESS`]).
fn ratio(rows: &[Row], l: &Row, base: &str, q: &str) -> Option<f64> {
    let b = rows.iter().find(|r| r.kind == base && r.repeat == l.repeat && r.skipped.is_empty())?;
    let (num, den) = match (base, q) {
        ("timer", "p50") => (l.lateness_p50, b.p50),
        ("timer", _) => (l.lateness_p99, b.p99),
        (_, "p50") => (l.p50, b.p50),
        (_, "p50-law") => (l.p50 - l.law_p50, b.p50),
        _ => (l.p99, b.p99),
    };
    Some(num / den).filter(|r| r.is_finite())
}

/// The interval of the ratio of `base` at `q` ([`ratio`]) over the repetitions of one
/// cell's `rows`.
fn interval(rows: &[Row], base: &str, q: &str) -> Option<Interval> {
    let loops = rows.iter().filter(|r| r.kind == "loop" && r.skipped.is_empty());
    let v: Vec<f64> = loops.filter_map(|l| ratio(rows, l, base, q)).collect();
    median_interval(&v)
}

/// Each ratio's interval over the repetitions of one cell's `rows`.
pub(super) fn intervals(rows: &[Row]) -> Vec<(&'static str, Option<Interval>)> {
    RATIOS.iter().map(|(name, base, q)| (*name, interval(rows, base, q))).collect()
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

/// The loop over bare iceoryx2 at p50 with the law taken off, per repetition: the loop's
/// sense-to-actuate p50 less its law stage's p50 (the work bare iceoryx2's echo does not
/// do), over the bare round trip's p50 of the same repetition.
pub(super) const LAWLESS: &str = "loop_less_law_over_iceoryx2_p50";

/// [`LAWLESS`]'s interval over the repetitions of one cell's `rows`.
fn lawless(rows: &[Row]) -> Option<Interval> {
    interval(rows, "iceoryx2", "p50-law")
}

/// The goal a ratio is held to (docs/measurements.md): the loop at most bare iceoryx2,
/// the plant's tick lateness at most 1.2 × the timer's.
fn goal_of(name: &str) -> Option<f64> {
    match name {
        n if n.starts_with("loop_over_iceoryx2") || n == LAWLESS => Some(1.0),
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
                 when the whole interval is at or below, or above it; else `undecided`. \
                 `loop_less_law_over_iceoryx2_p50`: the loop's p50 less its law stage's p50 \
                 (the work the bare echo does not do) over bare iceoryx2's (not in bench.csv: \
                 from the runs' summaries).\n\n\
                 | cell | ratio | median | interval | level | repetitions | verdict | goal |\n\
                 |---|---|---|---|---|---|---|---|\n",
            );
        }
        let at = |c: &str| cols.iter().position(|x| x == c).and_then(|i| l.ci.get(i)).cloned();
        let (level, reps) =
            (at("ci_level").unwrap_or_default(), at("repetitions").unwrap_or_default());
        let level: f64 = level.parse().unwrap_or(f64::NAN);
        let of_cell: Vec<Row> = rows.iter().filter(|r| r.cell == l.cell).cloned().collect();
        let extra = lawless(&of_cell).map(|i| (LAWLESS, i));
        let found = RATIOS.iter().filter_map(|(name, _, _)| {
            let num = |s: &str| at(&format!("{name}_{s}")).and_then(|v| v.parse::<f64>().ok());
            let (m, lo, hi) = (num("median")?, num("ci_low")?, num("ci_high")?);
            let verdict = at(&format!("{name}_verdict")).unwrap_or_default();
            Some((*name, m, lo, hi, verdict))
        });
        let extra = extra.map(|(n, i)| (n, i.median, i.low, i.high, Verdict::of(&i).name().into()));
        for (name, m, lo, hi, verdict) in found.chain(extra) {
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The law-less ratio is taken within each repetition, the law's p50 off the loop's,
    /// and bench.md shows it with its goal; a repetition without its bare round trip, or a
    /// loop without its law's figure (a row read back from bench.csv), gives none.
    #[test]
    fn the_loop_less_its_law_is_held_to_bare_iceoryx2_within_each_repetition() {
        let row = |kind: &str, repeat, p50, law_p50| Row {
            cell: "c".into(),
            kind: kind.into(),
            repeat,
            p50,
            law_p50,
            ..Row::default()
        };
        let mut rows: Vec<Row> = (0..3)
            .flat_map(|i| {
                let bare = 4.0 + i as f64;
                [row("loop", i, bare + 1.0 + 0.5, 1.0), row("iceoryx2", i, bare, f64::NAN)]
            })
            .collect();
        let i = lawless(&rows).expect("three repetitions");
        let want = [4.5 / 4.0, 5.5 / 5.0, 6.5 / 6.0];
        assert_eq!((i.low, i.median, i.high), (want[2], want[1], want[0]));
        fill(&mut rows);
        let md = repeat_md(&rows);
        let line =
            md.lines().find(|l| l.starts_with(&format!("| c | {LAWLESS} |"))).expect("its row");
        assert!(line.contains("| 1.10 |") && line.ends_with("≤ 1: missed |"), "{line}");
        rows.retain(|r| !(r.kind == "iceoryx2" && r.repeat == 1));
        assert_eq!(lawless(&rows).map(|i| i.n), Some(2));
        rows.iter_mut().for_each(|r| r.law_p50 = f64::NAN);
        assert!(lawless(&rows).is_none());
    }
}
