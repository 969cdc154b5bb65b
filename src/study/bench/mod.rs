//! `rotorloop bench`: the latency study. For every cell (rate × wait strategy × core
//! placement × load) it runs the real four-process loop in real time and, in the same
//! invocation with the same placement, wait strategy and pacing (one exchange per tick at
//! the cell's rate), the baselines it should be judged against: shared-memory atomics
//! (the hardware floor), bare iceoryx2, and Unix domain sockets.
//!
//! Output: `bench.csv` (a row per cell and baseline, appended as cells finish, so an
//! interrupted bench keeps what it measured), `bench.md` (the table with ratios to the
//! baselines), one `.hgrm` per measurement, and plots.
//!
//! - [`cell`]: the arguments, the cells, what cannot be measured here, a row;
//! - [`measure`]: measuring a cell and its baselines;
//! - [`repeat`]: `--repeat`'s medians, intervals and verdicts;
//! - [`report`]: `bench.md` and the plots.

pub mod cell;
pub mod measure;
pub mod repeat;
pub mod report;

use std::io::{IsTerminal, Write};
use std::process::{Command, Stdio};

use anyhow::Context;
use rotorloop_common::signals::shutdown_requested;

use cell::{BenchArgs, Row, cells, cores, csv_header, skip_reason, validate};
use measure::{
    Variant, measure_baseline, measure_loop, measure_loop_variants, measure_loops, scale_steps,
};
use report::{plots, write_markdown};
use rotorloop_common::rt::CpuDmaLatency;

/// Runs the bench.
pub fn run(a: &BenchArgs) -> anyhow::Result<()> {
    validate(a)?;
    if a.replot {
        let text = std::fs::read_to_string(a.out.join("bench.csv"))
            .with_context(|| format!("no bench.csv in {}", a.out.display()))?;
        let rows: Vec<Row> = text.lines().skip(1).filter_map(Row::parse).collect();
        // The machine the figures were taken on, from the invocation's own doctor.json.
        let note = match a.out.join("doctor.json") {
            d if d.is_file() => machine_note(a, &d, String::new()),
            _ => String::new(),
        };
        write_markdown(a, &rows, &note)?;
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
    rotorloop_common::outdir::OutDir::make(&a.out)
        .map(drop)
        .with_context(|| format!("cannot create {}", a.out.display()))?;
    let exe = std::env::current_exe().context("cannot find the rotorloop executable")?;
    let topology = crate::cpus::Topology::this_process();
    let ncores = topology.allowed.len();
    rotorloop_common::signals::install_signal_handlers();
    // Held to the end of the invocation, so the loop and every baseline run under it.
    let (_idle, idle_note) = hold_idle_states(a.cpu_dma_latency);

    // The machine state the figures were taken in; bench.md quotes what matters.
    let doctor = crate::doctor::write_into(&a.out, a.rates[0], a.seconds, Some(&topology.allowed));
    let idle_note = machine_note(a, &doctor, idle_note);
    let csv_path = a.out.join("bench.csv");
    rotorloop_common::outdir::write_file(&csv_path, format!("{}\n", csv_header()))?;
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
        rotorloop_common::outdir::OutDir::make(&dir).map(drop)?;
        let hog = if load == "other-core"
            && skip_reason("loop", *wait, placement, load, ncores).is_none()
        {
            // The hog on another CPU of the process's set than the loop's.
            let core = cores(placement, &topology)
                .and_then(|(p, _)| topology.allowed.iter().copied().find(|c| *c != p));
            let mut cmd = Command::new(&exe);
            cmd.args(["role", "hog"]).stdin(Stdio::null());
            if let Some(c) = core {
                cmd.args(["--core", &c.to_string()]);
            }
            Some(cmd.spawn().context("cannot start the CPU hog")?)
        } else {
            None
        };
        let mut measured = measure_repeated(a, &exe, &base, &topology, &dir)?;
        for n in scale_steps(a.loops) {
            measured.extend(measure_loops(a, &base, &topology, n)?);
        }
        if let Some(mut h) = hog {
            // SAFETY: signals our own child.
            unsafe { libc::kill(h.id() as libc::pid_t, libc::SIGTERM) };
            let _ = h.wait();
        }
        let mut f = rotorloop_common::outdir::append_file(&csv_path)?;
        for r in &measured {
            writeln!(f, "{}", r.csv())?;
        }
        rows.extend(measured);
        write_markdown(a, &rows, &idle_note)?;
    }
    if tty {
        eprintln!();
    }
    write_markdown(a, &rows, &idle_note)?;
    plots(a, &rows)?;
    println!("bench: {} measurements in {}", rows.len(), a.out.display());
    Ok(())
}

/// One cell's loop and baselines, `--repeat` times in turn (loop, baselines, loop, …; the
/// loop's variants once, first; the repetitions after the first in `DIR/repI`), with
/// each ratio's interval on the loop rows.
fn measure_repeated(
    a: &BenchArgs,
    exe: &std::path::Path,
    base: &Row,
    topology: &crate::cpus::Topology,
    dir: &std::path::Path,
) -> anyhow::Result<Vec<Row>> {
    let wait: rotorloop_common::ipc::wait::Wait =
        base.wait.parse().unwrap_or(rotorloop_common::ipc::wait::Wait::Event);
    let mut measured = Vec::new();
    for rep in 0..a.repeat {
        let d = match rep {
            0 => dir.to_owned(),
            r => dir.join(format!("rep{r}")),
        };
        rotorloop_common::outdir::OutDir::make(&d).map(drop)?;
        let mut these = match rep {
            0 => measure_loop_variants(a, base, topology, &d)?,
            _ => vec![measure_loop(a, base, topology, &d, Variant::Loop)?],
        };
        for b in &a.baselines {
            these.push(measure_baseline(exe, a, base, b, wait, &base.placement, topology, &d)?);
        }
        these.iter_mut().for_each(|r| r.repeat = rep);
        measured.extend(these);
        if shutdown_requested() {
            break;
        }
    }
    repeat::fill(&mut measured);
    Ok(measured)
}

/// The lines of the invocation's `doctor.json` that matter (what is not as a real-time
/// loop wants it), after the idle-state line, for bench.md; SCHED_FIFO's first, saying
/// at what priority the invocation ran.
fn machine_note(a: &BenchArgs, doctor: &std::path::Path, idle_note: String) -> String {
    let lines = crate::doctor::quoted_lines(doctor);
    let mut note = idle_note;
    if let Some(fifo) = lines.iter().find(|l| l.starts_with("sched_fifo")) {
        let ran = match a.rt_priority {
            Some(p) => format!("--rt-priority {p} asked, so the roles ran at normal priority"),
            None => "ran at normal priority".to_owned(),
        };
        note.push_str(&format!("\n\nSCHED_FIFO not available: {ran} ({fifo})."));
    }
    let others: Vec<&String> = lines.iter().filter(|l| !l.starts_with("sched_fifo")).collect();
    if !others.is_empty() {
        note.push_str("\n\nThis machine (`doctor.json`, `rotorloop doctor`), what is not as a real-time loop wants it:\n");
        for l in others {
            note.push_str(&format!("\n- {l}"));
        }
    }
    note
}

/// Holds `--cpu-dma-latency` where it is given, and says in a line of `bench.md` which idle
/// states the invocation ran under.
fn hold_idle_states(us: Option<u32>) -> (Option<CpuDmaLatency>, String) {
    let held = CpuDmaLatency::hold_or_warn(us);
    let note = match (&held, rotorloop_common::rt::cpu_dma_latency_now()) {
        (Some(h), _) => {
            format!(
                "CPU idle states: `/dev/cpu_dma_latency` held at {} µs for the invocation.",
                h.us()
            )
        }
        (None, Some(v)) => {
            format!("CPU idle states: as the machine has them (`/dev/cpu_dma_latency` {v} µs).")
        }
        (None, None) => "CPU idle states: as the machine has them.".to_owned(),
    };
    (held, note)
}
