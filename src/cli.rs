//! The `rotorloop` command line: argument types (clap derive) and the dispatch to the
//! library. `main.rs` only calls [`main`].

use rotorloop_common::graph::Role;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};
use glam::DVec3;
use rotorloop_common::scenario::Actuation;

use crate::sim::{self, SimOptions, summary_table};
use crate::study::gains;
use crate::study::montecarlo::{self, McOptions, McSummary};
use rotorloop_common::input::{number_in, whole_in};
use rotorloop_common::role::UsageError;
use rotorloop_common::role::args::{duration_s, rate_hz, scenario_with_overrides};
use rotorloop_plant::actuator::ActuationDelay;

/// Attitude tracking of a rigid body with three internal rotors (geometric PID,
/// almost-global), simulated and analysed.
#[derive(Debug, Parser)]
#[command(name = "rotorloop", version, about)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run one scenario in one process, faster than real time.
    Sim(SimArgs),
    /// The paper's three runs through the four processes (real time) and in process
    /// (control-effort comparison), with a report.
    Paper {
        /// Output directory: one sub-directory per run, plus report.md.
        #[arg(long, default_value = "out/paper")]
        out: PathBuf,
        /// Simulated seconds per run, 0.001 to 86400.
        #[arg(long, allow_hyphen_values = true, default_value_t = 30.0, value_parser = duration_s())]
        duration: f64,
        /// Tick rate (Hz), 1 to 100000.
        #[arg(long, allow_hyphen_values = true, default_value_t = 1000.0, value_parser = rate_hz())]
        rate: f64,
        /// Only the in-process simulator (no four-process runs).
        #[arg(long)]
        in_process: bool,
    },
    /// The paper's Appendix A gain bounds and the linearised closed-loop poles.
    Gains {
        /// Built-in scenario name or TOML path.
        #[arg(long, default_value = "paper-zero")]
        scenario: String,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Random initial attitudes and rates, including errors within 2° of 180°.
    Montecarlo(McArgs),
    /// The four processes over iceoryx2 shared memory, with the monitor's report.
    Run(crate::run::args::RunArgs),
    /// The latency study: the loop against same-invocation baselines, per cell.
    Bench(crate::study::bench::cell::BenchArgs),
    /// What this machine allows a real-time loop: CPUs, scheduling (whether SCHED_FIFO
    /// works, and why not), timers and idle states, memory, interference; each item with
    /// what it means for a loop at `--rate` and the command that changes it.
    Doctor(crate::doctor::DoctorArgs),
    /// Two run or bench directories side by side: the same figures, with their intervals
    /// where the benches measured repetitions (`bench --repeat`), a plain statement where not.
    Compare(crate::study::compare::CompareArgs),
    /// The rotorloop domains on this machine: roles with pid, core, policy, state, ticks,
    /// rate, and the services (read-only: no node, no port).
    Ps(crate::observe::ps::PsArgs),
    /// A live view of a running loop (passive: reads the roles' resume slots).
    Watch(crate::observe::watch::WatchArgs),
    /// Serve a running loop to Foxglove or Lichtblick (Foxglove WebSocket, default
    /// 127.0.0.1:8765): the state, torque, reference, latency, tracking and the attitudes
    /// in 3D, live (docs/foxglove.md).
    Foxglove(crate::observe::foxglove::FoxgloveArgs),
    /// How much actuation delay the loop tolerates: the linearised prediction per mode and
    /// a sweep of the nonlinear loop in process.
    Margin(crate::study::margin::MarginArgs),
    /// Remove what dead processes of a domain left in shared memory (and, when none of
    /// its processes is alive, the domain's last iceoryx2 file).
    Clean(crate::run::clean::CleanArgs),
    /// A finished run in the formats other tools read: `--mcap` writes `DIR/run.mcap`
    /// (Foxglove, Lichtblick), also for runs made before `run` wrote it.
    Export(crate::export::ExportArgs),
    /// The wire contract of the samples (docs/wire.md): its tables, JSON, the Python
    /// module (ctypes) or the C header, from the Rust types themselves.
    Wire(crate::export::wire::WireArgs),
    /// The report of a run whose launcher did not end normally (`kill -9` of `rotorloop
    /// run`): moves its flight records into the run directory and assembles the report from
    /// them, as the launcher would have.
    Recover {
        /// The run directory (the `--out` of `rotorloop run`).
        dir: PathBuf,
    },
    /// Why the ticks of a finished run were late and what it cost: its incidents again
    /// (`incidents.csv`, `incidents.md`, `incidents.png` in the run directory, the worst in
    /// `summary.json`), from its flight records, faults and `sched.csv`.
    Explain {
        /// The run directory (the `--out` of `rotorloop run`).
        dir: PathBuf,
        /// A plant wake or an answer this many ticks later than usual is abnormal, 0.001 to
        /// 100.
        #[arg(long, allow_hyphen_values = true, default_value_t = 0.25,
              value_parser = number_in(0.001, 100.0, "ticks"))]
        threshold_ticks: f64,
    },
    /// The link gateway of one host: carries a run domain's services to and from another
    /// host over Zenoh (the `rotorloop-link` binary; `rotorloop link --help` for its options).
    #[command(disable_help_flag = true)]
    Link {
        /// The gateway's arguments (`--domain D --listen|--connect ENDPOINT` …).
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Run one role of the loop in this process (what `run` starts; the `plant`,
    /// `reference`, `controller` and `monitor` binaries do the same).
    #[command(subcommand, hide = true)]
    Role(RoleCommand),
}

#[derive(Debug, Subcommand)]
enum RoleCommand {
    Plant(rotorloop_plant::process::args::PlantArgs),
    Reference(rotorloop_reference::process::args::ReferenceArgs),
    Controller(rotorloop_controller::process::args::ControllerArgs),
    Monitor(rotorloop_monitor::process::args::MonitorArgs),
    Pingpong(crate::baseline::pingpong::PingPongArgs),
    Hog(crate::baseline::pingpong::HogArgs),
    /// Sleep to the plant's grid and record the wake-up lateness (the bench's timer baseline).
    Timer(crate::baseline::timer::TimerArgs),
    /// Try to reach a run's services and files from outside; print what was granted.
    Probe(crate::baseline::probe::ProbeArgs),
}

#[derive(Debug, clap::Args)]
struct SimArgs {
    /// A built-in scenario (`paper-zero`, `paper-constant`, `paper-sinusoid`,
    /// `disturbance-pid`, `disturbance-pd`, `saturation-antiwindup`, `saturation-windup`)
    /// or the path of a TOML file.
    #[arg(long, required_unless_present = "replay")]
    scenario: Option<String>,
    /// Simulated seconds, 0.001 to 86400 (default: the scenario's, 30).
    #[arg(long, allow_hyphen_values = true, value_parser = duration_s())]
    duration: Option<f64>,
    /// Tick rate in Hz, 1 to 100000 (default: the scenario's, 1000).
    #[arg(long, allow_hyphen_values = true, value_parser = rate_hz())]
    rate: Option<f64>,
    /// `internal` (rotors) or `external` (gas jets) (default: the scenario's).
    #[arg(long)]
    actuation: Option<Actuation>,
    /// Switch the controller off and hold this rotor torque (N m): U1,U2,U3.
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    open_loop: Option<DVec3>,
    /// Write every N-th tick to trace.csv (the last tick always), 1 or more.
    #[arg(long, allow_hyphen_values = true, default_value_t = 1,
          value_parser = whole_in(1u64, u64::MAX, "ticks"))]
    trace_every: u64,
    /// Skip the PNG figures.
    #[arg(long)]
    no_figures: bool,
    /// Step the reference on the loop's thread (by default it runs ahead on a second
    /// thread: it depends on nothing the loop does); the rows are the same either way.
    #[arg(long)]
    one_thread: bool,
    /// Each torque takes effect this many seconds after its tick's time (delayed
    /// zero-order hold; 0 to 3600, longer than a tick is a queue; 0: the plain hold).
    #[arg(long, allow_hyphen_values = true, default_value = "0", conflicts_with = "delay_from")]
    actuation_delay: String,
    /// Draw each torque's delay from a measured latency distribution: a `.hgrm` file such
    /// as a real-time run's `sense_to_actuate.hgrm` (µs), with `--seed`.
    #[arg(long)]
    delay_from: Option<PathBuf>,
    /// Seed of the delays drawn with `--delay-from`, 0 to 2⁶⁴ − 1.
    #[arg(long, allow_hyphen_values = true, default_value_t = 1,
          value_parser = whole_in(0u64, u64::MAX, "seeds"))]
    seed: u64,
    /// Re-run a finished real-time run DIR (its `summary.json`, `trace.csv`, `timing.csv`)
    /// in process, with each torque taking effect where and when it did there; writes the
    /// same `trace.csv` and says whether it is identical (exit 1 when it is not).
    #[arg(long, conflicts_with_all = ["scenario", "open_loop", "delay_from"])]
    replay: Option<PathBuf>,
    /// With `--replay`: compare each replayed row with the run's and write only
    /// `replay.json`, no `trace.csv` or `run.mcap` (a long run's replay would write about
    /// 1 MB per second of run).
    #[arg(long, requires = "replay")]
    compare_only: bool,
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
}

#[derive(Debug, clap::Args)]
struct McArgs {
    /// Number of runs, 1 to 100000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 100,
          value_parser = whole_in(1u64, 100_000, "runs"))]
    runs: u64,
    /// RNG seed, 0 to 2⁶⁴ − 1.
    #[arg(long, allow_hyphen_values = true, default_value_t = 1,
          value_parser = whole_in(0u64, u64::MAX, "seeds"))]
    seed: u64,
    /// Base scenario (bodies, reference, gains).
    #[arg(long, default_value = "paper-zero")]
    scenario: String,
    /// Simulated seconds per run, 0.001 to 86400.
    #[arg(long, allow_hyphen_values = true, default_value_t = 60.0, value_parser = duration_s())]
    duration: f64,
    /// Tick rate (Hz), 1 to 100000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 1000.0, value_parser = rate_hz())]
    rate: f64,
    /// Every N-th run starts within 2° of a 180° error, 1 or more.
    #[arg(long, allow_hyphen_values = true, default_value_t = 3,
          value_parser = whole_in(1u64, u64::MAX, "runs"))]
    near_pi_every: u64,
    /// Largest |IΩ(0)| and |Ω_r(0)| component drawn, 0.001 to 1000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 3.0,
          value_parser = number_in(0.001, 1000.0, "N m s and rad/s"))]
    max_rate: f64,
    /// Output directory.
    #[arg(long)]
    out: PathBuf,
}

fn parse_vec3(s: &str) -> Result<DVec3, String> {
    let parts: Vec<&str> = s.split(',').collect();
    let vals: Result<Vec<f64>, _> = parts.iter().map(|p| p.trim().parse::<f64>()).collect();
    match vals {
        Ok(v) if v.len() == 3 && v.iter().all(|x| x.is_finite() && x.abs() <= 1e6) => {
            Ok(DVec3::new(v[0], v[1], v[2]))
        }
        _ => Err(format!(
            "`{s}` is not allowed: three finite numbers of magnitude ≤ 1e6 separated by commas, e.g. 0.1,-0.2,0"
        )),
    }
}

/// Parses the command line, runs, prints errors with their chain, and returns the exit
/// code (docs/running.md, "Exit codes"): 0 success; 1 the command failed on its own (a
/// role beyond its restart policy, a write that failed midway); 2 the input is the user's
/// to mend (a flag's value, the scenario, a file or directory named on the command line
/// that is missing, unreadable or damaged, an `--out` that cannot be made, a run that
/// diverged); 3 `run` stopped by a signal.
pub fn main() -> ExitCode {
    rotorloop_common::ipc::quiet_iceoryx_logs();
    let cli = Cli::parse();
    // Output that nobody reads never stops the loop (see `relay`). Not for `link`, which
    // becomes the `rotorloop-link` binary (exec), and relays its own.
    let relay = match cli.command {
        Command::Link { .. } => rotorloop_common::relay::Stdio::none(),
        Command::Run(_) => rotorloop_common::relay::Stdio::relay_terminals_too(),
        _ => rotorloop_common::relay::Stdio::relay(),
    };
    let code = dispatch(cli);
    relay.finish();
    code
}

/// Runs a role or a command, and maps its end to the exit code.
fn dispatch(cli: Cli) -> ExitCode {
    use rotorloop_common::role::run_role;
    use rotorloop_controller::process as controller;
    use rotorloop_monitor::process as monitor;
    use rotorloop_plant::process as plant;
    use rotorloop_reference::process as reference;
    if let Command::Role(role) = &cli.command {
        return match role {
            RoleCommand::Plant(a) => run_role(Role::Plant.name(), a, plant::run),
            RoleCommand::Reference(a) => run_role(Role::Reference.name(), a, reference::run),
            RoleCommand::Controller(a) => run_role(Role::Controller.name(), a, controller::run),
            RoleCommand::Monitor(a) => run_role(Role::Monitor.name(), a, monitor::run),
            RoleCommand::Pingpong(a) => run_role("pingpong", a, crate::baseline::pingpong::run),
            RoleCommand::Hog(a) => run_role("hog", a, crate::baseline::pingpong::hog),
            RoleCommand::Timer(a) => run_role("timer", a, crate::baseline::timer::run),
            RoleCommand::Probe(a) => run_role("probe", a, crate::baseline::probe::run),
        };
    }
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            if rotorloop_common::role::is_usage_error(&e) {
                ExitCode::from(2)
            } else if e.downcast_ref::<crate::run::launch::RunEnd>().is_some() {
                ExitCode::from(3)
            } else {
                ExitCode::FAILURE
            }
        }
    }
}

fn print_warnings(w: &[String]) {
    for w in w {
        eprintln!("warning: {w}");
    }
}

/// The output directory a command writes into, if any.
fn out_dir(command: &Command) -> Option<&std::path::Path> {
    match command {
        Command::Sim(a) => Some(&a.out),
        Command::Paper { out, .. } => Some(out),
        Command::Montecarlo(a) => Some(&a.out),
        Command::Run(a) => Some(&a.out),
        Command::Bench(a) => Some(&a.out),
        Command::Margin(a) => Some(&a.out),
        _ => None,
    }
}

/// The finished run a command reads (`explain`, `recover`, `export`, `sim --replay`): an
/// existing directory, or exit 2 naming it, the same for every command (`export` gave 1).
fn run_dir(command: &Command) -> Option<&std::path::Path> {
    match command {
        Command::Explain { dir, .. } | Command::Recover { dir } => Some(dir),
        Command::Export(a) => Some(&a.dir),
        Command::Sim(a) => a.replay.as_deref(),
        _ => None,
    }
}

/// What every command checks of the paths it is given before it starts (exit 2): the run
/// directory it reads exists, and the output directory can be made or written into.
fn check_paths(command: &Command) -> Result<(), UsageError> {
    if let Some(dir) = run_dir(command) {
        let why = match std::fs::metadata(dir) {
            Ok(m) if m.is_dir() => None,
            Ok(_) => Some("; this is not a directory".to_owned()),
            Err(e) => Some(format!(": {e}")),
        };
        if let Some(why) = why {
            let d = dir.display();
            let what = "a run directory (the --out of `rotorloop run`)";
            return Err(UsageError(format!("{d} is not allowed: {what}{why}")));
        }
    }
    if let Some(out) = out_dir(command) {
        rotorloop_common::input::check_out_dir(out)
            .map_err(|why| UsageError(format!("--out {} is not allowed: {why}", out.display())))?;
    }
    Ok(())
}

/// A command that reads a run directory named on the command line: a flight record in it
/// that is damaged or of another build is the input's fault (exit 2, as docs/running.md's
/// table says), not the command's.
fn damaged_is_input<T>(r: anyhow::Result<T>) -> anyhow::Result<T> {
    use rotorloop_common::flight::FlightError;
    r.map_err(|e| {
        let damaged =
            e.chain().any(|c| matches!(c.downcast_ref(), Some(FlightError::Foreign { .. })));
        if damaged { UsageError(format!("{e:#}")).into() } else { e }
    })
}

/// Runs a parsed command line.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    check_paths(&cli.command)?;
    match cli.command {
        Command::Sim(a) => sim_command(&a)?,
        Command::Paper { out, duration, rate, in_process } => {
            crate::study::paper::run(&out, duration, rate, in_process)?
        }
        Command::Gains { scenario, json } => {
            let s =
                rotorloop_common::scenario::Scenario::load(&scenario).map_err(UsageError::from)?;
            print_warnings(&s.warnings);
            let r = gains::analyse(&s);
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                print!("{}", gains::render(&r));
            }
        }
        Command::Run(a) => {
            // Who may watch (loopback unless the user means it): a rule of the command line.
            if let Some(addr) = &a.foxglove {
                let allowed = a.foxglove_allow_network;
                crate::observe::foxglove::check_reach(
                    addr,
                    "--foxglove",
                    allowed,
                    "--foxglove-allow-network",
                )?;
            }
            crate::run::launch::run(&a)?
        }
        Command::Link { args } => crate::run::split::exec_link(&args)?,
        Command::Bench(a) => crate::study::bench::run(&a)?,
        Command::Ps(a) => crate::observe::ps::ps(&a)?,
        Command::Doctor(a) => crate::doctor::run(&a)?,
        Command::Compare(a) => crate::study::compare::run(&a)?,
        Command::Watch(a) => crate::observe::watch::watch(&a)?,
        Command::Foxglove(a) => crate::observe::foxglove::run(&a)?,
        Command::Margin(a) => {
            crate::study::margin::run(&a)?;
            println!("output: {}", a.out.display());
        }
        Command::Role(_) => unreachable!("handled in main"),
        Command::Clean(a) => crate::run::clean::run(&a)?,
        Command::Recover { dir } => damaged_is_input(crate::run::recover::run(&dir))?,
        Command::Explain { dir, threshold_ticks } => {
            damaged_is_input(explain_command(&dir, threshold_ticks))?
        }
        Command::Export(a) => damaged_is_input(crate::export::run(&a))?,
        Command::Wire(a) => crate::export::wire::run(&a)?,
        Command::Montecarlo(a) => montecarlo_command(&a)?,
    }
    Ok(())
}

/// `rotorloop explain DIR`.
fn explain_command(dir: &std::path::Path, threshold_ticks: f64) -> anyhow::Result<()> {
    let options = crate::pipeline::incidents::Options { threshold_ticks };
    let found = crate::pipeline::incidents::explain(dir, options)?;
    println!("{}: {}", dir.display(), found.describe_worst());
    println!("incidents: {}", dir.join("incidents.md").display());
    Ok(())
}

/// `rotorloop sim`: a replay, or an in-process run of a scenario.
fn sim_command(a: &SimArgs) -> anyhow::Result<()> {
    if let Some(dir) = &a.replay {
        let r = damaged_is_input(crate::sim::replay::run(dir, &a.out, !a.compare_only))?;
        println!("{}", r.describe());
        if !a.compare_only {
            crate::export::mcap_after_run(&a.out, false);
        }
        // Like `cmp`: a script sees a replay that differs by its exit code (1), with the
        // files written all the same.
        anyhow::ensure!(
            r.identical,
            "the replay is not the run's trace; {} says where",
            a.out.join("replay.json").display()
        );
        return Ok(());
    }
    let name = a.scenario.as_deref().unwrap_or_default();
    let scenario = scenario_with_overrides(name, a.duration, a.rate, a.actuation)?;
    print_warnings(&scenario.warnings);
    let delay = a.actuation_delay.parse().map_err(|e: String| {
        UsageError(format!("--actuation-delay {e}").replace("`measured`, or seconds", "seconds"))
    })?;
    if delay == ActuationDelay::Measured {
        return Err(UsageError(
            "--actuation-delay measured is for real-time runs; sim takes SECONDS".into(),
        )
        .into());
    }
    let drawn = a.delay_from.as_deref().map(|p| sim::drawn_delays(p, a.seed)).transpose()?;
    let opts = SimOptions {
        scenario,
        open_loop: a.open_loop,
        trace_every: a.trace_every,
        out: a.out.clone(),
        figures: !a.no_figures,
        progress: true,
        delay,
        drawn,
        one_thread: a.one_thread,
    };
    let (summary, _) = sim::run(&opts).with_context(|| format!("sim of {name}"))?;
    print!("{}", summary_table(&summary));
    crate::export::mcap_after_run(&a.out, false);
    println!("  {:<28} {}", "output", a.out.display());
    Ok(())
}

/// `rotorloop montecarlo`: many in-process runs from random initial attitudes.
fn montecarlo_command(a: &McArgs) -> anyhow::Result<()> {
    let scenario = scenario_with_overrides(&a.scenario, Some(a.duration), Some(a.rate), None)?;
    let opts = McOptions {
        scenario,
        runs: a.runs as usize,
        seed: a.seed,
        near_pi_every: a.near_pi_every as usize,
        max_rate: a.max_rate,
        threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
        out: Some(a.out.clone()),
    };
    let (s, _) = montecarlo::run(&opts)?;
    let McSummary { runs, near_pi_runs, closest_to_pi_deg: closest, duration_s, rate_hz, .. } = s;
    let (converged, worst) = (100.0 * s.fraction_converged, s.worst_final_err_deg);
    let (limit, out) = (montecarlo::CONVERGED_DEG, a.out.display());
    println!(
        "{runs} runs ({near_pi_runs} within 2° of 180°, closest {closest:.3}° from it), \
         {duration_s} s each at {rate_hz} Hz\nconverged (final error < {limit}°): {converged:.1} %\n\
         worst final error: {worst:.3e}°\noutput: {out}"
    );
    Ok(())
}
