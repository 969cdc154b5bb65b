//! `rotorloop bench`: the latency study. For every cell (rate × wait strategy × core
//! placement × load) it runs the real four-process loop in real time and, in the same
//! invocation with the same placement, wait strategy and pacing (one exchange per tick at
//! the cell's rate), the baselines it should be judged against: shared-memory atomics
//! (the hardware floor), bare iceoryx2, and Unix domain sockets.
//!
//! Output: `bench.csv` (a row per cell and baseline, appended as cells finish, so an
//! interrupted bench keeps what it measured), `bench.md` (the table with ratios to the
//! baselines), one `.hgrm` per measurement, and plots.

use std::fmt::Write as _;
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::Context;
use clap::Args;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::ipc::wait::Wait;
use rotorloop_common::signals::shutdown_requested;
use rotorloop_monitor::plot::{Series, YScale, line_chart};

use crate::baseline::pingpong::Kind;
use crate::run::launch::RunArgs;
use rotorloop_common::role::UsageError;
use rotorloop_common::role::args::{Mode, RoleArgs};

/// `rotorloop bench` arguments.
#[derive(Debug, Clone, Args)]
pub struct BenchArgs {
    /// Tick rates (Hz).
    #[arg(
        long,
        allow_negative_numbers = true,
        value_delimiter = ',',
        default_value = "1000,2000,5000,10000,20000"
    )]
    pub rates: Vec<f64>,
    /// Wait strategies.
    #[arg(long, value_delimiter = ',', default_value = "event,spin,hybrid")]
    pub wait: Vec<Wait>,
    /// Core placements of plant and controller: same-core, cross-core, unpinned,
    /// dedicated (every role on its own core, all spinning: `rotorloop run --preset
    /// dedicated`; needs 4 cores, measured once per rate whatever `--wait` says), or
    /// cross-host (unpinned, the controller on another "host" joined by two link gateways
    /// over Zenoh on loopback: `rotorloop run --split`; needs `rotorloop-link`).
    #[arg(long, value_delimiter = ',', default_value = "same-core,cross-core,unpinned")]
    pub placement: Vec<String>,
    /// Seconds per measurement.
    #[arg(long, allow_negative_numbers = true, default_value_t = 3.0)]
    pub seconds: f64,
    /// Load: none, or other-core (a CPU hog on the core the loop is not pinned to).
    #[arg(long, value_delimiter = ',', default_value = "none")]
    pub load: Vec<String>,
    /// Baselines: atomic, iceoryx2, uds.
    #[arg(long, value_delimiter = ',', default_value = "atomic,iceoryx2,uds")]
    pub baselines: Vec<String>,
    /// The plant sleeps until this many µs before each tick and spins the rest.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
    pub spin_before_tick_us: u64,
    /// Also run each loop cell without the monitor and report the change of the
    /// plant-measured sense-to-actuate p50 (`loop-nomon` rows).
    #[arg(long)]
    pub monitor_cost: bool,
    /// Also run each loop cell as it was before the newest change to the hot path, in the
    /// same invocation: without the flight recorders (`loop-before` rows; `rotorloop run
    /// --no-record`). The change before that, the cut overhead, is `run --plain-hot-path`
    /// by hand (docs/measured/overhead.md).
    #[arg(long)]
    pub before_after: bool,
    /// With `--before-after`: measure before and after this many times each, alternating
    /// (before, after, before, …), and report the run with the median p50 of each (the
    /// difference between two runs of one loop here is often larger than the change).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..=99))]
    pub pairs: u64,
    /// Scale: also run 2, 4, … up to N independent loops (domains) at once per cell, each
    /// with its own four processes (`-xN` cells, a `loop-I` row per loop), and report the
    /// largest N at which every loop has no more misses than the bare iceoryx2 baseline.
    #[arg(long, default_value_t = 1)]
    pub loops: usize,
    /// Rebuild bench.md and the plots from an existing `--out` directory, measuring nothing.
    #[arg(long)]
    pub replot: bool,
    /// Scenario the loop runs.
    #[arg(long, default_value = "paper-sinusoid")]
    pub scenario: String,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
}

/// One measurement (a loop cell or a baseline), as a row of `bench.csv`.
#[derive(Debug, Clone, Default)]
pub struct Row {
    /// Cell identifier.
    pub cell: String,
    /// `loop`, `atomic`, `iceoryx2`, `uds`.
    pub kind: String,
    /// Rate (Hz).
    pub rate: f64,
    /// Wait strategy.
    pub wait: String,
    /// Placement.
    pub placement: String,
    /// Load.
    pub load: String,
    /// Samples.
    pub count: u64,
    /// µs.
    pub p50: f64,
    /// µs.
    pub p99: f64,
    /// µs.
    pub p99_9: f64,
    /// µs.
    pub max: f64,
    /// Ticks without a fresh answer in time.
    pub misses: u64,
    /// Achieved rate (Hz).
    pub achieved: f64,
    /// Tick lateness p99 (µs), loop only.
    pub lateness_p99: f64,
    /// Why the measurement was skipped, if it was.
    pub skipped: String,
    /// Tracking error at the end of the run (degrees), loop only.
    pub err_deg_final: f64,
    /// Root mean square of the tracking error over the run (degrees), loop only.
    pub err_deg_rms: f64,
    /// Cell number (for short domain names).
    pub index: usize,
}

const CSV_HEADER: &str = "cell,kind,rate_hz,wait,placement,load,count,p50_us,p99_us,p99_9_us,max_us,misses,achieved_rate_hz,tick_lateness_p99_us,skipped,err_deg_final,err_deg_rms";

impl Row {
    fn parse(line: &str) -> Option<Self> {
        let f: Vec<&str> = line.split(',').collect();
        // Bench files written before `err_deg_final` have 15 columns, before `err_deg_rms` 16.
        if !(15..=17).contains(&f.len()) {
            return None;
        }
        let num = |i: usize| f.get(i).map_or(f64::NAN, |v| v.parse::<f64>().unwrap_or(f64::NAN));
        Some(Self {
            cell: f[0].into(),
            kind: f[1].into(),
            rate: num(2),
            wait: f[3].into(),
            placement: f[4].into(),
            load: f[5].into(),
            count: f[6].parse().unwrap_or(0),
            p50: num(7),
            p99: num(8),
            p99_9: num(9),
            max: num(10),
            misses: f[11].parse().unwrap_or(0),
            achieved: num(12),
            lateness_p99: num(13),
            skipped: f[14].into(),
            err_deg_final: num(15),
            err_deg_rms: num(16),
            index: 0,
        })
    }

    fn csv(&self) -> String {
        format!(
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            self.cell,
            self.kind,
            self.rate,
            self.wait,
            self.placement,
            self.load,
            self.count,
            self.p50,
            self.p99,
            self.p99_9,
            self.max,
            self.misses,
            self.achieved,
            self.lateness_p99,
            self.skipped.replace(',', ";"),
            self.err_deg_final,
            self.err_deg_rms
        )
    }
}

/// Cores of plant/controller (and ping/pong) for a placement; `None` = unpinned.
fn cores(placement: &str, ncores: usize) -> Option<(usize, usize)> {
    match placement {
        "same-core" => Some((0, 0)),
        "cross-core" => Some((0, 1)),
        "dedicated" => crate::run::launch::dedicated_cores(ncores).ok().map(|c| (c[0], c[1])),
        _ => None, // unpinned, cross-host
    }
}

/// Why a combination cannot work on this machine, if it cannot.
pub fn skip_reason(
    kind: &str,
    wait: Wait,
    placement: &str,
    load: &str,
    ncores: usize,
) -> Option<String> {
    if placement == "dedicated" {
        return crate::run::launch::dedicated_cores(ncores).err();
    }
    let spins = matches!(wait, Wait::Spin) || kind == "atomic";
    if spins && placement == "same-core" {
        return Some(
            "busy-wait with both ends on one core: each hand-off waits for a scheduler time slice"
                .into(),
        );
    }
    if spins && ncores < 2 {
        return Some(format!("busy-wait needs 2 dedicated cores; this machine has {ncores}"));
    }
    if load == "other-core" && placement != "same-core" {
        return Some("other-core load needs the loop on one core (same-core placement)".into());
    }
    if placement == "cross-host" {
        return cross_host_skip(kind, spins, ncores);
    }
    None
}

/// Why a cross-host cell cannot be measured here, if it cannot.
fn cross_host_skip(kind: &str, spins: bool, ncores: usize) -> Option<String> {
    if kind == "atomic" || kind == "uds" {
        return Some("shared-memory atomics and a Unix socket do not cross hosts".into());
    }
    if spins && ncores < 6 {
        return Some(format!(
            "busy-wait across hosts needs a core for each role and each gateway (6); this \
             machine has {ncores}"
        ));
    }
    crate::run::split::link_binary().err().map(|e| e.0)
}

fn validate(a: &BenchArgs) -> Result<(), UsageError> {
    for r in &a.rates {
        if !(r.is_finite() && (1.0..=100_000.0).contains(r)) {
            return Err(UsageError(format!("--rates {r} is not allowed: 1 to 100000 Hz")));
        }
    }
    for p in &a.placement {
        if !["same-core", "cross-core", "unpinned", "dedicated", "cross-host"].contains(&p.as_str())
        {
            return Err(UsageError(format!(
                "--placement `{p}` is not allowed: same-core, cross-core, unpinned, dedicated or \
                 cross-host"
            )));
        }
    }
    for l in &a.load {
        if !["none", "other-core"].contains(&l.as_str()) {
            return Err(UsageError(format!("--load `{l}` is not allowed: none or other-core")));
        }
    }
    for b in &a.baselines {
        if !["atomic", "iceoryx2", "uds"].contains(&b.as_str()) {
            return Err(UsageError(format!(
                "--baselines `{b}` is not allowed: atomic, iceoryx2, uds"
            )));
        }
    }
    if !(1..=64).contains(&a.loops) {
        return Err(UsageError(format!("--loops {} is not allowed: 1 to 64", a.loops)));
    }
    if !(a.seconds.is_finite() && a.seconds >= 0.05 && a.seconds <= 3600.0) {
        return Err(UsageError(format!("--seconds {} is not allowed: 0.05 to 3600", a.seconds)));
    }
    Ok(())
}

/// Runs the bench.
pub fn run(a: &BenchArgs) -> anyhow::Result<()> {
    validate(a)?;
    if a.replot {
        let text = std::fs::read_to_string(a.out.join("bench.csv"))
            .with_context(|| format!("no bench.csv in {}", a.out.display()))?;
        let rows: Vec<Row> = text.lines().skip(1).filter_map(Row::parse).collect();
        write_markdown(a, &rows)?;
        plots(a, &rows)?;
        println!("bench: {} measurements re-plotted in {}", rows.len(), a.out.display());
        return Ok(());
    }
    rotorloop_common::role::args::scenario_with_overrides(
        &a.scenario,
        Some(a.seconds),
        Some(a.rates[0]),
        None,
    )?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let exe = std::env::current_exe().context("cannot find the rotorloop executable")?;
    let ncores = std::thread::available_parallelism().map_or(1, |n| n.get());
    rotorloop_common::signals::install_signal_handlers();

    let csv_path = a.out.join("bench.csv");
    std::fs::write(&csv_path, format!("{CSV_HEADER}\n"))?;
    let mut rows: Vec<Row> = Vec::new();
    let cells = cells(a);
    let tty = std::io::stderr().is_terminal();
    for (i, (rate, wait, placement, load)) in cells.iter().enumerate() {
        if shutdown_requested() {
            eprintln!("interrupted: {} of {} cells measured", i, cells.len());
            break;
        }
        let cell = format!("r{rate}-{wait}-{placement}-{load}");
        let bar = "#".repeat(20 * i / cells.len()) + &" ".repeat(20 - 20 * i / cells.len());
        eprint!(
            "{}[{bar}] {}/{} {cell}{}",
            if tty { "\r" } else { "" },
            i + 1,
            cells.len(),
            if tty { "        " } else { "\n" }
        );
        let base = Row {
            index: i,
            cell: cell.clone(),
            rate: *rate,
            wait: wait.to_string(),
            placement: placement.clone(),
            load: load.clone(),
            ..Row::default()
        };
        let dir = a.out.join("cells").join(&cell);
        std::fs::create_dir_all(&dir)?;
        let hog = if load == "other-core"
            && skip_reason("loop", *wait, placement, load, ncores).is_none()
        {
            let core = cores(placement, ncores).map(|(p, _)| (p + 1) % ncores);
            let mut cmd = Command::new(&exe);
            cmd.args(["role", "hog"]).stdin(Stdio::null());
            if let Some(c) = core {
                cmd.args(["--core", &c.to_string()]);
            }
            Some(cmd.spawn().context("cannot start the CPU hog")?)
        } else {
            None
        };
        let mut measured = vec![measure_loop(a, &base, ncores, &dir, Variant::Loop)?];
        if a.monitor_cost {
            measured.push(measure_loop(a, &base, ncores, &dir, Variant::NoMonitor)?);
        }
        if a.before_after {
            let (after, before) = before_after(a, &base, ncores, &dir, measured.remove(0))?;
            measured.insert(0, after);
            measured.push(before);
        }
        for b in &a.baselines {
            measured.push(measure_baseline(&exe, a, &base, b, *wait, placement, ncores, &dir)?);
        }
        for n in scale_steps(a.loops) {
            measured.extend(measure_loops(a, &base, ncores, n)?);
        }
        if let Some(mut h) = hog {
            // SAFETY: signals our own child.
            unsafe { libc::kill(h.id() as libc::pid_t, libc::SIGTERM) };
            let _ = h.wait();
        }
        let mut f = std::fs::OpenOptions::new().append(true).open(&csv_path)?;
        for r in &measured {
            writeln!(f, "{}", r.csv())?;
        }
        rows.extend(measured);
        write_markdown(a, &rows)?;
    }
    if tty {
        eprintln!();
    }
    write_markdown(a, &rows)?;
    plots(a, &rows)?;
    println!("bench: {} measurements in {}", rows.len(), a.out.display());
    Ok(())
}

/// The cells to measure: rate × wait × placement × load, the dedicated preset once per
/// rate (it spins, whatever `--wait` lists).
fn cells(a: &BenchArgs) -> Vec<(f64, Wait, String, String)> {
    let mut cells = Vec::new();
    for &rate in &a.rates {
        for &wait in &a.wait {
            for placement in &a.placement {
                // The dedicated preset spins: one cell per rate, whatever `--wait` lists.
                let wait = if placement == "dedicated" { Wait::Spin } else { wait };
                for load in &a.load {
                    let cell = (rate, wait, placement.clone(), load.clone());
                    if !cells.contains(&cell) {
                        cells.push(cell);
                    }
                }
            }
        }
    }
    cells
}

/// `--before-after`: the loop without flight recorders and with them, `--pairs` times
/// each, alternating (`first` is the first "after"); the median run of each.
fn before_after(
    a: &BenchArgs,
    base: &Row,
    ncores: usize,
    dir: &Path,
    first: Row,
) -> anyhow::Result<(Row, Row)> {
    let (mut before, mut after) = (Vec::new(), vec![first]);
    for i in 0..a.pairs {
        let d = if i == 0 { dir.to_owned() } else { dir.join(format!("pair{i}")) };
        before.push(measure_loop(a, base, ncores, &d, Variant::Before)?);
        if i > 0 {
            after.push(measure_loop(a, base, ncores, &d, Variant::Loop)?);
        }
    }
    Ok((median_p50(after), median_p50(before)))
}

/// The row with the median p50 of `rows` (the upper one of an even count; skipped rows
/// sort last).
fn median_p50(mut rows: Vec<Row>) -> Row {
    rows.sort_by(|a, b| a.p50.total_cmp(&b.p50));
    let n = rows.len();
    rows.swap_remove(n / 2)
}

/// Which loop a measurement runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Variant {
    /// The loop as it is.
    Loop,
    /// Without the monitor (the plant's own histogram).
    NoMonitor,
    /// With `--no-record`: the loop before its flight recorders.
    Before,
}

impl Variant {
    fn kind(self) -> &'static str {
        match self {
            Variant::Loop => "loop",
            Variant::NoMonitor => "loop-nomon",
            Variant::Before => "loop-before",
        }
    }
}

/// The loop counts of the scale cells: 2, 4, 8, … and `max` itself.
fn scale_steps(max: usize) -> Vec<usize> {
    let mut steps: Vec<usize> =
        std::iter::successors(Some(2), |n| Some(n * 2)).take_while(|n| *n < max).collect();
    if max > 1 {
        steps.push(max);
    }
    steps
}

/// The launcher's arguments of one loop of cell `base` in domain `domain`, into `out`.
fn loop_run_args(
    a: &BenchArgs,
    base: &Row,
    ncores: usize,
    domain: String,
    out: PathBuf,
) -> RunArgs {
    let wait: Wait = base.wait.parse().unwrap_or(Wait::Event);
    let dedicated = base.placement == "dedicated";
    let pin = cores(&base.placement, ncores).filter(|_| !dedicated).map(|(p, c)| {
        let other = |x: usize| (x + 1) % ncores;
        format!("plant={p},controller={c},reference={},monitor={}", other(p), other(c))
    });
    let role = RoleArgs {
        domain: Some(domain),
        host: None,
        scenario: a.scenario.clone(),
        duration: Some(a.seconds),
        rate: Some(base.rate),
        actuation: None,
        mode: Mode::Realtime,
        wait,
        core: None,
        rt_priority: None,
        mlock: false,
        plain_hot_path: false,
        record: None,
        flight_ring_ticks: rotorloop_common::flight::DEFAULT_RING_TICKS,
        hooks: Default::default(),
    };
    RunArgs {
        pin,
        quiet: true,
        spin_before_tick_us: a.spin_before_tick_us,
        preset: dedicated.then(|| "dedicated".to_owned()),
        split: (base.placement == "cross-host").then(|| crate::run::split::CROSS_HOST.to_owned()),
        ..RunArgs::defaults(role, out)
    }
}

fn measure_loop(
    a: &BenchArgs,
    base: &Row,
    ncores: usize,
    dir: &Path,
    variant: Variant,
) -> anyhow::Result<Row> {
    let kind = variant.kind();
    let without_monitor = variant == Variant::NoMonitor;
    let mut row = Row { kind: kind.into(), ..base.clone() };
    let wait: Wait = base.wait.parse().unwrap_or(Wait::Event);
    if let Some(why) = skip_reason("loop", wait, &base.placement, &base.load, ncores) {
        row.skipped = why;
        return Ok(row);
    }
    let out = dir.join(kind);
    let suffix = match variant {
        Variant::Loop => "",
        Variant::NoMonitor => "n",
        Variant::Before => "b",
    };
    let domain = format!("bl{}-{}{suffix}", std::process::id(), base.index);
    let mut run = loop_run_args(a, base, ncores, domain, out.clone());
    run.no_monitor = without_monitor;
    run.no_record = variant == Variant::Before;
    crate::run::launch::run(&run)?;
    if without_monitor {
        // No monitor, no summary: the plant's own histogram of the loop.
        let hgrm = out.join("plant_sense_to_actuate.hgrm");
        row.p50 = hgrm_quantile(&hgrm, 0.5);
        row.p99 = hgrm_quantile(&hgrm, 0.99);
        row.p99_9 = hgrm_quantile(&hgrm, 0.999);
        row.max = hgrm_quantile(&hgrm, 1.0);
        row.count = hgrm_count(&hgrm);
        row.lateness_p99 = f64::NAN;
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
fn read_loop_summary(row: &mut Row, out: &Path) -> anyhow::Result<()> {
    let path = out.join("summary.json");
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("cannot read {}", path.display()))?;
    let j: serde_json::Value = serde_json::from_str(&text)?;
    let h = &j["hops"]["sense_to_actuate"];
    let us = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN) / 1e3;
    row.count = h["count"].as_u64().unwrap_or(0);
    row.p50 = us(&h["p50"]);
    row.p99 = us(&h["p99"]);
    row.p99_9 = us(&h["p99_9"]);
    row.max = us(&h["max"]);
    row.misses = j["misses"].as_u64().unwrap_or(0);
    row.achieved = j["achieved_rate_hz"].as_f64().unwrap_or(0.0);
    row.lateness_p99 = us(&j["hops"]["tick_lateness"]["p99"]);
    row.err_deg_final = j["err_deg_final"].as_f64().unwrap_or(f64::NAN);
    row.err_deg_rms = j["err_deg_rms"].as_f64().unwrap_or(f64::NAN);
    Ok(())
}

/// The scale cell of `base` with `n` loops at once: a row per loop (`loop-1` …).
fn measure_loops(a: &BenchArgs, base: &Row, ncores: usize, n: usize) -> anyhow::Result<Vec<Row>> {
    let cell = format!("{}-x{n}", base.cell);
    let dir = a.out.join("cells").join(&cell);
    let row = |i: usize| Row { cell: cell.clone(), kind: format!("loop-{i}"), ..base.clone() };
    let wait: Wait = base.wait.parse().unwrap_or(Wait::Event);
    if let Some(why) = skip_reason("loop", wait, &base.placement, &base.load, ncores) {
        return Ok((1..=n).map(|i| Row { skipped: why.clone(), ..row(i) }).collect());
    }
    let results: Vec<anyhow::Result<()>> = std::thread::scope(|scope| {
        let handles: Vec<_> = (1..=n)
            .map(|i| {
                let domain = format!("bs{}-{}-{n}-{i}", std::process::id(), base.index);
                let run = loop_run_args(a, base, ncores, domain, dir.join(format!("loop-{i}")));
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

#[allow(clippy::too_many_arguments)]
fn measure_baseline(
    exe: &Path,
    a: &BenchArgs,
    base: &Row,
    kind: &str,
    wait: Wait,
    placement: &str,
    ncores: usize,
    dir: &Path,
) -> anyhow::Result<Row> {
    let mut row = Row { kind: kind.into(), ..base.clone() };
    if let Some(why) = skip_reason(kind, wait, placement, &base.load, ncores) {
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
        cores(placement, ncores).map_or((None, None), |(p, c)| (Some(p), Some(c)));
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
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(stem.with_extension("json"))?)?;
    let us = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN) / 1e3;
    let r = &j["rtt"];
    row.count = r["count"].as_u64().unwrap_or(0);
    row.p50 = us(&r["p50"]);
    row.p99 = us(&r["p99"]);
    row.p99_9 = us(&r["p99_9"]);
    row.max = us(&r["max"]);
    row.misses = j["misses"].as_u64().unwrap_or(0);
    row.achieved = j["achieved_rate_hz"].as_f64().unwrap_or(0.0);
    (row.lateness_p99, row.err_deg_final, row.err_deg_rms) = (f64::NAN, f64::NAN, f64::NAN);
    if k == Kind::Atomic {
        row.wait = "spin".into();
    }
    Ok(row)
}

fn write_markdown(a: &BenchArgs, rows: &[Row]) -> anyhow::Result<()> {
    let mut md = format!(
        "# rotorloop bench\n\n{} s per measurement; scenario {}. Loop: sense-to-actuate (plant publishes \
         state k → plant holds torque k), real time. Baselines: paced round trip, one per tick, same \
         placement and wait strategy (atomic: always spin). Latencies in µs.\n\n\
         | cell | kind | p50 | p99 | p99.9 | max | misses | achieved Hz | tick lateness p99 | loop/iceoryx2 p50 | loop/iceoryx2 p99.9 | loop/uds p50 | loop/atomic p50 |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
        a.seconds, a.scenario
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
    md.push_str(&zero_miss_md(a, rows));
    md.push_str(&breakdown_md(a, rows));
    md.push_str(&before_after_md(rows, a.pairs));
    md.push_str(&scale_md(rows));
    md.push_str(&cross_host_md(rows));
    std::fs::write(a.out.join("bench.md"), md)?;
    Ok(())
}

/// Each cross-host measurement beside the same one on one host (`unpinned` if measured,
/// else another placement of this invocation): what the link costs.
fn cross_host_md(rows: &[Row]) -> String {
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
fn zero_miss_md(a: &BenchArgs, rows: &[Row]) -> String {
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
const BREAKDOWN: [(&str, &str); 10] = [
    ("state_send", "state send"),
    ("state_delivery", "state delivery"),
    ("controller_validate", "validate"),
    ("controller_pair", "pair"),
    ("controller_law", "law"),
    ("controller_publish_prep", "publish prep"),
    ("torque_send", "torque send"),
    ("torque_delivery", "torque delivery"),
    ("state_notify", "(state notify)"),
    ("torque_notify", "(torque notify)"),
];

/// The stage p50s (µs) of a loop measurement, from its `summary.json`.
fn stage_p50s(a: &BenchArgs, r: &Row) -> Option<Vec<f64>> {
    let path = a.out.join("cells").join(&r.cell).join(&r.kind).join("summary.json");
    let j: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()?;
    let stages = j["stages"].as_array()?;
    let p50 = |name: &str| {
        let s = stages.iter().find(|s| s["stage"] == name)?;
        s["p50"].as_f64().map(|ns| ns / 1e3)
    };
    BREAKDOWN.iter().map(|(name, _)| p50(name)).collect()
}

/// Where the microseconds of sense-to-actuate go (`crate` monitor's `stages`).
fn breakdown_md(a: &BenchArgs, rows: &[Row]) -> String {
    let mut md = String::from(
        "\n## Where the microseconds go (p50, µs)\n\nSense-to-actuate split at the stamps the plant \
         and the controller carry in their samples; the eight stages add up to it tick by tick \
         (their p50s need not add up to its p50). Notifies run after the send, beside the \
         delivery; a spinning receiver does not wait for them.\n\n| cell | kind | s2a |",
    );
    for (_, label) in BREAKDOWN {
        let _ = write!(md, " {label} |");
    }
    md.push_str("\n|---|---|---|");
    md.push_str(&"---|".repeat(BREAKDOWN.len()));
    md.push('\n');
    for r in rows.iter().filter(|r| r.kind == "loop" || r.kind == "loop-before") {
        let Some(p50s) = stage_p50s(a, r).filter(|_| r.skipped.is_empty()) else { continue };
        let _ = write!(md, "| {} | {} | {:.1} |", r.cell, r.kind, r.p50);
        for v in p50s {
            let _ = write!(md, " {v:.2} |");
        }
        md.push('\n');
    }
    md
}

/// The loop before and after its overhead was cut, with the bare baseline of the cell.
fn before_after_md(rows: &[Row], pairs: u64) -> String {
    let mut md = String::new();
    let ok = |cell: &str, kind: &str| {
        rows.iter().find(|r| r.cell == cell && r.kind == kind && r.skipped.is_empty())
    };
    for r in rows.iter().filter(|r| r.kind == "loop" && r.skipped.is_empty()) {
        let (Some(before), bare) = (ok(&r.cell, "loop-before"), ok(&r.cell, "iceoryx2")) else {
            continue;
        };
        if md.is_empty() {
            md.push_str(&format!(
                "\n## Before and after (same invocation)\n\nBefore: the loop without flight recorders \
                 (`run --no-record`); after: with them (the default). \
                 Each measured {pairs} time(s), alternating; each row is the run with the \
                 median p50.\n\n| cell | before p50 | after p50 | \
                 change | bare iceoryx2 p50 | before/bare | after/bare | misses before/after/bare |\n\
                 |---|---|---|---|---|---|---|---|\n",
            ));
        }
        let bare_p50 = bare.map_or(f64::NAN, |b| b.p50);
        let bare_misses = bare.map_or("—".to_owned(), |b| b.misses.to_string());
        let _ = writeln!(
            md,
            "| {} | {:.1} | {:.1} | {:+.0} % | {:.1} | {:.2} | {:.2} | {} / {} / {} |",
            r.cell,
            before.p50,
            r.p50,
            100.0 * (r.p50 / before.p50 - 1.0),
            bare_p50,
            before.p50 / bare_p50,
            r.p50 / bare_p50,
            before.misses,
            r.misses,
            bare_misses
        );
    }
    md
}

/// The scale cells: per loop count, the loops' p50s, worst p99 and misses, against the
/// bare baseline's misses; the largest count at which no loop missed more.
fn scale_md(rows: &[Row]) -> String {
    let mut md = String::new();
    for base in rows.iter().filter(|r| r.kind == "loop" && r.skipped.is_empty()) {
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
        let bare = rows.iter().find(|r| r.cell == base.cell && r.kind == "iceoryx2");
        let limit = bare.filter(|b| b.skipped.is_empty()).map(|b| b.misses);
        let _ = write!(
            md,
            "\n## Scale: {} (loops at once)\n\nBare iceoryx2 misses (one pair): {}.\n\n\
             | loops | p50 of each loop (µs) | worst p99 | misses of each loop | all ≤ bare |\n\
             |---|---|---|---|---|\n",
            base.cell,
            limit.map_or("not measured".into(), |m| m.to_string())
        );
        let (mut largest, mut unbroken) = (None, true);
        let mut all = vec![(1, vec![base])];
        all.extend(scaled);
        for (n, rs) in &all {
            let measured = rs.iter().all(|r| r.skipped.is_empty());
            let fits = measured && limit.is_some_and(|l| rs.iter().all(|r| r.misses <= l));
            let list =
                |f: &dyn Fn(&Row) -> String| rs.iter().map(|r| f(r)).collect::<Vec<_>>().join(", ");
            let worst = rs.iter().map(|r| r.p99).fold(f64::NAN, f64::max);
            let _ = writeln!(
                md,
                "| {n} | {} | {worst:.1} | {} | {} |",
                list(&|r| if r.skipped.is_empty() {
                    format!("{:.1}", r.p50)
                } else {
                    r.skipped.clone()
                }),
                list(&|r| r.misses.to_string()),
                if fits { "yes" } else { "no" }
            );
            // The largest count up to which every count measured fits.
            unbroken &= fits;
            if unbroken {
                largest = Some(*n);
            }
        }
        let _ = writeln!(
            md,
            "\nLargest number of loops with every loop at or below the bare baseline's misses: {}.",
            largest.map_or("none measured".into(), |n| n.to_string())
        );
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
fn hgrm_quantile(path: &Path, q: f64) -> f64 {
    read_hgrm_values(path).iter().find(|(p, _)| *p >= q).map_or(f64::NAN, |(_, v)| *v)
}

/// The total count of a `.hgrm` file.
fn hgrm_count(path: &Path) -> u64 {
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

fn plots(a: &BenchArgs, rows: &[Row]) -> anyhow::Result<()> {
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
