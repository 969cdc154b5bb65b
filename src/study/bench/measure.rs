//! Measuring a cell: the loop through the four processes (also before and after its
//! flight recorders, and scaled to several loops), and each baseline with the same
//! placement, wait and pacing.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::Context;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::ipc::wait::Wait;
use rotorloop_monitor::latency::Hop;
use rotorloop_monitor::summary::Summary;

use super::cell::{BeforeAfter, BenchArgs, Row, cores, skip_reason};
use super::report::{hgrm_count, hgrm_quantile};
use crate::baseline::pingpong::Kind;
use crate::cpus::{LoopCores, Shape, Topology, place};
use crate::run::args::RunArgs;
use rotorloop_common::role::args::RoleArgs;

/// The loop rows of a cell: the loop, and what `--monitor-cost`, `--controllers` and
/// `--before-after` add (the plain loop's row first).
pub(super) fn measure_loop_variants(
    a: &BenchArgs,
    base: &Row,
    t: &Topology,
    dir: &Path,
) -> anyhow::Result<Vec<Row>> {
    let mut measured = vec![measure_loop(a, base, t, dir, Variant::Loop)?];
    if a.monitor_cost {
        measured.push(measure_loop(a, base, t, dir, Variant::NoMonitor)?);
    }
    for c in &a.controllers {
        measured.push(measure_loop(a, base, t, dir, Variant::of_controller(c))?);
    }
    if let Some(change) = a.before_after {
        let (plain, other) = before_after(a, change, base, t, dir, measured.remove(0))?;
        measured.insert(0, plain);
        measured.push(other);
    }
    Ok(measured)
}

/// `--before-after`: the loop before and after `change`, `--pairs` times each,
/// alternating (`first`, the plain loop already measured, is the first of its side); the
/// median run of each side: the plain loop's (`loop`) first, then the other.
pub(super) fn before_after(
    a: &BenchArgs,
    change: BeforeAfter,
    base: &Row,
    t: &Topology,
    dir: &Path,
    first: Row,
) -> anyhow::Result<(Row, Row)> {
    let (b, f) = sides(change);
    // The plain loop already measured is the first run of its side (of neither for
    // `pack`: both sides run small rings).
    let plain_after = f == Variant::Loop;
    let (mut before, mut after) = (Vec::new(), Vec::new());
    match (change, plain_after) {
        (BeforeAfter::Pack, _) => {}
        (_, true) => after.push(first),
        (_, false) => before.push(first),
    }
    for i in 0..a.pairs as usize {
        let d = if i == 0 { dir.to_owned() } else { dir.join(format!("pair{i}")) };
        if before.len() <= i {
            before.push(measure_loop(a, base, t, &d, b)?);
        }
        if after.len() <= i {
            after.push(measure_loop(a, base, t, &d, f)?);
        }
    }
    write_pair_intervals(dir, &before, &after)?;
    let (after, before) = (median_p50(after), median_p50(before));
    Ok(match plain_after {
        true => (after, before),
        false => (before, after),
    })
}

/// The loops `--before-after CHANGE` compares: (before, after).
pub(super) fn sides(change: BeforeAfter) -> (Variant, Variant) {
    match change {
        BeforeAfter::Record => (Variant::Before, Variant::Loop),
        BeforeAfter::Foxglove => (Variant::Loop, Variant::Foxglove),
        BeforeAfter::Sched => (Variant::NoSched, Variant::Loop),
        BeforeAfter::TraceSched => (Variant::Loop, Variant::TraceSched),
        BeforeAfter::HotPath => (Variant::PlainHotPath, Variant::Loop),
        BeforeAfter::Pack => (Variant::RawSegments, Variant::Packed),
        BeforeAfter::Gate => (Variant::NoGate, Variant::Loop),
        BeforeAfter::Journal => (Variant::NoJournal, Variant::Loop),
    }
}

/// `before-after.json` of a cell: the after / before ratios of each pair at p50 and p99,
/// their median, interval and verdict ([`crate::study::stats`], as `--repeat`), and each
/// pair's misses with their sums.
fn write_pair_intervals(dir: &Path, before: &[Row], after: &[Row]) -> anyhow::Result<()> {
    use crate::study::stats::{Verdict, median_interval, paired_ratios};
    let mut j = serde_json::json!({ "pairs": before.len().min(after.len()) });
    for (name, f) in [("p50", (|r: &Row| r.p50) as fn(&Row) -> f64), ("p99", |r: &Row| r.p99)] {
        let a: Vec<f64> = after.iter().map(f).collect();
        let b: Vec<f64> = before.iter().map(f).collect();
        let ratios = paired_ratios(&a, &b);
        j[format!("after_over_before_{name}")] = match median_interval(&ratios) {
            Some(i) => serde_json::json!({
                "ratios": ratios, "median": i.median, "ci_low": i.low, "ci_high": i.high,
                "level": i.level, "verdict": Verdict::of(&i).name(),
            }),
            None => serde_json::Value::Null,
        };
    }
    // Misses, which the median rows alone show by one run each: every pair's, summed.
    let (b, a): (Vec<u64>, Vec<u64>) =
        before.iter().zip(after).map(|(b, a)| (b.misses, a.misses)).unzip();
    j["misses"] = serde_json::json!({
        "before": b, "after": a,
        "before_total": b.iter().sum::<u64>(), "after_total": a.iter().sum::<u64>(),
        "pairs_after_more": b.iter().zip(&a).filter(|(b, a)| a > b).count(),
        "pairs_after_fewer": b.iter().zip(&a).filter(|(b, a)| a < b).count(),
    });
    let path = dir.join("before-after.json");
    rotorloop_common::outdir::write_file(&path, format!("{j:#}\n"))
        .with_context(|| format!("cannot write {}", path.display()))
}

/// The row with the median p50 of `rows` (the upper one of an even count; skipped rows
/// sort last).
pub(super) fn median_p50(mut rows: Vec<Row>) -> Row {
    rows.sort_by(|a, b| a.p50.total_cmp(&b.p50));
    let n = rows.len();
    rows.swap_remove(n / 2)
}

/// The rings of `--before-after pack` (a half moved every 2048 ticks).
const PACK_RING: u64 = 4096;

/// Which loop a measurement runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Variant {
    /// The loop as it is.
    Loop,
    /// Without the monitor (the plant's own histogram).
    NoMonitor,
    /// With `--no-record`: the loop before its flight recorders.
    Before,
    /// With `--foxglove` and a viewer subscribed to every topic.
    Foxglove,
    /// With `--no-sched-sample`: the loop before the scheduling samples.
    NoSched,
    /// With `--trace-sched`.
    TraceSched,
    /// With `--plain-hot-path`: the hot path before its overhead was cut.
    PlainHotPath,
    /// With rings of [`PACK_RING`] ticks, the segments packed.
    Packed,
    /// The same with `--raw-segments`.
    RawSegments,
    /// With `--no-gate`: the plant's tick loop before the lockstep fault gate.
    NoGate,
    /// With `--no-journal`: the loop before the durable journal of the newest ticks.
    NoJournal,
    /// With the second law (`--controllers mrp-pid`).
    MrpPid,
    /// With the Python example controller (`--controllers python`).
    Python,
    /// With the C example controller (`--controllers c`).
    C,
}

impl Variant {
    /// Its row's kind.
    pub(super) fn kind(self) -> &'static str {
        self.names().0
    }

    /// Its row's kind and the letter its domain's name ends with.
    fn names(self) -> (&'static str, &'static str) {
        match self {
            Variant::Loop => ("loop", ""),
            Variant::NoMonitor => ("loop-nomon", "n"),
            Variant::Before => ("loop-before", "b"),
            Variant::Foxglove => ("loop-foxglove", "f"),
            Variant::NoSched => ("loop-nosched", "s"),
            Variant::TraceSched => ("loop-tracesched", "t"),
            Variant::PlainHotPath => ("loop-plain", "h"),
            Variant::Packed => ("loop-packed", "k"),
            Variant::RawSegments => ("loop-raw", "r"),
            Variant::NoGate => ("loop-nogate", "g"),
            Variant::NoJournal => ("loop-nojournal", "j"),
            Variant::MrpPid => ("loop-mrp-pid", "m"),
            Variant::Python => ("loop-python", "p"),
            Variant::C => ("loop-c", "c"),
        }
    }

    /// The variant of `--controllers NAME`.
    pub(super) fn of_controller(name: &str) -> Self {
        match name {
            "python" => Variant::Python,
            "c" => Variant::C,
            _ => Variant::MrpPid,
        }
    }
}

/// The loop counts of the scale cells: 2, 4, 8, … and `max` itself.
pub(super) fn scale_steps(max: usize) -> Vec<usize> {
    let mut steps: Vec<usize> =
        std::iter::successors(Some(2), |n| Some(n * 2)).take_while(|n| *n < max).collect();
    if max > 1 {
        steps.push(max);
    }
    steps
}

/// The launcher's arguments of one loop of cell `base` on `cores` (its `--cpus` and, pinned,
/// its `--pin`) in domain `domain`, into `out`.
pub(super) fn loop_run_args(
    a: &BenchArgs,
    base: &Row,
    cores: &LoopCores,
    domain: String,
    out: PathBuf,
) -> RunArgs {
    let wait: Wait = base.wait.parse().unwrap_or(Wait::Event);
    let dedicated = base.placement == "dedicated";
    let cross_host = base.placement == "cross-host";
    let pin = cores.pin();
    let cpus = (!cross_host).then(|| crate::cpus::format_list(&cores.cpus));
    let role = RoleArgs {
        domain: Some(domain),
        rt_priority: a.rt_priority,
        ..RoleArgs::realtime(&a.scenario, a.seconds, base.rate, wait)
    };
    RunArgs {
        pin,
        cpus,
        quiet: true,
        no_mcap: true,
        spin_before_tick_us: a.spin_before_tick_us,
        preset: dedicated.then(|| "dedicated".to_owned()),
        split: (base.placement == "cross-host").then(|| crate::run::split::CROSS_HOST.to_owned()),
        ..RunArgs::defaults(role, out)
    }
}

pub(super) fn measure_loop(
    a: &BenchArgs,
    base: &Row,
    t: &Topology,
    dir: &Path,
    variant: Variant,
) -> anyhow::Result<Row> {
    let ncores = t.allowed.len();
    let (kind, suffix) = variant.names();
    let without_monitor = variant == Variant::NoMonitor;
    let mut row = Row { kind: kind.into(), ..base.clone() };
    let wait: Wait = base.wait.parse().unwrap_or(Wait::Event);
    if let Some(why) = skip_reason("loop", wait, &base.placement, &base.load, ncores) {
        row.skipped = why;
        return Ok(row);
    }
    // SAFETY: geteuid reads this process's effective user id.
    if variant == Variant::TraceSched && unsafe { libc::geteuid() } != 0 {
        row.skipped = "--trace-sched needs root".into();
        return Ok(row);
    }
    let out = dir.join(kind);
    let domain = format!("bl{}-{}{suffix}", std::process::id(), base.index);
    let one = place(t, 1, Shape::of_placement(&base.placement));
    let mut run = loop_run_args(a, base, &one.loops[0], domain, out.clone());
    if let Err(why) = crate::run::args::check_spin_priority(&run) {
        row.skipped = why.0; // `run` refuses it: the roles would starve one another
        return Ok(row);
    }
    run.no_monitor = without_monitor;
    run.no_record = variant == Variant::Before;
    run.no_sched_sample = variant == Variant::NoSched;
    run.trace_sched = variant == Variant::TraceSched;
    run.role.plain_hot_path = variant == Variant::PlainHotPath;
    run.no_gate = variant == Variant::NoGate;
    run.no_journal = variant == Variant::NoJournal;
    if matches!(variant, Variant::Packed | Variant::RawSegments) {
        run.role.flight_ring_ticks = PACK_RING;
        run.raw_segments = variant == Variant::RawSegments;
    }
    match variant {
        Variant::MrpPid => run.role.scenario = mrp_scenario(a, &out)?,
        Variant::Python | Variant::C => {
            let cmd = if variant == Variant::C { c_controller() } else { python_controller(a) };
            match cmd {
                Ok(cmd) => run.controller_cmd = Some(cmd),
                Err(why) => {
                    row.skipped = why;
                    return Ok(row);
                }
            }
        }
        _ => {}
    }
    if variant == Variant::Foxglove {
        run.foxglove = Some("127.0.0.1:0".into());
        let viewer = Watching::start(out.join("foxglove.addr"));
        let ran = crate::run::launch::run(&run);
        let watched = viewer.stop(&out.join("viewer.json"));
        ran?;
        watched?;
    } else {
        crate::run::launch::run(&run)?;
    }
    if without_monitor {
        // No monitor, no summary: the plant's own histogram of the loop.
        let hgrm = out.join("plant_sense_to_actuate.hgrm");
        row.p50 = hgrm_quantile(&hgrm, 0.5);
        row.p99 = hgrm_quantile(&hgrm, 0.99);
        row.p99_9 = hgrm_quantile(&hgrm, 0.999);
        row.max = hgrm_quantile(&hgrm, 1.0);
        row.count = hgrm_count(&hgrm);
        (row.lateness_p50, row.lateness_p99, row.lateness_p99_9) = (f64::NAN, f64::NAN, f64::NAN);
        row.achieved = f64::NAN;
        (row.err_deg_final, row.err_deg_rms) = (f64::NAN, f64::NAN);
        std::fs::copy(&hgrm, dir.join("loop-nomon.hgrm"))?;
        return Ok(row);
    }
    read_loop_summary(&mut row, &out)?;
    std::fs::copy(out.join("sense_to_actuate.hgrm"), dir.join(format!("{kind}.hgrm")))?;
    Ok(row)
}

/// Fills `row` from the `summary.json` of a loop's report in `out`.
pub(super) fn read_loop_summary(row: &mut Row, out: &Path) -> anyhow::Result<()> {
    let s = Summary::read(out)?;
    let (h, late) = (s.hop(Hop::SenseToActuate), s.hop(Hop::TickLateness));
    let us = |ns: Option<f64>| ns.unwrap_or(f64::NAN) / 1e3;
    row.count = h.count.unwrap_or(0);
    (row.p50, row.p99, row.p99_9, row.max) = (us(h.p50), us(h.p99), us(h.p99_9), us(h.max));
    row.misses = s.misses.unwrap_or(0);
    row.achieved = s.achieved_rate_hz.unwrap_or(0.0);
    (row.lateness_p50, row.lateness_p99, row.lateness_p99_9) =
        (us(late.p50), us(late.p99), us(late.p99_9));
    row.err_deg_final = s.err_deg_final.unwrap_or(f64::NAN);
    row.err_deg_rms = s.err_deg_rms.unwrap_or(f64::NAN);
    row.law_p50 = us(s.stage(rotorloop_monitor::stages::Stage::Law).and_then(|f| f.p50));
    Ok(())
}

/// The scale cell of `base` with `n` loops at once: a row per loop (`loop-1` …).
pub(super) fn measure_loops(
    a: &BenchArgs,
    base: &Row,
    t: &Topology,
    n: usize,
) -> anyhow::Result<Vec<Row>> {
    let cell = format!("{}-x{n}", base.cell);
    let dir = a.out.join("cells").join(&cell);
    let row = |i: usize| Row { cell: cell.clone(), kind: format!("loop-{i}"), ..base.clone() };
    let wait: Wait = base.wait.parse().unwrap_or(Wait::Event);
    if let Some(why) = skip_reason("loop", wait, &base.placement, &base.load, t.allowed.len()) {
        return Ok((1..=n).map(|i| Row { skipped: why.clone(), ..row(i) }).collect());
    }
    let placed = crate::cpus::place_smt(t, n, Shape::of_placement(&base.placement), a.smt);
    rotorloop_common::outdir::OutDir::make(&dir).map(drop)?;
    write_placement(&dir.join("placement.json"), &placed)?;
    let results: Vec<anyhow::Result<()>> = std::thread::scope(|scope| {
        let handles: Vec<_> = (1..=n)
            .map(|i| {
                let domain = format!("bs{}-{}-{n}-{i}", std::process::id(), base.index);
                let cores = &placed.loops[i - 1];
                let run = loop_run_args(a, base, cores, domain, dir.join(format!("loop-{i}")));
                scope.spawn(move || crate::run::launch::run(&run))
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().unwrap_or_else(|_| Err(anyhow::anyhow!("panicked"))))
            .collect()
    });
    let mut rows = Vec::new();
    for (i, result) in (1..=n).zip(results) {
        let mut r = row(i);
        let out = dir.join(&r.kind);
        match result.and_then(|()| read_loop_summary(&mut r, &out)) {
            Ok(()) => {}
            Err(e) => r.skipped = format!("loop failed: {e:#}"),
        }
        rows.push(r);
    }
    Ok(rows)
}

/// `placement.json` of a scale cell: each loop's CPUs and pins, whether cores are shared,
/// and the notes (SMT, sharing) that bench.md quotes.
fn write_placement(path: &Path, p: &crate::cpus::Placement) -> anyhow::Result<()> {
    let loops: Vec<serde_json::Value> = p
        .loops
        .iter()
        .map(|l| serde_json::json!({ "cpus": crate::cpus::format_list(&l.cpus), "pin": l.pin() }))
        .collect();
    let j = serde_json::json!({ "loops": loops, "shared": p.shared, "notes": p.notes });
    rotorloop_common::outdir::write_file(path, format!("{j:#}\n"))
        .with_context(|| format!("cannot write {}", path.display()))
}

#[allow(clippy::too_many_arguments)]
pub(super) fn measure_baseline(
    exe: &Path,
    a: &BenchArgs,
    base: &Row,
    kind: &str,
    wait: Wait,
    placement: &str,
    t: &Topology,
    dir: &Path,
) -> anyhow::Result<Row> {
    if kind == "timer" {
        return measure_timer(exe, a, base, placement, t, dir);
    }
    let mut row = Row { kind: kind.into(), ..base.clone() };
    if let Some(why) = skip_reason(kind, wait, placement, &base.load, t.allowed.len()) {
        row.skipped = why;
        return Ok(row);
    }
    let k = match kind {
        "atomic" => Kind::Atomic,
        "iceoryx2" => Kind::Iceoryx2,
        _ => Kind::Uds,
    };
    let w = if k == Kind::Atomic { Wait::Spin } else { wait };
    let name = format!("bb{}-{kind}", std::process::id());
    let (ping_core, pong_core) =
        cores(placement, t).map_or((None, None), |(p, c)| (Some(p), Some(c)));
    // Across hosts: ping on host a, pong on host b, two gateways between them.
    let split = (placement == "cross-host")
        .then(|| crate::run::split::Split::parse(crate::run::split::CROSS_HOST, true))
        .transpose()?;
    let gateways =
        split.as_ref().map(|s| crate::run::split::Gateways::start(s, &name, dir)).transpose()?;
    let hosts = split.as_ref().map(|s| s.hosts().to_vec()).unwrap_or_default();
    let side = |side: &str, core: Option<usize>| {
        let mut cmd = Command::new(exe);
        cmd.args(["role", "pingpong", "--kind", kind, "--side", side, "--name", &name])
            .args([
                "--rate",
                &base.rate.to_string(),
                "--seconds",
                &a.seconds.to_string(),
                "--wait",
                &w.to_string(),
            ])
            .stdin(Stdio::null());
        if let Some(c) = core {
            cmd.args(["--core", &c.to_string()]);
        }
        if let Some(h) = hosts.get(usize::from(side == "pong")) {
            cmd.args(["--host", h]);
        }
        cmd
    };
    let mut pong = side("pong", pong_core).spawn().context("cannot start the pong side")?;
    let stem = dir.join(kind);
    let ping = side("ping", ping_core)
        .arg("--out")
        .arg(&stem)
        .status()
        .context("cannot run the ping side")?;
    let _ = pong.wait();
    drop(gateways);
    if k == Kind::Iceoryx2 {
        for h in hosts.iter().map(|h| Some(h.as_str())).chain(split.is_none().then_some(None)) {
            let _ = Domain::on_host(&name, h).map(|d| d.cleanup());
        }
    }
    if !ping.success() {
        row.skipped = format!("baseline failed ({ping})");
        return Ok(row);
    }
    let j = read_baseline(&mut row, &stem, "rtt")?;
    row.misses = j["misses"].as_u64().unwrap_or(0);
    row.achieved = j["achieved_rate_hz"].as_f64().unwrap_or(0.0);
    (row.lateness_p99, row.err_deg_final, row.err_deg_rms) = (f64::NAN, f64::NAN, f64::NAN);
    (row.lateness_p50, row.lateness_p99_9) = (f64::NAN, f64::NAN);
    if k == Kind::Atomic {
        row.wait = "spin".into();
    }
    Ok(row)
}

/// The `timer` baseline of cell `base`: a bare thread sleeping to the plant's grid on the
/// plant's core (none when unpinned), with its priority and its spin before each tick
/// (`crate::baseline::timer`). Its row's latencies are the wake-up lateness (µs).
fn measure_timer(
    exe: &Path,
    a: &BenchArgs,
    base: &Row,
    placement: &str,
    t: &Topology,
    dir: &Path,
) -> anyhow::Result<Row> {
    let mut row = Row { kind: "timer".into(), ..base.clone() };
    if placement == "dedicated" {
        if let Err(why) = crate::run::args::dedicated_cores(t) {
            row.skipped = why;
            return Ok(row);
        }
    }
    // The plant's spin before each tick: the cell's, or the dedicated preset's 50 µs.
    let spin = match (placement, a.spin_before_tick_us) {
        ("dedicated", 0) => 50,
        (_, s) => s,
    };
    let stem = dir.join("timer");
    let mut cmd = Command::new(exe);
    cmd.args(["role", "timer", "--rate", &base.rate.to_string()])
        .args(["--seconds", &a.seconds.to_string(), "--spin-before-tick-us", &spin.to_string()])
        .arg("--out")
        .arg(&stem)
        .stdin(Stdio::null());
    if let Some((plant, _)) = cores(placement, t) {
        cmd.args(["--core", &plant.to_string()]);
    }
    if let Some(p) = a.rt_priority {
        cmd.args(["--rt-priority", &p.to_string()]);
    }
    let status = cmd.status().context("cannot run the timer baseline")?;
    if !status.success() {
        row.skipped = format!("timer baseline failed ({status})");
        return Ok(row);
    }
    read_baseline(&mut row, &stem, "lateness")?;
    (row.lateness_p50, row.lateness_p99, row.lateness_p99_9) = (row.p50, row.p99, row.p99_9);
    (row.achieved, row.err_deg_final, row.err_deg_rms) = (base.rate, f64::NAN, f64::NAN);
    Ok(row)
}

/// Fills `row`'s count and latencies (µs) from the figures `stats` of a baseline's
/// `stem.json`, and returns the file.
fn read_baseline(row: &mut Row, stem: &Path, stats: &str) -> anyhow::Result<serde_json::Value> {
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(stem.with_extension("json"))?)?;
    let us = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN) / 1e3;
    let h = &j[stats];
    row.count = h["count"].as_u64().unwrap_or(0);
    (row.p50, row.p99, row.p99_9, row.max) =
        (us(&h["p50"]), us(&h["p99"]), us(&h["p99_9"]), us(&h["max"]));
    Ok(j)
}

/// A viewer subscribed to every topic of a `--foxglove` run's server, on a thread of the
/// bench (not of the loop), reading as fast as the server sends.
struct Watching {
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: std::thread::JoinHandle<anyhow::Result<u64>>,
}

impl Watching {
    /// Connects once the server has written its address to `addr_file`.
    fn start(addr_file: PathBuf) -> Self {
        use std::sync::atomic::{AtomicBool, Ordering};
        let stop = std::sync::Arc::new(AtomicBool::new(false));
        let done = stop.clone();
        let thread = std::thread::spawn(move || {
            let addr = loop {
                if let Ok(a) = std::fs::read_to_string(&addr_file).map(|a| a.trim().to_owned()) {
                    if !a.is_empty() {
                        break a;
                    }
                }
                if done.load(Ordering::Relaxed) {
                    anyhow::bail!("the Foxglove server never said its address");
                }
                std::thread::sleep(std::time::Duration::from_millis(10));
            };
            let poll = std::time::Duration::from_millis(50);
            let mut v = crate::observe::viewer::Viewer::connect(&addr, poll)?;
            v.subscribe(&["*"])?;
            let mut n = 0u64;
            while !done.load(Ordering::Relaxed) {
                match v.receive() {
                    Ok(Some(_)) => n += 1,
                    Ok(None) => {}
                    // The server ends with the run.
                    Err(_) => break,
                }
            }
            Ok(n)
        });
        Self { stop, thread }
    }

    /// Stops the viewer and writes how many messages it received to `path`.
    fn stop(self, path: &Path) -> anyhow::Result<()> {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        let n = match self.thread.join() {
            Ok(r) => r?,
            Err(_) => anyhow::bail!("the bench's viewer panicked"),
        };
        rotorloop_common::outdir::write_file(
            path,
            serde_json::json!({ "messages": n }).to_string() + "\n",
        )?;
        Ok(())
    }
}

/// The bench's scenario with the second law (`mrp-pid`) and `mrp-regulation`'s gains,
/// written beside the measurement; its path.
fn mrp_scenario(a: &BenchArgs, out: &Path) -> anyhow::Result<String> {
    use rotorloop_common::scenario::Scenario;
    let mut file = Scenario::load(&a.scenario)?.file;
    let gains = Scenario::load("mrp-regulation")?.file.controller;
    file.controller.law = gains.law;
    file.controller.law_params = gains.law_params;
    file.name = format!("{}-mrp-pid", file.name);
    rotorloop_common::outdir::OutDir::make(out).map(drop)?;
    let path = out.with_extension("scenario.toml");
    rotorloop_common::outdir::write_file(&path, file.to_toml())?;
    Ok(path.display().to_string())
}

/// The `--controller-cmd` of the C example, built by `make -C examples/c` against the
/// `librotorloop_c.so` beside this executable (`cargo build --release --workspace` puts
/// both in `target/release/`), or why it cannot run here.
fn c_controller() -> Result<String, String> {
    let dir = Path::new("examples/c");
    if !dir.join("controller.c").exists() {
        return Err(format!(
            "no {}/controller.c here (run the bench from the repository)",
            dir.display()
        ));
    }
    let exe = std::env::current_exe().map_err(|e| format!("cannot find this executable: {e}"))?;
    let libdir = exe.parent().map(Path::to_path_buf).unwrap_or_default();
    if !libdir.join("librotorloop_c.so").exists() {
        return Err(format!(
            "no librotorloop_c.so in {} (cargo build --release --workspace)",
            libdir.display()
        ));
    }
    let made = Command::new("make")
        .arg("-C")
        .arg(dir)
        .arg(format!("LIBDIR={}", libdir.display()))
        .stdout(Stdio::null())
        .output();
    match made {
        Ok(o) if o.status.success() => Ok(dir.join("controller").display().to_string()),
        Ok(o) => {
            Err(format!("make -C examples/c failed: {}", String::from_utf8_lossy(&o.stderr).trim()))
        }
        Err(e) => Err(format!("cannot run make ({e}): cc and make build the C controller")),
    }
}

/// The `--controller-cmd` of the Python example, or why it cannot run here.
fn python_controller(a: &BenchArgs) -> Result<String, String> {
    let script = Path::new("examples/python/controller.py");
    if !script.exists() {
        return Err(format!("no {} here (run the bench from the repository)", script.display()));
    }
    let ready = Command::new(&a.python)
        .args(["-c", "import numpy, iceoryx2"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status();
    if !ready.is_ok_and(|s| s.success()) {
        return Err(format!(
            "{} cannot import numpy and iceoryx2 (pip install -r python/requirements.txt, or --python)",
            a.python
        ));
    }
    Ok(format!("{} {}", a.python, script.display()))
}
