//! `rotorloop run`'s arguments, its `--preset` and `--pin`.

use std::collections::BTreeMap;
use std::path::PathBuf;

use clap::Args;

use rotorloop_common::graph::Role;
use rotorloop_common::ipc::wait::Wait;

use crate::cpus::{Shape, Topology, run_topology};

use rotorloop_common::input::whole_in;
use rotorloop_common::role::UsageError;
use rotorloop_common::role::args::{RoleArgs, with_defaults};
use rotorloop_common::role::args::{dma_latency_us, hold_ticks, spin_us};
use rotorloop_plant::actuator::ActuationDelay;

/// `rotorloop run` arguments.
#[derive(Debug, Clone, Args)]
pub struct RunArgs {
    /// What every role takes, passed on to each.
    #[command(flatten)]
    pub role: RoleArgs,
    /// Cores per role, e.g. `plant=0,controller=1,reference=0,monitor=1`: CPUs of the
    /// run's set (`--cpus`, else the launcher's own CPU set).
    #[arg(long)]
    pub pin: Option<String>,
    /// The run's CPU set, a CPU list such as `2-5` or `4,6` (CPUs 0 to 4095, each in the
    /// launcher's own CPU set: `taskset`, a cgroup's cpuset): every role (and gateway)
    /// runs on these CPUs only, and `--pin` and `--preset` place the roles inside them.
    /// Several runs started with disjoint `--cpus` never share a core (default: the
    /// launcher's own CPU set).
    #[arg(long, allow_hyphen_values = true, value_name = "LIST")]
    pub cpus: Option<String>,
    /// Output directory of the monitor's report.
    #[arg(long)]
    pub out: PathBuf,
    /// Run without the monitor (no report; for measuring what the monitor costs).
    #[arg(long)]
    pub no_monitor: bool,
    /// No status line and no per-run console summary.
    #[arg(long)]
    pub quiet: bool,
    /// Run without flight recorders (each role's record of what it published, in
    /// `OUT/flight`): the report is then only the monitor's live view, which a monitor
    /// kill or a monitor falling behind leaves incomplete. For measuring what the
    /// recorders cost (`bench --before-after`).
    #[arg(long)]
    pub no_record: bool,
    /// Run even where the estimate of what the run writes (printed before it starts)
    /// exceeds the free space of `--out`'s filesystem or of `/dev/shm` (a full disk stops
    /// the files, never the loop).
    #[arg(long)]
    pub force: bool,
    /// Do not write `OUT/run.mcap` at the end (`rotorloop export OUT --mcap` writes it
    /// later from the records).
    #[arg(long)]
    pub no_mcap: bool,
    /// Write no `OUT/trace.csv` or `OUT/timing.csv`, and the scheduler samples compressed
    /// (`OUT/sched.csv.zst`): for a long run, whose whole output is then mostly its packed
    /// flight records (measured: 0.26 MB a second at 1 kHz in real time). `rotorloop
    /// export OUT --csv` derives the two files from the records when wanted; `sim
    /// --replay` and `export --mcap` read the records directly.
    #[arg(long)]
    pub no_csv: bool,
    /// The flight records raw, not packed (the segments moved during the run, the rings
    /// at its end): to measure what packing costs the loop (`bench --before-after pack`),
    /// and for tests that write into a record's slots.
    #[arg(long, hide = true)]
    pub raw_segments: bool,
    /// No journal of the newest ticks (`OUT/flight/*.journal`, made durable every 200 ms):
    /// a machine crash then loses what is on tmpfs. Only to measure what the journal costs
    /// the loop (`bench --before-after journal`).
    #[arg(long, hide = true)]
    pub no_journal: bool,
    /// Do not sample each role's scheduling (`/proc/PID/schedstat`, its state, the steal
    /// time) into `OUT/sched.csv`: the incidents then lack the kernel's view. For
    /// measuring what the sampling costs (`bench --before-after sched`).
    #[arg(long)]
    pub no_sched_sample: bool,
    /// The plant's tick loop without the lockstep fault gate's check (`plant --no-gate`),
    /// to measure what the gate costs (`bench --before-after gate`). Refused with a
    /// `--fault` in lockstep, which needs the gate.
    #[arg(long, hide = true)]
    pub no_gate: bool,
    /// Record the kernel's scheduler (`sched_switch`, `sched_wakeup`) and IRQ events during
    /// the run into `OUT/sched-trace.txt`, from a tracefs instance of its own (mounted
    /// when needed, torn down at the end), so that an incident names what ran instead of
    /// the late process. Needs root.
    #[arg(long)]
    pub trace_sched: bool,
    /// Real time: the plant sleeps until this many µs before each grid time and spins
    /// the rest (sharper ticks, one core busier), 0 to 1000000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 0, value_parser = spin_us())]
    pub spin_before_tick_us: u64,
    /// Hold `/dev/cpu_dma_latency` at this many µs while it runs: no CPU enters an idle
    /// state that takes longer to leave (0: idle CPUs poll instead of halting, as
    /// cyclictest asks by default; sharper timer wake-ups on a VM, idle cores kept busy).
    /// Needs root; without it a warning, and the idle states stay as they are. 0 to
    /// 1000000.
    #[arg(long, allow_hyphen_values = true, value_parser = dma_latency_us())]
    pub cpu_dma_latency: Option<u32>,
    /// Start this command in the built-in controller's place (a controller of your own,
    /// in any language: docs/wire.md): split into words, no shell; the built-in
    /// controller's arguments are appended and the run is in its environment
    /// (`run::external`). Supervised, pinned and faulted like the built-in one.
    #[arg(long, value_name = "COMMAND")]
    pub controller_cmd: Option<String>,
    /// Serve the running loop to Foxglove or Lichtblick on `ADDR` (default
    /// 127.0.0.1:8765): `rotorloop foxglove` started beside the loop, stopped at its end
    /// (docs/foxglove.md). Loopback only, where any user of this machine may watch; another
    /// address needs `--foxglove-allow-network`. A port you name that is taken is an error
    /// (exit 2); the default port taken, the loop goes on without a live view. It reads like
    /// the monitor and never holds the loop up; a viewer gone or the server killed is no
    /// matter to the loop.
    #[arg(long, num_args = 0..=1, default_missing_value = crate::observe::foxglove::DEFAULT_ADDR, value_name = "ADDR")]
    pub foxglove: Option<String>,
    /// Let `--foxglove` serve on an address that is not loopback: anyone who can reach it
    /// watches the loop, with no authentication. Refused without this flag (exit 2).
    #[arg(long, requires = "foxglove")]
    pub foxglove_allow_network: bool,
    /// Real time: ticks the plant holds the last torque before safe mode, 0 to 1000000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 50, value_parser = hold_ticks())]
    pub hold_ticks: u64,
    /// Inject a fault (each kind, its syntax and its help: `run::fault::KINDS`).
    #[arg(long, help = crate::run::fault::help())]
    pub fault: Vec<String>,
    /// Inject a corrupted sample: `ROLE:KIND@TICK` makes ROLE (plant, reference or
    /// controller) publish tick TICK with a NaN (`nan`), an infinity (`inf`), an absurd
    /// 1e12 (`huge`) or, for plant and reference, a non-rotation attitude (`skew`).
    /// The receivers must reject it. Repeatable.
    #[arg(long)]
    pub corrupt: Vec<String>,
    /// When a torque takes effect in the plant: `measured` (when it arrives: the loop's
    /// real latency, delayed zero-order hold; in lockstep at its own tick's time), `0` (at
    /// the start of the tick it arrives in: the plain zero-order hold), or SECONDS after
    /// its tick's time (a fixed delay of any length, never before it arrives).
    #[arg(long, default_value = "measured", allow_hyphen_values = true)]
    pub actuation_delay: ActuationDelay,
    /// Real time, when the plant process wakes more than a quarter tick late (a simulator
    /// stall, not the loop's latency): `hold` (the world's clock goes on and the torque in
    /// force acts all that time, the default) or `pause` (the world's clock stands still
    /// while the simulator is late: only the loop after the plant's publish shapes the
    /// physics). docs/incidents.md.
    #[arg(long, default_value = "hold")]
    pub plant_stall: rotorloop_plant::process::args::PlantStall,
    /// Restart policy for a role that exits abnormally, is killed by anyone or hangs:
    /// `on-failure`, `always` (also after a clean exit before the run's end) or `never`,
    /// for every role, per role (`monitor=always,plant=never`), or both (`never,monitor=always`).
    #[arg(long, default_value = "on-failure")]
    pub restart: String,
    /// Restart intensity limit `N/SECONDS`: a role restarted more than N times within that
    /// many seconds stops the run (the monitor is then given up instead; the loop goes on).
    #[arg(long, default_value = "5/10", allow_hyphen_values = true)]
    pub restart_limit: String,
    /// A role with work waiting that makes no progress (its resume slot does not move) for
    /// this many milliseconds is killed and restarted by its policy (0: no watchdog), 0 to
    /// 3600000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 3000,
          value_parser = whole_in(0u64, 3_600_000, "ms"))]
    pub watchdog_ms: u64,
    /// `dedicated`: every role on a core of its own (four of the run's CPUs, `--cpus`:
    /// isolated ones first, CPU 0 last, one hyperthread per physical core), every role
    /// busy-waiting (`--wait spin`), the plant spinning the last 50 µs before each tick
    /// (sharp ticks on a VM whose timer wake-ups are late), and `--cpu-dma-latency 0`. Needs 4 cores. A `--pin`, a
    /// `--spin-before-tick-us` other than 0 or a `--wait` other than `event` (the
    /// defaults, which the preset replaces) wins.
    #[arg(long)]
    pub preset: Option<String>,
    /// Run over two "hosts" joined by link gateways (Zenoh on loopback): `ROLES@HOST ...`,
    /// e.g. `plant,reference,monitor@a controller@b`. Each host has its own iceoryx2
    /// space; the gateways (`link-a`, `link-b`) are supervised and can take faults
    /// (`--fault link-b:kill@2:restart@3`). Needs the `rotorloop-link` binary beside this
    /// one (`cargo build --release --workspace`).
    #[arg(long)]
    pub split: Option<String>,
    /// Split: the loopback port of the listening gateway (default: a free one the
    /// launcher draws). For the tests of a port another process took first.
    #[arg(long, hide = true)]
    pub link_port: Option<u16>,
}

/// The cores of the `dedicated` preset among the CPUs of `t`: plant, controller,
/// reference, monitor, each on a core of its own ([`crate::cpus::place`]: isolated
/// CPUs first, CPU 0 last, one hyperthread per physical core while they suffice), or why
/// there are not enough.
pub fn dedicated_cores(t: &Topology) -> Result<[usize; 4], String> {
    let n = t.allowed.len();
    if n < 4 {
        return Err(format!("dedicated needs 4 cores (one per role); this machine has {n}"));
    }
    let placed = crate::cpus::place(t, 1, Shape::Dedicated);
    Ok(placed.loops[0].roles.unwrap_or([0; 4]))
}

/// Applies `--preset` (`dedicated`) to what the command line left unsaid.
/// Refuses first what `run` does not honour ([`check_role_flags`]).
pub(crate) fn with_preset(args: &RunArgs, explicit_wait: bool) -> Result<RunArgs, UsageError> {
    check_role_flags(args)?;
    let mut a = args.clone();
    match args.preset.as_deref() {
        None => {}
        Some("dedicated") => {
            // Its cores: [`pins`].
            dedicated_cores(&run_topology(args.cpus.as_deref())?)
                .map_err(|e| UsageError(format!("--preset {e}")))?;
            if !explicit_wait {
                a.role.wait = Wait::Spin;
            }
            if a.spin_before_tick_us == 0 {
                a.spin_before_tick_us = 50;
            }
            a.cpu_dma_latency.get_or_insert(0);
        }
        Some(other) => {
            return Err(UsageError(format!("--preset `{other}` is not allowed: dedicated")));
        }
    }
    check_spin_priority(&a)?;
    Ok(a)
}

/// Refuses spin waits at a real-time priority on fewer CPUs than the four roles: a role
/// that never sleeps at SCHED_FIFO keeps every other role off its core. On 2 vCPUs
/// (`bench --wait spin --rt-priority 80`) the reference was killed as hung after 3 s and a
/// run of 5 s lasted 859 s.
pub(crate) fn check_spin_priority(a: &RunArgs) -> Result<(), UsageError> {
    let (Wait::Spin, Some(p)) = (a.role.wait, a.role.rt_priority) else { return Ok(()) };
    let n = run_topology(a.cpus.as_deref())?.allowed.len();
    if n >= 4 {
        return Ok(());
    }
    Err(UsageError(format!(
        "--wait spin is not allowed with --rt-priority {p} on {n} CPU(s): the four roles would \
         spin at SCHED_FIFO and never sleep, and a role whose CPU another holds would not run; \
         use --wait event or hybrid, or run on 4 CPUs or more"
    )))
}

impl RunArgs {
    /// The defaults of every launcher option, for `role` into `out` (paper, bench).
    pub fn defaults(role: RoleArgs, out: PathBuf) -> Self {
        // The two options that have no default are given, then replaced.
        Self { role, out, ..with_defaults(&["--scenario=", "--out=."]) }
    }
}

/// Refuses the flags `run` shares with the roles (`RoleArgs`) but does not honour, which
/// were accepted and ignored: `--core` (the launcher pins each role with `--pin`) and
/// `--host` (the launcher places roles on hosts with `--split`; the roles ran in the
/// domain without a host while the launcher made and cleaned the host's, which was left
/// behind).
pub(crate) fn check_role_flags(a: &RunArgs) -> Result<(), UsageError> {
    if let Some(core) = a.role.core {
        return Err(UsageError(format!(
            "--core {core} is not allowed with `rotorloop run`: it pins each role with --pin \
             ROLE=CORE,… (--core is for a role started by hand)"
        )));
    }
    if a.no_csv && a.no_record {
        return Err(UsageError(
            "--no-csv is not allowed with --no-record: the trace would be written nowhere \
             (--no-csv derives it from the flight records)"
                .into(),
        ));
    }
    if let Some(host) = &a.role.host {
        return Err(UsageError(format!(
            "--host {host} is not allowed with `rotorloop run`: it places roles on hosts with \
             --split \"ROLES@HOST ROLES@HOST\" (--host is for a role or gateway started by hand)"
        )));
    }
    Ok(())
}

/// The roles' cores among the run's CPUs `t`: `--pin`, or where it is not given the
/// `dedicated` preset's ([`dedicated_cores`]), or none.
pub(crate) fn pins(args: &RunArgs, t: &Topology) -> Result<BTreeMap<Role, usize>, UsageError> {
    if let Some(p) = &args.pin {
        return parse_pins(p, &t.allowed);
    }
    if args.preset.as_deref() != Some("dedicated") {
        return Ok(BTreeMap::new());
    }
    let cores = dedicated_cores(t).map_err(|e| UsageError(format!("--preset {e}")))?;
    Ok(DEDICATED_ORDER.into_iter().zip(cores).collect())
}

/// The roles in the order of [`dedicated_cores`] and of `cpus.json`'s `pin` of a preset.
const DEDICATED_ORDER: [Role; 4] = [Role::Plant, Role::Controller, Role::Reference, Role::Monitor];

/// The pins as `cpus.json` writes them: `--pin` as given, or the preset's
/// (`plant=…,controller=…,reference=…,monitor=…`).
pub(crate) fn pin_text(args: &RunArgs, pins: &BTreeMap<Role, usize>) -> Option<String> {
    let preset = || {
        let each = DEDICATED_ORDER.iter().filter_map(|r| pins.get(r).map(|c| format!("{r}={c}")));
        Some(each.collect::<Vec<_>>().join(",")).filter(|t| !t.is_empty())
    };
    args.pin.clone().or_else(preset)
}

/// Parses `--pin`: `role=core` pairs separated by commas, each role at most once, each
/// core one of `allowed` (the run's CPUs).
pub fn parse_pins(s: &str, allowed: &[usize]) -> Result<BTreeMap<Role, usize>, UsageError> {
    let mut pins = BTreeMap::new();
    for part in s.split(',').filter(|p| !p.is_empty()) {
        let (role, core) = part.split_once('=').ok_or_else(|| {
            UsageError(format!("--pin `{part}` is not allowed: role=core, e.g. plant=0"))
        })?;
        let Ok(parsed) = role.parse::<Role>() else {
            return Err(UsageError(format!(
                "--pin role `{role}` is not allowed: plant, reference, controller or monitor"
            )));
        };
        let core: usize = core.parse().ok().filter(|c| allowed.contains(c)).ok_or_else(|| {
            UsageError(format!(
                "--pin {role}=`{core}` is not allowed: a CPU of the run's set ({})",
                crate::cpus::format_list(allowed)
            ))
        })?;
        if let Some(first) = pins.insert(parsed, core) {
            return Err(UsageError(format!(
                "--pin {role}={core} is not allowed: {role} is already pinned ({role}={first}); \
                 each role at most once"
            )));
        }
    }
    Ok(pins)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The launcher options `paper` and `bench` start a run with are the command line's
    /// defaults, the role's options as given.
    #[test]
    fn the_defaults_are_the_command_line_s() {
        use rotorloop_common::role::args::Mode;
        let role = RoleArgs::realtime("-odd name", 2.0, 500.0, Wait::Spin);
        assert_eq!(
            (role.scenario.as_str(), role.duration, role.rate),
            ("-odd name", Some(2.0), Some(500.0))
        );
        assert_eq!(
            (role.mode, role.wait, role.flight_ring_ticks),
            (Mode::Realtime, Wait::Spin, rotorloop_common::flight::DEFAULT_RING_TICKS)
        );
        assert_eq!((role.domain, role.record, role.hooks), (None, None, Default::default()));
        let a = RunArgs::defaults(RoleArgs::realtime("x", 1.0, 1000.0, Wait::Event), "o".into());
        assert_eq!((a.out.to_str(), a.role.scenario.as_str()), (Some("o"), "x"));
        assert_eq!((a.hold_ticks, a.watchdog_ms, a.spin_before_tick_us), (50, 3000, 0));
        assert_eq!((a.restart.as_str(), a.restart_limit.as_str()), ("on-failure", "5/10"));
        assert_eq!(a.actuation_delay, ActuationDelay::Measured);
        assert!(a.pin.is_none() && a.fault.is_empty() && !a.no_monitor && !a.no_record);
    }

    /// `--pin plant=0,plant=1` was accepted and the last one won.
    #[test]
    fn a_role_is_pinned_at_most_once() {
        let e = parse_pins("plant=0,controller=0,plant=0", &[0, 1]).expect_err("plant twice").0;
        assert!(e.starts_with("--pin plant=0 is not allowed: plant is already pinned"), "{e}");
        let pins = parse_pins("plant=0,controller=0", &[0, 1]).expect("once each");
        assert_eq!(pins.len(), 2);
    }

    /// `--preset dedicated` pins each role to a core of its own, typed; `cpus.json` writes
    /// them as the preset's text, and a `--pin` given as it was given.
    #[test]
    fn the_dedicated_preset_gives_typed_pins_and_a_given_pin_wins() {
        use clap::Parser;
        #[derive(Debug, Parser)]
        struct Cli {
            #[command(flatten)]
            run: RunArgs,
        }
        let parse = |extra: &[&str]| {
            let base = ["x", "--scenario", "paper-zero", "--out", "o", "--preset", "dedicated"];
            Cli::parse_from(base.iter().chain(extra)).run
        };
        let t = Topology { allowed: vec![0, 1, 2, 3], isolated: vec![], siblings: vec![] };
        let a = parse(&[]);
        let p = pins(&a, &t).expect("4 cores");
        assert_eq!(p.len(), 4);
        assert!(p.values().collect::<std::collections::BTreeSet<_>>().len() == 4, "{p:?}");
        let text = pin_text(&a, &p).expect("the preset's");
        assert!(text.starts_with("plant=") && text.contains(",monitor="), "{text}");
        assert_eq!(parse_pins(&text, &t.allowed).expect("reads back"), p);
        let given = parse(&["--pin", "controller=1,plant=2"]);
        let p = pins(&given, &t).expect("given");
        assert_eq!((p[&Role::Plant], p[&Role::Controller], p.len()), (2, 1, 2));
        assert_eq!(pin_text(&given, &p).as_deref(), Some("controller=1,plant=2"));
    }

    /// With `--cpus 2-3` a pin outside the run's set is refused, naming the set.
    #[test]
    fn a_pin_stays_inside_the_run_cpus() {
        let e = parse_pins("plant=1", &[2, 3]).expect_err("outside").0;
        assert!(
            e.starts_with("--pin plant=`1` is not allowed: a CPU of the run's set (2-3)"),
            "{e}"
        );
        assert!(parse_pins("plant=3,controller=2", &[2, 3]).is_ok());
    }

    /// `run --core N` was accepted and ignored (the launcher pins with `--pin`).
    #[test]
    fn run_refuses_the_core_and_host_of_a_role_started_by_hand() {
        use clap::Parser;
        #[derive(Debug, Parser)]
        struct Cli {
            #[command(flatten)]
            run: RunArgs,
        }
        let parse = |extra: &[&str]| {
            let mut argv = vec!["run", "--scenario", "paper-zero", "--out", "o"];
            argv.extend(extra);
            Cli::try_parse_from(argv).expect("parses").run
        };
        assert!(check_role_flags(&parse(&[])).is_ok());
        let e = check_role_flags(&parse(&["--core", "0"])).expect_err("--core").0;
        assert!(e.starts_with("--core 0 is not allowed with `rotorloop run`"), "{e}");
        // `--host h` without `--split` left the domain's files behind (issue 45, 16).
        let e = check_role_flags(&parse(&["--host", "h"])).expect_err("--host").0;
        assert!(e.starts_with("--host h is not allowed with `rotorloop run`"), "{e}");
        // Spinning at SCHED_FIFO on fewer CPUs than roles starves them: refused, whatever
        // the machine (one CPU of its set), and the same run with event waits is not.
        let cpu = crate::cpus::allowed_now()[0].to_string();
        let spin = ["--wait", "spin", "--rt-priority", "80", "--cpus", &cpu];
        let e = with_preset(&parse(&spin), true).expect_err("spin at FIFO on one CPU").0;
        assert!(e.starts_with("--wait spin is not allowed with --rt-priority 80 on 1 CPU"), "{e}");
        let event = ["--wait", "event", "--rt-priority", "80", "--cpus", &cpu];
        assert!(with_preset(&parse(&event), true).is_ok());
        assert!(with_preset(&parse(&spin[..2]), true).is_ok(), "spin at the normal policy");
    }
}
