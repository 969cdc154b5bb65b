//! The bench's files: `bench.md` (the tables with ratios to the baselines, the stage
//! breakdown, before and after, scaling) and the plots, from the rows and their `.hgrm`
//! files.

use std::fmt::Write as _;
use std::path::Path;

use rotorloop_monitor::latency::Hop;
use rotorloop_monitor::plot::{Series, YScale, line_chart};
use rotorloop_monitor::stages::Stage;
use rotorloop_monitor::summary::Summary;

use super::cell::{BenchArgs, Row};

pub(super) fn write_markdown(a: &BenchArgs, rows: &[Row], idle_note: &str) -> anyhow::Result<()> {
    let mut md = format!(
        "# rotorloop bench\n\n{} s per measurement; scenario {}. Loop: sense-to-actuate (plant publishes \
         state k → plant holds torque k), real time. Baselines: paced round trip, one per tick, same \
         placement and wait strategy (atomic: always spin). Latencies in µs. {}\n\n\
         | cell | kind | p50 | p99 | p99.9 | max | misses | achieved Hz | tick lateness p99 | loop/iceoryx2 p50 | loop/iceoryx2 p99.9 | loop/uds p50 | loop/atomic p50 |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
        a.seconds, a.scenario, idle_note
    );
    for r in rows {
        if !r.skipped.is_empty() {
            let _ = writeln!(
                md,
                "| {} | {} | skipped: {} | | | | | | | | | | |",
                r.cell, r.kind, r.skipped
            );
            continue;
        }
        let find =
            |k: &str| rows.iter().find(|x| x.cell == r.cell && x.kind == k && x.skipped.is_empty());
        let ratio = |k: &str, f: fn(&Row) -> f64| {
            if !r.kind.starts_with("loop") {
                return String::new();
            }
            find(k).map_or("—".into(), |b| format!("{:.2}", f(r) / f(b)))
        };
        // Without the monitor nobody counts misses or the achieved rate.
        let (misses, achieved) = if r.kind == "loop-nomon" {
            ("n/a".to_owned(), "n/a".to_owned())
        } else {
            (r.misses.to_string(), format!("{:.3}", r.achieved))
        };
        let _ = writeln!(
            md,
            "| {} | {} | {:.1} | {:.1} | {:.1} | {:.1} | {} | {} | {} | {} | {} | {} | {} |",
            r.cell,
            r.kind,
            r.p50,
            r.p99,
            r.p99_9,
            r.max,
            misses,
            achieved,
            if r.lateness_p99.is_finite() {
                format!("{:.1}", r.lateness_p99)
            } else {
                String::new()
            },
            ratio("iceoryx2", |x| x.p50),
            ratio("iceoryx2", |x| x.p99_9),
            ratio("uds", |x| x.p50),
            ratio("atomic", |x| x.p50),
        );
    }
    if rows.iter().any(|r| r.kind == "loop-nomon") {
        let _ = writeln!(
            md,
            "\n## What the monitor costs\n\nSense-to-actuate p50 measured by the plant itself, \
             with and without the monitor attached (separate runs, same cell).\n"
        );
        for r in rows.iter().filter(|r| r.kind == "loop-nomon" && r.skipped.is_empty()) {
            let with = hgrm_quantile(
                &a.out.join("cells").join(&r.cell).join("loop").join("plant_sense_to_actuate.hgrm"),
                0.5,
            );
            let _ = writeln!(
                md,
                "- {}: {:.1} µs with the monitor, {:.1} µs without ({:+.1} %)",
                r.cell,
                with,
                r.p50,
                100.0 * (with / r.p50 - 1.0)
            );
        }
    }
    md.push_str(&super::repeat::repeat_md(rows));
    md.push_str(&timer_md(rows));
    md.push_str(&controllers_md(rows, a));
    md.push_str(&zero_miss_md(a, rows));
    md.push_str(&breakdown_md(a, rows));
    md.push_str(&before_after_md(rows, a));
    md.push_str(&scale_md(rows, &a.out));
    md.push_str(&cross_host_md(rows));
    rotorloop_common::outdir::write_file(&a.out.join("bench.md"), md)?;
    Ok(())
}

/// Each cross-host measurement beside the same one on one host (`unpinned` if measured,
/// else another placement of this invocation): what the link costs.
pub(super) fn cross_host_md(rows: &[Row]) -> String {
    let measured = |r: &&Row| r.skipped.is_empty() && (r.kind == "loop" || r.kind == "iceoryx2");
    let far: Vec<&Row> =
        rows.iter().filter(measured).filter(|r| r.placement == "cross-host").collect();
    if far.is_empty() {
        return String::new();
    }
    let mut md = String::from(
        "\n## What the link costs (cross-host against one host, this invocation)\n\n\
         `loop`: sense-to-actuate; `iceoryx2`: the bare paced round trip, here through the two \
         gateways. Latencies in µs; error: tracking error over the run (RMS) and at the end \
         (degrees).\n\n\
         | rate | wait | kind | one host (placement) p50 / p99 | cross-host p50 / p99 | p50 ratio \
         | misses one host / cross-host | error RMS one host / cross-host \
         | final error one host / cross-host |\n\
         |---|---|---|---|---|---|---|---|---|\n",
    );
    // A baseline has no tracking error.
    let deg = |v: f64| if v.is_finite() { format!("{v:.1}") } else { "—".to_owned() };
    for f in far {
        let near = rows
            .iter()
            .filter(measured)
            .filter(|r| r.rate == f.rate && r.wait == f.wait && r.kind == f.kind)
            .filter(|r| r.placement != "cross-host" && r.load == f.load)
            .min_by_key(|r| r.placement != "unpinned");
        let Some(n) = near else { continue };
        let _ = writeln!(
            md,
            "| {} | {} | {} | {:.1} / {:.1} ({}) | {:.1} / {:.1} | {:.1} | {} / {} | {} / {} | {} / {} |",
            f.rate,
            f.wait,
            f.kind,
            n.p50,
            n.p99,
            n.placement,
            f.p50,
            f.p99,
            f.p50 / n.p50,
            n.misses,
            f.misses,
            deg(n.err_deg_rms),
            deg(f.err_deg_rms),
            deg(n.err_deg_final),
            deg(f.err_deg_final)
        );
    }
    md
}

/// The highest rate with zero misses, per wait strategy, on one host; across hosts on a
/// line of its own (the link's misses are not a property of the wait strategy).
pub(super) fn zero_miss_md(a: &BenchArgs, rows: &[Row]) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "\n## Highest rate with zero misses (loop)\n");
    let best = |w: &str, far: bool| {
        rows.iter()
            .filter(|r| r.kind == "loop" && r.skipped.is_empty() && r.wait == w && r.misses == 0)
            .filter(|r| (r.placement == "cross-host") == far)
            .map(|r| r.rate)
            .fold(f64::NAN, f64::max)
    };
    let say = |best: f64| match best.is_finite() {
        true => format!("{best} Hz"),
        false => "none of the rates measured".to_owned(),
    };
    let across = rows.iter().any(|r| r.placement == "cross-host" && r.skipped.is_empty());
    for w in &a.wait {
        let w = w.to_string();
        let _ = writeln!(md, "- {w}: {}", say(best(&w, false)));
        if across {
            let _ = writeln!(md, "- {w}, across hosts: {}", say(best(&w, true)));
        }
    }
    md
}

/// The in-loop stages and the notifies, p50 in µs, in tick order.
pub(super) const BREAKDOWN: [(Stage, &str); 13] = [
    (Stage::StateSend, "state send"),
    (Stage::StateDelivery, "state delivery"),
    (Stage::Validate, "validate"),
    (Stage::Pair, "pair"),
    (Stage::Law, "law"),
    (Stage::PublishPrep, "publish prep"),
    (Stage::TorqueSend, "torque send"),
    (Stage::TorqueDelivery, "torque delivery"),
    (Stage::StateNotify, "(state notify)"),
    (Stage::TorqueNotify, "(torque notify)"),
    (Stage::StateLoan, "(state loan)"),
    (Stage::TorqueLoan, "(torque loan)"),
    (Stage::StatePrep, "(plant wake → publish)"),
];

/// The directories a row's run may be in: its repetition's (`--repeat`: the first in the
/// cell's directory, repetition I in `repI`), then, with `--pairs`, each pair's.
fn run_dirs(a: &BenchArgs, r: &Row) -> Vec<std::path::PathBuf> {
    let cell = match r.repeat {
        0 => a.out.join("cells").join(&r.cell),
        i => a.out.join("cells").join(&r.cell).join(format!("rep{i}")),
    };
    let pairs = (1..a.pairs.max(1)).map(|i| cell.join(format!("pair{i}")));
    std::iter::once(cell.clone()).chain(pairs).map(|d| d.join(&r.kind)).collect()
}

/// A row's kind, with its repetition where its cell was measured more than once.
fn labelled(r: &Row) -> String {
    match r.ci.is_empty() {
        true => r.kind.clone(),
        false => format!("{}, repetition {}", r.kind, r.repeat + 1),
    }
}

/// The `summary.json` of the run a row is: with `--pairs`, the pair whose sense-to-actuate
/// p50 is the row's (its median run), else its repetition's.
fn summary_of(a: &BenchArgs, r: &Row) -> Option<Summary> {
    let runs: Vec<Summary> = run_dirs(a, r).iter().filter_map(|d| Summary::read(d).ok()).collect();
    let p50 = |j: &Summary| j.hop(Hop::SenseToActuate).p50;
    let median = runs.iter().position(|j| p50(j).is_some_and(|ns| ns / 1e3 == r.p50));
    runs.into_iter().nth(median.unwrap_or(0))
}

/// The stage p50s (µs) of a loop measurement, from its `summary.json` (`j`).
fn stage_p50s(j: &Summary) -> Option<Vec<f64>> {
    BREAKDOWN.iter().map(|(stage, _)| j.stage(*stage)?.p50.map(|ns| ns / 1e3)).collect()
}

/// Where the microseconds of sense-to-actuate go (`crate` monitor's `stages`).
pub(super) fn breakdown_md(a: &BenchArgs, rows: &[Row]) -> String {
    let mut md = String::from(
        "\n## Where the microseconds go (p50, µs)\n\nSense-to-actuate split at the stamps the plant \
         and the controller carry in their samples; the eight stages add up to it tick by tick \
         (their p50s need not add up to its p50). Notifies run after the send, beside the \
         delivery; a spinning receiver does not wait for them. Loans are taken before the \
         publish stamp (ahead of time, except with `--plain-hot-path`: `loop-plain` rows); the \
         plant's wake → publish comes before sense-to-actuate starts. Compute: the \
         controller's, state received → torque published.\n\n| cell | kind | s2a | compute |",
    );
    for (_, label) in BREAKDOWN {
        let _ = write!(md, " {label} |");
    }
    md.push_str("\n|---|---|---|---|");
    md.push_str(&"---|".repeat(BREAKDOWN.len()));
    md.push('\n');
    for r in
        rows.iter().filter(|r| ["loop", "loop-before", "loop-plain"].contains(&r.kind.as_str()))
    {
        let Some(j) = summary_of(a, r).filter(|_| r.skipped.is_empty()) else { continue };
        let Some(p50s) = stage_p50s(&j) else { continue };
        let compute = j.hop(Hop::ControllerCompute).p50.map_or(f64::NAN, |ns| ns / 1e3);
        let _ = write!(md, "| {} | {} | {:.1} | {compute:.2} |", r.cell, labelled(r), r.p50);
        for v in p50s {
            let _ = write!(md, " {v:.2} |");
        }
        md.push('\n');
    }
    md
}

/// What `bench --before-after CHANGE` compares, in words (its loops: `measure::sides`).
fn described(change: super::cell::BeforeAfter) -> &'static str {
    use super::cell::BeforeAfter;
    match change {
        BeforeAfter::Record => {
            "Before: the loop without flight recorders (`run --no-record`); after: with them \
             (the default)."
        }
        BeforeAfter::Foxglove => {
            "Before: the loop alone; after: with the live Foxglove server (`run --foxglove`) \
             and a viewer subscribed to every topic (on a thread of the bench)."
        }
        BeforeAfter::Sched => {
            "Before: the loop without the launcher's scheduling samples (`run \
             --no-sched-sample`); after: with them (the default: each role's schedstat every \
             1 ms into `sched.csv`)."
        }
        BeforeAfter::TraceSched => {
            "Before: the loop as it is; after: with the kernel's scheduler and IRQ events \
             recorded (`run --trace-sched`, root)."
        }
        BeforeAfter::HotPath => {
            "Before: the hot path as it was before its overhead was cut (`run \
             --plain-hot-path`: the reference woken by every state, the reference topic read \
             every tick, each sample loaned and the plant's state made between its wake-up and \
             its publish); after: as it is."
        }
        BeforeAfter::Pack => {
            "Before: rings of 4096 ticks, the launcher moving each finished half raw (`run \
             --raw-segments`); after: the same, each half packed (the default)."
        }
        BeforeAfter::Gate => {
            "Before: the plant's tick loop without the lockstep fault gate's check (`run \
             --no-gate`, compiled without it); after: with it (the default: one comparison of \
             two integers a tick)."
        }
        BeforeAfter::Journal => {
            "Before: the loop without the journal of the newest ticks (`run --no-journal`); \
             after: with it (the default: every stream's newest ticks appended to \
             `OUT/flight/*.journal` and made durable every 200 ms)."
        }
    }
}

/// The loop before and after its overhead was cut, with the bare baseline of the cell.
pub(super) fn before_after_md(rows: &[Row], a: &BenchArgs) -> String {
    use super::cell::BeforeAfter;
    let Some(change) = a.before_after else { return String::new() };
    let (before, after) = super::measure::sides(change);
    let (before_kind, after_kind, what) = (before.kind(), after.kind(), described(change));
    let mut md = String::new();
    let ok = |cell: &str, kind: &str| {
        rows.iter().find(|r| r.cell == cell && r.kind == kind && r.skipped.is_empty())
    };
    for r in rows.iter().filter(|r| r.kind == after_kind && r.skipped.is_empty()) {
        let (Some(before), bare) = (ok(&r.cell, before_kind), ok(&r.cell, "iceoryx2")) else {
            continue;
        };
        if md.is_empty() {
            md.push_str(&format!(
                "\n## Before and after (same invocation)\n\n{what} Each measured {} time(s), \
                 alternating; each row is the run with the median p50.\n\n| cell | before p50 | \
                 after p50 | change | bare iceoryx2 p50 | before/bare | after/bare | misses \
                 before/after/bare | after p99 | before p99 |\n\
                 |---|---|---|---|---|---|---|---|---|---|\n",
                a.pairs
            ));
        }
        let bare_p50 = bare.map_or(f64::NAN, |b| b.p50);
        let bare_misses = bare.map_or("—".to_owned(), |b| b.misses.to_string());
        let _ = writeln!(
            md,
            "| {} | {:.1} | {:.1} | {:+.0} % | {:.1} | {:.2} | {:.2} | {} / {} / {} | {:.1} | {:.1} |",
            r.cell,
            before.p50,
            r.p50,
            100.0 * (r.p50 / before.p50 - 1.0),
            bare_p50,
            before.p50 / bare_p50,
            r.p50 / bare_p50,
            before.misses,
            r.misses,
            bare_misses,
            r.p99,
            before.p99
        );
    }
    md.push_str(&pair_intervals_md(rows, a, after_kind));
    if change == BeforeAfter::Foxglove {
        for r in rows.iter().filter(|r| r.kind == after_kind && r.skipped.is_empty()) {
            let seen = a.out.join("cells").join(&r.cell).join(after_kind).join("viewer.json");
            let n = std::fs::read_to_string(seen)
                .ok()
                .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
                .and_then(|v| v["messages"].as_u64());
            let said =
                n.map_or("its count was not written".to_owned(), |n| format!("{n} messages"));
            let _ = writeln!(md, "\n{}: the viewer of the first pair received {said}.", r.cell);
        }
    }
    md
}

/// Under the before/after table: each cell's after / before ratios of its pairs at p50
/// and p99, their median, interval and verdict (`before-after.json`).
fn pair_intervals_md(rows: &[Row], a: &BenchArgs, after_kind: &str) -> String {
    let mut md = String::new();
    for r in rows.iter().filter(|r| r.kind == after_kind && r.skipped.is_empty() && r.repeat == 0) {
        let path = a.out.join("cells").join(&r.cell).join("before-after.json");
        let Some(j) = std::fs::read_to_string(path)
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        else {
            continue;
        };
        for q in ["p50", "p99"] {
            let i = &j[format!("after_over_before_{q}")];
            let Some(m) = i["median"].as_f64() else { continue };
            let f = |k: &str| i[k].as_f64().unwrap_or(f64::NAN);
            let _ = writeln!(
                md,
                "\n{}: after / before {q} over {} pair(s): median {m:.3}, interval [{:.3}, {:.3}] at {:.1} %: {}.",
                r.cell,
                j["pairs"],
                f("ci_low"),
                f("ci_high"),
                100.0 * f("level"),
                i["verdict"].as_str().unwrap_or("?")
            );
        }
        let m = &j["misses"];
        if let (Some(b), Some(a)) = (m["before_total"].as_u64(), m["after_total"].as_u64()) {
            let _ = writeln!(
                md,
                "\n{}: misses over {} pair(s): before {b}, after {a}; after more in {} pair(s), \
                 fewer in {}.",
                r.cell, j["pairs"], m["pairs_after_more"], m["pairs_after_fewer"]
            );
        }
    }
    md
}

/// Where the loops of a scale cell ran (`placement.json`, written by the bench): each
/// loop's CPUs, and what was said of SMT and of shared cores.
fn placement_md(out: &Path, cell: &str) -> Option<String> {
    let text = std::fs::read_to_string(out.join("cells").join(cell).join("placement.json")).ok()?;
    let j: serde_json::Value = serde_json::from_str(&text).ok()?;
    let cpus: Vec<String> = j["loops"]
        .as_array()?
        .iter()
        .map(|l| l["cpus"].as_str().unwrap_or("?").to_owned())
        .collect();
    let mut line = format!("- {cell}: CPUs of each loop {}", cpus.join(" | "));
    line.push_str(match j["shared"].as_bool() {
        Some(true) => "; cores shared",
        _ => "; no core carries roles of two loops",
    });
    for n in j["notes"].as_array().into_iter().flatten().filter_map(|n| n.as_str()) {
        let _ = write!(line, ". {n}");
    }
    Some(line + ".\n")
}

/// The median of the rows' misses (the upper one of an even count); `None` without rows.
fn median_misses(rows: &[&Row]) -> Option<u64> {
    let mut m: Vec<u64> = rows.iter().map(|r| r.misses).collect();
    m.sort_unstable();
    m.get(m.len() / 2).copied()
}

/// A scale section's heading: the bare pair's misses (the median where it was measured
/// more than once) and the table's head.
fn scale_heading(cell: &str, bare: &[&Row], alone: &[&Row]) -> String {
    let said = match bare.len() {
        0 => "not measured".to_owned(),
        1 => format!("{} (one pair)", bare[0].misses),
        n => format!(
            "{} (the median of {n} repetitions: {})",
            median_misses(bare).unwrap_or_default(),
            bare.iter().map(|r| r.misses.to_string()).collect::<Vec<_>>().join(", ")
        ),
    };
    format!(
        "\n## Scale: {cell} (loops at once)\n\nBare iceoryx2 misses: {said}.{}\n\n\
         | loops | p50 of each loop (µs) | worst p99 | misses of each loop | all ≤ bare | all ≤ alone |\n\
         |---|---|---|---|---|---|\n",
        match alone.len() {
            0 | 1 => "",
            _ => " The loop alone, measured more than once, counts with the median of its misses.",
        }
    )
}

/// The scale cells: per loop count, the loops' p50s, worst p99 and misses, against the
/// bare baseline's misses and the loop alone's; the largest count at which no loop missed
/// more than each; where each count's loops ran.
pub(super) fn scale_md(rows: &[Row], out: &Path) -> String {
    let mut md = String::new();
    let mut seen: Vec<&str> = Vec::new();
    for base in rows.iter().filter(|r| r.kind == "loop" && r.skipped.is_empty()) {
        // With `--repeat`, the cell's loop and bare pair were measured more than once:
        // one section per cell, its single loop the median of its repetitions.
        if seen.contains(&base.cell.as_str()) {
            continue;
        }
        seen.push(&base.cell);
        let scaled: Vec<(usize, Vec<&Row>)> = (2..=64)
            .map(|n| {
                let cell = format!("{}-x{n}", base.cell);
                (n, rows.iter().filter(|r| r.cell == cell).collect::<Vec<_>>())
            })
            .filter(|(_, rs)| !rs.is_empty())
            .collect();
        if scaled.is_empty() {
            continue;
        }
        let of = |kind: &str| -> Vec<&Row> {
            rows.iter()
                .filter(|r| r.cell == base.cell && r.kind == kind && r.skipped.is_empty())
                .collect()
        };
        let (bare, alone) = (of("iceoryx2"), of("loop"));
        let limit = median_misses(&bare);
        md.push_str(&scale_heading(&base.cell, &bare, &alone));
        // Beside the bare pair, the loop alone: whether more loops make each one worse
        // than one loop on an otherwise idle machine (its most misses over repetitions).
        let alone_most = alone.iter().map(|r| r.misses).max();
        let (mut largest, mut unbroken) = ([None, None], [true, true]);
        let mut all = vec![(1, alone.clone())];
        all.extend(scaled);
        for (n, rs) in &all {
            let measured = rs.iter().all(|r| r.skipped.is_empty());
            let fits = [limit, alone_most].map(|limit| {
                measured
                    && limit.is_some_and(|l| match n {
                        1 => median_misses(rs).is_some_and(|m| m <= l),
                        _ => rs.iter().all(|r| r.misses <= l),
                    })
            });
            let list =
                |f: &dyn Fn(&Row) -> String| rs.iter().map(|r| f(r)).collect::<Vec<_>>().join(", ");
            let worst = rs.iter().map(|r| r.p99).fold(f64::NAN, f64::max);
            let yes = |f: bool| if f { "yes" } else { "no" };
            let _ = writeln!(
                md,
                "| {n} | {} | {worst:.1} | {} | {} | {} |",
                list(&|r| if r.skipped.is_empty() {
                    format!("{:.1}", r.p50)
                } else {
                    r.skipped.clone()
                }),
                list(&|r| r.misses.to_string()),
                yes(fits[0]),
                yes(fits[1]),
            );
            // The largest count up to which every count measured fits.
            for i in 0..2 {
                unbroken[i] &= fits[i];
                if unbroken[i] {
                    largest[i] = Some(*n);
                }
            }
        }
        let said = |n: Option<usize>| match (n, alone.is_empty()) {
            (Some(n), _) => n.to_string(),
            (None, true) => "none measured".into(),
            (None, false) => "none (the loop alone already missed more)".into(),
        };
        let _ = writeln!(
            md,
            "\nLargest number of loops with every loop at or below the bare baseline's misses: {}.\n\
             Largest number of loops with every loop at or below the loop alone's most misses ({}): {}.",
            said(largest[0]),
            alone_most.map_or("not measured".into(), |m| m.to_string()),
            said(largest[1]),
        );
        let placed: Vec<String> = all
            .iter()
            .skip(1)
            .filter_map(|(n, _)| placement_md(out, &format!("{}-x{n}", base.cell)))
            .collect();
        if !placed.is_empty() {
            let _ = write!(
                md,
                "\nPlacement (disjoint core sets from the process's CPU set, isolated CPUs \
                 first, CPU 0 last):\n\n{}",
                placed.concat()
            );
        }
    }
    md
}

/// `(percentile, value µs)` rows of a `.hgrm` file.
pub fn read_hgrm_values(path: &Path) -> Vec<(f64, f64)> {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    text.lines()
        .filter_map(|l| {
            let v: Vec<f64> = l.split_whitespace().filter_map(|x| x.parse().ok()).collect();
            (v.len() >= 3 && !l.starts_with('#')).then(|| (v[1], v[0]))
        })
        .collect()
}

/// The value (µs) at percentile `q` of a `.hgrm` file (`q = 1` is the maximum).
pub(super) fn hgrm_quantile(path: &Path, q: f64) -> f64 {
    read_hgrm_values(path).iter().find(|(p, _)| *p >= q).map_or(f64::NAN, |(_, v)| *v)
}

/// The total count of a `.hgrm` file.
pub(super) fn hgrm_count(path: &Path) -> u64 {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    text.split("Total count    =")
        .nth(1)
        .and_then(|r| r.split(']').next())
        .and_then(|n| n.trim().parse().ok())
        .unwrap_or(0)
}

/// Reads `(log10(1/(1−q)), value µs)` points from a `.hgrm` file.
pub fn read_hgrm(path: &Path) -> Vec<(f64, f64)> {
    read_hgrm_values(path)
        .into_iter()
        .filter(|(q, _)| *q < 1.0)
        .map(|(q, v)| ((1.0 / (1.0 - q)).log10(), v))
        .collect()
}

pub(super) fn plots(a: &BenchArgs, rows: &[Row]) -> anyhow::Result<()> {
    // One chart per placement, rate and wait strategy: the loop and its baselines.
    let mut groups: Vec<(String, f64, String)> = Vec::new();
    for r in rows.iter().filter(|r| r.skipped.is_empty() && r.load == "none") {
        let key = (
            r.placement.clone(),
            r.rate,
            if r.kind == "atomic" { String::new() } else { r.wait.clone() },
        );
        if !key.2.is_empty() && !groups.contains(&key) {
            groups.push(key);
        }
    }
    for (placement, rate, wait) in groups {
        let mut data = Vec::new();
        for r in rows.iter().filter(|r| {
            r.placement == placement
                && r.rate == rate
                && r.skipped.is_empty()
                && r.load == "none"
                && (r.wait == wait || r.kind == "atomic")
        }) {
            let pts =
                read_hgrm(&a.out.join("cells").join(&r.cell).join(format!("{}.hgrm", r.kind)));
            if !pts.is_empty()
                && !data.iter().any(|(l, _): &(String, Vec<(f64, f64)>)| l.starts_with(&r.kind))
            {
                data.push((format!("{} ({})", r.kind, r.wait), pts));
            }
        }
        let series: Vec<Series<'_>> = data
            .iter()
            .map(|(l, p)| Series { label: l, points: p, dashed: !l.starts_with("loop") })
            .collect();
        line_chart(
            &a.out.join(format!("spectrum_{placement}_{rate}hz_{wait}.png")),
            &format!("{placement}, {rate} Hz, {wait}: loop sense-to-actuate vs paced round trips"),
            "log10(1 / (1 - percentile))   (1 = p90, 2 = p99, 3 = p99.9)",
            "µs (log)",
            &series,
            YScale::Log { floor: 0.1 },
        )?;
    }
    let mut per_wait = Vec::new();
    for w in &a.wait {
        let pts: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| r.kind == "loop" && r.skipped.is_empty() && r.wait == w.to_string())
            .map(|r| (r.rate, r.misses as f64 + 0.5))
            .collect();
        per_wait.push((format!("{w} (misses + 0.5)"), pts));
    }
    let series: Vec<Series<'_>> =
        per_wait.iter().map(|(l, p)| Series { label: l, points: p, dashed: false }).collect();
    line_chart(
        &a.out.join("misses_by_rate.png"),
        "loop misses by rate and wait strategy (0.5 = no miss)",
        "rate (Hz)",
        "misses + 0.5 (log)",
        &series,
        YScale::Log { floor: 0.5 },
    )?;
    Ok(())
}

/// The plant's tick lateness beside the `timer` baseline of the same cell (a bare thread
/// sleeping to the same grid on the same core with the same priority): how close the
/// plant's tick is to what the kernel allows.
pub(super) fn timer_md(rows: &[Row]) -> String {
    let measured = |r: &&Row| r.skipped.is_empty();
    let timers: Vec<&Row> = rows.iter().filter(measured).filter(|r| r.kind == "timer").collect();
    if timers.is_empty() {
        return String::new();
    }
    let mut md = String::from(
        "\n## The plant's tick against the timer baseline\n\n\
         Tick lateness: wake-up − grid time (µs). `timer`: a bare thread sleeping to the same \
         absolute grid with the same clock, timer slack, policy, priority, core and spin, in \
         the same invocation (what cyclictest measures). Ratios: plant / timer.\n\n\
         | cell | kind | plant p50 / p99 / p99.9 | timer p50 / p99 / p99.9 | ratio p50 | ratio p99 | ratio p99.9 |\n\
         |---|---|---|---|---|---|---|\n",
    );
    // With `--repeat`, each loop beside the timer of its own repetition.
    let repeated = rows.iter().any(|r| r.repeat > 0);
    for t in timers {
        let loops =
            rows.iter().filter(measured).filter(|r| r.cell == t.cell && r.repeat == t.repeat);
        for l in loops.filter(|r| r.kind.starts_with("loop") && r.lateness_p50.is_finite()) {
            let kind = match repeated {
                true => format!("{}, repetition {}", l.kind, l.repeat + 1),
                false => l.kind.clone(),
            };
            let _ = writeln!(
                md,
                "| {} | {} | {:.1} / {:.1} / {:.1} | {:.1} / {:.1} / {:.1} | {:.2} | {:.2} | {:.2} |",
                t.cell,
                kind,
                l.lateness_p50,
                l.lateness_p99,
                l.lateness_p99_9,
                t.p50,
                t.p99,
                t.p99_9,
                l.lateness_p50 / t.p50,
                l.lateness_p99 / t.p99,
                l.lateness_p99_9 / t.p99_9
            );
        }
    }
    md
}

/// `--controllers`: per cell, the loop with each controller against the bare iceoryx2
/// round trip, with the controller's compute and the law's stage from each run's summary.
pub(super) fn controllers_md(rows: &[Row], a: &BenchArgs) -> String {
    if a.controllers.is_empty() {
        return String::new();
    }
    let mut md = String::from(
        "\n## What each controller costs the loop\n\nThe same cell with the built-in geometric \
         PID (`loop`), the second law (`loop-mrp-pid`: Basilisk's MRP feedback) and the Python \
         example through `run --controller-cmd` (`loop-python`) and the C example against the \
         C API (`loop-c`), in the same invocation. \
         Sense-to-actuate and the controller's compute (state received to torque published) \
         and its law stage, µs.\n\n\
         | cell | controller | sense-to-actuate p50 / p99 | / bare iceoryx2 p50 | compute p50 / p99 | law p50 | misses |\n\
         |---|---|---|---|---|---|---|\n",
    );
    let us = |v: Option<f64>| v.map_or(f64::NAN, |ns| ns / 1e3);
    for r in rows
        .iter()
        .filter(|r| ["loop", "loop-mrp-pid", "loop-python", "loop-c"].contains(&r.kind.as_str()))
    {
        if !r.skipped.is_empty() {
            let _ = writeln!(md, "| {} | {} | skipped: {} | | | | |", r.cell, r.kind, r.skipped);
            continue;
        }
        let bare = rows.iter().find(|b| {
            b.cell == r.cell && b.repeat == r.repeat && b.kind == "iceoryx2" && b.skipped.is_empty()
        });
        let ratio = bare.map_or("—".to_owned(), |b| format!("{:.2}", r.p50 / b.p50));
        let s = summary_of(a, r).unwrap_or_default();
        let compute = s.hop(Hop::ControllerCompute);
        let law = us(s.stage(Stage::Law).and_then(|l| l.p50));
        let _ = writeln!(
            md,
            "| {} | {} | {:.1} / {:.1} | {ratio} | {:.1} / {:.1} | {:.2} | {} |",
            r.cell,
            labelled(r),
            r.p50,
            r.p99,
            us(compute.p50),
            us(compute.p99),
            law,
            r.misses
        );
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    /// With `--repeat`, each loop row stands beside the timer of its own repetition: one
    /// row per repetition, its ratio that repetition's (it was every loop against every
    /// timer, N² rows, on the 16-core machine's first `--repeat 6`).
    #[test]
    fn each_repetitions_loop_is_set_beside_its_own_timer() {
        let row = |kind: &str, repeat: usize, p50: f64, lateness_p50: f64| Row {
            cell: "c".into(),
            kind: kind.into(),
            p50,
            p99: 1.0,
            p99_9: 1.0,
            lateness_p50,
            lateness_p99: 1.0,
            lateness_p99_9: 1.0,
            repeat,
            ..Row::default()
        };
        let rows: Vec<Row> = (0..3)
            .flat_map(|r| {
                let t = 10.0 * (r + 1) as f64;
                [row("loop", r, f64::NAN, 2.0 * t), row("timer", r, t, f64::NAN)]
            })
            .collect();
        let md = timer_md(&rows);
        let lines: Vec<&str> = md.lines().filter(|l| l.starts_with("| c |")).collect();
        assert_eq!(lines.len(), 3, "{md}");
        for (r, line) in lines.iter().enumerate() {
            assert!(line.contains(&format!("loop, repetition {}", r + 1)), "{line}");
            assert!(line.contains("| 2.00 |"), "every ratio 2: {line}");
        }
        let once = timer_md(&rows[..2]);
        assert!(once.contains("| c | loop | 20.0"), "{once}");
    }

    /// With `--repeat`, each repetition's row of "Where the microseconds go" and of "What
    /// each controller costs" holds the figures of its own run (`repI`), the latter over
    /// its own repetition's bare round trip: every row held the first repetition's (the
    /// 16-core machine's `--repeat 6`, 2026-11-30: six rows, one set of stages).
    #[test]
    fn each_repetitions_stages_are_its_own_runs() {
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            a: BenchArgs,
        }
        let dir = tempfile::tempdir().expect("tempdir");
        let out = dir.path().to_str().expect("utf-8");
        let a = <Cli as clap::Parser>::parse_from(["bench", "--out", out, "--controllers", "c"]).a;
        let mut rows = Vec::new();
        for rep in 0..3 {
            let run = match rep {
                0 => dir.path().join("cells/c/loop"),
                r => dir.path().join(format!("cells/c/rep{r}/loop")),
            };
            std::fs::create_dir_all(&run).expect("run dir");
            let law_ns = 100 * (rep + 1);
            let stages: Vec<serde_json::Value> = BREAKDOWN
                .iter()
                .map(|(st, _)| {
                    let p50 = if *st == Stage::Law { law_ns } else { 10 };
                    serde_json::json!({"stage": st.name(), "p50": p50})
                })
                .collect();
            let j = serde_json::json!({"hops": {"sense_to_actuate": {"p50": 4000 + rep}},
                                       "stages": stages});
            std::fs::write(run.join("summary.json"), j.to_string()).expect("summary");
            rows.push(Row {
                cell: "c".into(),
                kind: "loop".into(),
                p50: (4000 + rep) as f64 / 1e3,
                repeat: rep,
                ci: vec!["1".into()],
                ..Row::default()
            });
            let bare_p50 = (rep + 1) as f64;
            rows.push(Row {
                cell: "c".into(),
                kind: "iceoryx2".into(),
                p50: bare_p50,
                repeat: rep,
                ..Row::default()
            });
        }
        let md = breakdown_md(&a, &rows);
        let lines: Vec<&str> = md.lines().filter(|l| l.starts_with("| c |")).collect();
        assert_eq!(lines.len(), 3, "{md}");
        for (rep, line) in lines.iter().enumerate() {
            assert!(line.contains(&format!("loop, repetition {}", rep + 1)), "{line}");
            let law = format!("| {:.2} |", 0.1 * (rep + 1) as f64);
            assert!(line.contains(&law), "repetition {rep}'s law {law}: {line}");
        }
        // "What each controller costs": each repetition's law, and its own bare round trip.
        let md = controllers_md(&rows, &a);
        let lines: Vec<&str> = md.lines().filter(|l| l.starts_with("| c |")).collect();
        assert_eq!(lines.len(), 3, "{md}");
        for (rep, (line, ratio)) in lines.iter().zip(["4.00", "2.00", "1.33"]).enumerate() {
            assert!(line.contains(&format!("loop, repetition {}", rep + 1)), "{line}");
            assert!(line.contains(&format!("| {ratio} |")), "over its own bare: {line}");
            let law = format!("| {:.2} |", 0.1 * (rep + 1) as f64);
            assert!(line.contains(&law), "repetition {rep}'s law {law}: {line}");
        }
    }

    /// With `--repeat`, a scale cell gets one section, the bare pair's limit the median
    /// of its repetitions (one disturbed repetition does not set it) and the loop alone
    /// its median; each count is also held to the loop alone's most misses.
    #[test]
    fn a_repeated_scale_cell_has_one_section_held_to_medians() {
        let row = |cell: &str, kind: &str, repeat: usize, misses: u64| Row {
            cell: cell.into(),
            kind: kind.into(),
            repeat,
            misses,
            ..Row::default()
        };
        let mut rows = Vec::new();
        for (r, (bare, alone)) in [(280, 8), (5, 4), (6, 9)].into_iter().enumerate() {
            rows.push(row("c", "loop", r, alone));
            rows.push(row("c", "iceoryx2", r, bare));
        }
        rows.extend([row("c-x2", "loop-1", 0, 6), row("c-x2", "loop-2", 0, 5)]);
        rows.extend(
            (1..=4).map(|i| row("c-x4", &format!("loop-{i}"), 0, if i == 3 { 9 } else { 1 })),
        );
        rows.extend((1..=8).map(|i| row("c-x8", &format!("loop-{i}"), 0, 10)));
        let md = scale_md(&rows, Path::new("/nonexistent"));
        assert_eq!(md.matches("## Scale: c ").count(), 1, "{md}");
        assert!(
            md.contains("Bare iceoryx2 misses: 6 (the median of 3 repetitions: 280, 5, 6)"),
            "{md}"
        );
        assert!(md.contains("| 1 | 0.0, 0.0, 0.0 | 0.0 | 8, 4, 9 | no | yes |"), "{md}");
        assert!(md.contains("| 2 | 0.0, 0.0 | 0.0 | 6, 5 | yes | yes |"), "{md}");
        assert!(md.contains("| 4 |"), "{md}");
        assert!(md.contains("| 1, 1, 9, 1 | no | yes |"), "{md}");
        assert!(md.contains("| 10, 10, 10, 10, 10, 10, 10, 10 | no | no |"), "{md}");
        assert!(md.contains("bare baseline's misses: none (the loop alone already"), "{md}");
        assert!(md.contains("the loop alone's most misses (9): 4."), "{md}");
    }
}
