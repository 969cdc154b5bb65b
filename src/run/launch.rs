//! `rotorloop run`: starts the four processes from this very executable (so they are
//! always the same build), pins them, shows the monitor's live status line, stops them
//! cleanly at the end or on Ctrl-C/SIGTERM, and leaves the report in `--out`.

use std::collections::BTreeMap;
use std::os::unix::process::ExitStatusExt;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use anyhow::Context;
use clap::Args;
use rotorloop_common::clock::now_ns;
use rotorloop_common::ipc::REFERENCE_LEAD;
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::role::end::LINGER_S;
use rotorloop_common::signals::{install_signal_handlers, shutdown_requested};
use rotorloop_common::wire::{FLAG_LAST, StateSample};
use rotorloop_controller::policy::ControllerResume;
use rotorloop_monitor::hosts::Hosts;
use rotorloop_monitor::policy::MonitorResume;
use rotorloop_reference::policy::ReferenceResume;

use rotorloop_common::graph::{Role, Topic};
use rotorloop_common::ipc::domain::Domain;

use crate::run::fault::{Action, Apply, Fault, FaultEvent, FaultKind, FaultSchedule, parse_fault};
use crate::run::split::{Split, wait_until};
use crate::run::supervise::{
    Children, Ending, LinkWatch, Marks, RestartLimit, START_TIMEOUT_S, Supervisor, Verdict,
    Watchdog, parse_restart, signal,
};
use rotorloop_common::role::UsageError;
use rotorloop_common::role::args::{Mode, RoleArgs};
use rotorloop_common::role::inject::Corrupt;
use rotorloop_plant::actuator::ActuationDelay;

/// `rotorloop run` arguments.
#[derive(Debug, Clone, Args)]
pub struct RunArgs {
    /// What every role takes, passed on to each.
    #[command(flatten)]
    pub role: RoleArgs,
    /// Cores per role, e.g. `plant=0,controller=1,reference=0,monitor=1`.
    #[arg(long)]
    pub pin: Option<String>,
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
    /// Real time: the plant sleeps until this many µs before each grid time and spins
    /// the rest (sharper ticks, one core busier).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
    pub spin_before_tick_us: u64,
    /// Real time: ticks the plant holds the last torque before safe mode.
    #[arg(long, allow_negative_numbers = true, default_value_t = 50)]
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
    #[arg(long, default_value = "measured")]
    pub actuation_delay: ActuationDelay,
    /// Restart policy for a role that exits abnormally, is killed by anyone or hangs:
    /// `on-failure`, `always` (also after a clean exit before the run's end) or `never`,
    /// for every role, per role (`monitor=always,plant=never`), or both (`never,monitor=always`).
    #[arg(long, default_value = "on-failure")]
    pub restart: String,
    /// Restart intensity limit `N/SECONDS`: a role restarted more than N times within that
    /// many seconds stops the run (the monitor is then given up instead; the loop goes on).
    #[arg(long, default_value = "5/10")]
    pub restart_limit: String,
    /// A role with work waiting that makes no progress (its resume slot does not move) for
    /// this many milliseconds is killed and restarted by its policy (0: no watchdog).
    #[arg(long, allow_negative_numbers = true, default_value_t = 3000)]
    pub watchdog_ms: u64,
    /// `dedicated`: every role on a core of its own (the machine's last four), every role
    /// busy-waiting (`--wait spin`), and the plant spinning the last 50 µs before each tick
    /// (sharp ticks on a VM whose timer wake-ups are late). Needs 4 cores. A `--pin`, a
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
}

/// The cores of the `dedicated` preset on a machine with `ncores`: plant, controller,
/// reference, monitor on the last four (core 0 takes most of the housekeeping), or why
/// there are not enough.
pub fn dedicated_cores(ncores: usize) -> Result<[usize; 4], String> {
    if ncores < 4 {
        return Err(format!("dedicated needs 4 cores (one per role); this machine has {ncores}"));
    }
    Ok([ncores - 4, ncores - 3, ncores - 2, ncores - 1])
}

/// Applies `--preset` (`dedicated`) to what the command line left unsaid.
fn with_preset(args: &RunArgs, explicit_wait: bool) -> Result<RunArgs, UsageError> {
    let mut a = args.clone();
    match args.preset.as_deref() {
        None => {}
        Some("dedicated") => {
            let ncores = std::thread::available_parallelism().map_or(1, |n| n.get());
            let [p, c, r, m] =
                dedicated_cores(ncores).map_err(|e| UsageError(format!("--preset {e}")))?;
            a.pin.get_or_insert_with(|| {
                format!("plant={p},controller={c},reference={r},monitor={m}")
            });
            if !explicit_wait {
                a.role.wait = rotorloop_common::ipc::wait::Wait::Spin;
            }
            if a.spin_before_tick_us == 0 {
                a.spin_before_tick_us = 50;
            }
        }
        Some(other) => {
            return Err(UsageError(format!("--preset `{other}` is not allowed: dedicated")));
        }
    }
    Ok(a)
}

impl RunArgs {
    /// The defaults of every launcher option, for `role` into `out` (paper, bench).
    pub fn defaults(role: RoleArgs, out: PathBuf) -> Self {
        Self {
            role,
            pin: None,
            out,
            no_monitor: false,
            quiet: false,
            no_record: false,
            spin_before_tick_us: 0,
            hold_ticks: 50,
            fault: Vec::new(),
            corrupt: Vec::new(),
            restart: "on-failure".into(),
            restart_limit: "5/10".into(),
            watchdog_ms: 3000,
            actuation_delay: ActuationDelay::Measured,
            preset: None,
            split: None,
        }
    }
}

/// A role started by the launcher gets SIGTERM when the launcher dies, however it dies
/// (`kill -9` of the launcher, a test's time limit): no orphaned role keeps a domain, or
/// a pipe of whoever started the launcher, open.
fn stop_with_parent(cmd: &mut Command) {
    use std::os::unix::process::CommandExt;
    let parent = libc::pid_t::try_from(std::process::id()).unwrap_or(0);
    // SAFETY: runs in the child between fork and exec, calling only async-signal-safe
    // functions (prctl, getppid, raise).
    unsafe {
        cmd.pre_exec(move || {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
            // The launcher may have died before the prctl: then nobody would signal us.
            if libc::getppid() != parent {
                libc::raise(libc::SIGTERM);
            }
            Ok(())
        });
    }
}

/// Parses `--pin`: `role=core` pairs separated by commas.
pub fn parse_pins(s: &str) -> Result<BTreeMap<String, usize>, UsageError> {
    let mut pins = BTreeMap::new();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    for part in s.split(',').filter(|p| !p.is_empty()) {
        let (role, core) = part.split_once('=').ok_or_else(|| {
            UsageError(format!("--pin `{part}` is not allowed: role=core, e.g. plant=0"))
        })?;
        if role.parse::<Role>().is_err() {
            return Err(UsageError(format!(
                "--pin role `{role}` is not allowed: plant, reference, controller or monitor"
            )));
        }
        let core: usize = core.parse().ok().filter(|c| *c < cores).ok_or_else(|| {
            UsageError(format!(
                "--pin {role}=`{core}` is not allowed: a core from 0 to {}",
                cores - 1
            ))
        })?;
        pins.insert(role.to_owned(), core);
    }
    Ok(pins)
}

/// Resident memory of one role over a run, from `/proc/<pid>/status`, sampled once a
/// second by the launcher: `VmRSS` and its parts `RssAnon` (heap and stacks: what a leak
/// grows), `RssFile` (code and libraries, paged in as code paths first run) and
/// `RssShmem` (the iceoryx2 segments' pages touched so far). A restarted role starts a new
/// life: the figures are of its last life.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct RssTrack {
    /// The process's pid (last life).
    pub pid: u32,
    /// First sample taken at least [`RSS_SETTLE_S`] after the start, or the first at all
    /// for a shorter life (KiB).
    pub start_kib: u64,
    /// Seconds after the start of that sample.
    pub start_at_s: f64,
    /// Last sample before the process ended (KiB).
    pub end_kib: u64,
    /// Seconds after the start of that sample.
    pub end_at_s: f64,
    /// Largest sample (KiB).
    pub max_kib: u64,
    /// `(RssAnon, RssFile, RssShmem)` of the start sample (KiB).
    pub start_parts_kib: [u64; 3],
    /// The same of the end sample (KiB).
    pub end_parts_kib: [u64; 3],
    /// Samples taken.
    pub samples: u64,
    #[serde(skip)]
    spawned_ns: u64,
    #[serde(skip)]
    settled: bool,
}

/// Seconds a process may allocate its set-up before its "start" memory is taken.
pub const RSS_SETTLE_S: f64 = 3.0;

/// `VmRSS` and `(RssAnon, RssFile, RssShmem)` of a process (KiB), if it is alive.
pub fn rss_kib(pid: u32) -> Option<(u64, [u64; 3])> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| -> Option<u64> {
        let line = status.lines().find(|l| l.starts_with(name))?;
        line.split_whitespace().nth(1)?.parse().ok()
    };
    Some((field("VmRSS:")?, [field("RssAnon:")?, field("RssFile:")?, field("RssShmem:")?]))
}

impl RssTrack {
    fn new(pid: u32) -> Self {
        Self { pid, spawned_ns: now_ns(), ..Self::default() }
    }

    fn sample(&mut self) -> Option<(u64, [u64; 3])> {
        let (kib, parts) = rss_kib(self.pid)?;
        let at = (now_ns() - self.spawned_ns) as f64 / 1e9;
        if self.samples == 0 || (!self.settled && at >= RSS_SETTLE_S) {
            self.start_kib = kib;
            self.start_parts_kib = parts;
            self.start_at_s = at;
            self.settled = at >= RSS_SETTLE_S;
        }
        self.end_kib = kib;
        self.end_parts_kib = parts;
        self.end_at_s = at;
        self.max_kib = self.max_kib.max(kib);
        self.samples += 1;
        Some((kib, parts))
    }
}

/// How a run ended without completing its control loop (mapped to exit codes by the CLI).
#[derive(Debug, thiserror::Error)]
pub enum RunEnd {
    /// SIGINT or SIGTERM before the plant's last tick: exit code 3.
    #[error("the run was stopped by a signal before its last tick")]
    StoppedBySignal,
}

/// What the launcher starts, and how: the roles' arguments, pins, corruptions, and the
/// executable they run from (this one, so the four are always the same build).
struct Launch<'a> {
    args: &'a RunArgs,
    /// The run's domain as each host sees it (one, with no host, unless split).
    domains: Vec<Domain>,
    split: Option<Split>,
    /// The first host's gateway listens on this loopback port.
    link_port: u16,
    faults: Vec<Fault>,
    supervisor: Supervisor,
    role_args: RoleArgs,
    pins: BTreeMap<String, usize>,
    corrupt: Vec<(String, Corrupt)>,
    exe: PathBuf,
    /// The run's ticks.
    ticks: u64,
}

impl Launch<'_> {
    /// The command line of `role`: `rotorloop role ROLE` with the run's arguments.
    fn command(&self, role: &str) -> Command {
        let args = self.args;
        if let (Some(split), Some(host)) = (&self.split, role.strip_prefix("link-")) {
            let mut cmd = crate::run::split::gateway_command(
                split,
                host,
                self.role_args.domain(),
                self.link_port,
                &args.out,
            );
            cmd.stdin(Stdio::null());
            // Quiet (the bench): what the gateway says goes to OUT/link-HOST.log.
            let log = args.quiet.then(|| crate::run::split::gateway_log(&args.out, role));
            if let Some(Ok(f)) = log {
                cmd.stderr(f);
            }
            stop_with_parent(&mut cmd);
            return cmd;
        }
        let mut r = self.role_args.clone();
        r.core = self.pins.get(role).copied();
        r.host = self.split.as_ref().and_then(|s| s.host_of(role)).map(str::to_owned);
        let mut cmd = Command::new(&self.exe);
        cmd.arg("role").arg(role).args(r.to_args()).stdin(Stdio::null());
        stop_with_parent(&mut cmd);
        for (_, c) in self.corrupt.iter().filter(|(r, _)| r == role) {
            cmd.arg("--corrupt").arg(c.to_string());
        }
        if args.quiet {
            cmd.stdout(Stdio::null());
        }
        match role.parse::<Role>() {
            Ok(Role::Monitor) => {
                cmd.arg("--out").arg(&args.out);
                if let Some(hosts) = self.monitor_hosts() {
                    cmd.arg("--hosts").arg(hosts);
                }
                if !args.quiet {
                    cmd.arg("--status");
                }
            }
            Ok(Role::Plant) => {
                let n = match &self.split {
                    Some(s) => s.plant_subscribers(),
                    None => Topic::State
                        .subscribers()
                        .iter()
                        .filter(|r| **r != Role::Monitor || !args.no_monitor)
                        .count(),
                };
                cmd.arg("--subscribers").arg(n.to_string());
                cmd.arg("--spin-before-tick-us").arg(args.spin_before_tick_us.to_string());
                cmd.arg("--hold-ticks").arg(args.hold_ticks.to_string());
                cmd.arg("--latency-out").arg(&args.out);
                cmd.arg("--actuation-delay").arg(args.actuation_delay.to_string());
            }
            Ok(Role::Controller) => {
                for (flag, value) in self.faults.iter().filter_map(|f| f.role_arg()) {
                    cmd.arg(flag).arg(value);
                }
            }
            _ => {}
        }
        cmd
    }

    /// The monitor's `--hosts` of a split run.
    fn monitor_hosts(&self) -> Option<String> {
        let s = self.split.as_ref()?;
        let hosts: Vec<String> =
            Role::ALL.iter().filter_map(|r| s.host(*r).map(|h| format!("{r}={h}"))).collect();
        Some(hosts.join(","))
    }

    /// A monitor that left no report (killed for good, or its restart refused): the
    /// report from the flight records, without a live view.
    fn report_without_monitor(
        &self,
        scenario: &rotorloop_common::Scenario,
        dir: Option<&std::path::Path>,
    ) {
        let (out, Some(dir)) = (&self.args.out, dir) else { return };
        if self.args.no_monitor || out.join("summary.json").exists() {
            return;
        }
        let records = match rotorloop_monitor::assemble::FlightRecords::read(dir) {
            Ok(r) => r,
            Err(e) => return eprintln!("launcher: no summary.json and no report from {e}"),
        };
        let hosts = self.monitor_hosts().and_then(|h| Hosts::parse(&h).ok()).unwrap_or_default();
        let summary = rotorloop_monitor::assemble::report(
            out,
            dir,
            &records,
            scenario,
            &self.role_args,
            &hosts,
            None,
        );
        let fallback = rotorloop_monitor::recording::fallback_dir(self.role_args.domain());
        match rotorloop_monitor::report::write_summary(out, &fallback, &summary) {
            Ok(()) => eprintln!(
                "launcher: the monitor left no report; assembled it from the flight records"
            ),
            Err(e) => eprintln!("launcher: cannot write the report: {e:#}"),
        }
    }

    /// Moves the flight records from their staging directory into `OUT/flight` once every
    /// role has ended, and says so in `summary.json`; returns where they are (`None`: no
    /// records). Records that cannot be moved stay where they are, and the warning names it.
    fn keep_flight_records(&self) -> Option<PathBuf> {
        let staged = self.role_args.record.clone()?;
        let kept = self.args.out.join("flight");
        if self.args.role.record.is_some() || staged == kept {
            return Some(staged); // recorded where the user asked
        }
        if let Err(e) = rotorloop_common::flight::move_records(&staged, &kept) {
            let (s, k) = (staged.display(), kept.display());
            eprintln!("warning: the flight records stay in {s}: cannot move them into {k}: {e}");
            return Some(staged);
        }
        let _ = rotorloop_common::output::patch_summary(&self.args.out, |j| {
            if j["flight"].is_object() {
                j["flight"]["dir"] = kept.display().to_string().into();
            }
        });
        Some(kept)
    }

    /// The mover of the records' finished halves, when the rings are shorter than the run
    /// and the records are the launcher's to move (see `common::flight`).
    fn mover(&self) -> Option<rotorloop_common::flight::Mover> {
        use rotorloop_common::flight::{Mover, SPARE_SLOTS, ring_capacity};
        let staged = self.role_args.record.as_ref()?;
        let ring = ring_capacity(self.ticks, self.role_args.flight_ring_ticks);
        let wraps = ring < self.ticks + 1 + SPARE_SLOTS;
        (wraps && self.args.role.record.is_none())
            .then(|| Mover::new(staged, &self.args.out.join("flight")))
    }

    /// The domain as `role`'s host sees it.
    fn domain_of(&self, role: &str) -> &Domain {
        let host = self.split.as_ref().and_then(|s| s.host_of(role));
        self.domains.iter().find(|d| d.host() == host).unwrap_or(&self.domains[0])
    }

    fn spawn(&self, role: &str, rss: &mut RssLog) -> anyhow::Result<Child> {
        let child = self.command(role).spawn().with_context(|| format!("cannot start {role}"))?;
        rss.track(role, child.id());
        Ok(child)
    }
}

/// The `--fault`s, checked against each other and against the placement of the roles.
fn checked_faults(args: &RunArgs, split: Option<&Split>) -> anyhow::Result<Vec<Fault>> {
    let faults = args.fault.iter().map(|f| parse_fault(f)).collect::<Result<Vec<_>, _>>()?;
    crate::run::fault::check_overlaps(&args.fault, &faults)?;
    for f in &faults {
        match split {
            Some(s) => s.check_fault_target(&f.role)?,
            None if f.role.starts_with("link-") => {
                return Err(UsageError(format!(
                    "--fault {}: gateways exist only with --split",
                    f.role
                ))
                .into());
            }
            None => {}
        }
    }
    Ok(faults)
}

/// Runs the four processes to the end of the scenario.
pub fn run(args: &RunArgs) -> anyhow::Result<()> {
    // `--wait` has a default, so "explicit" means: not the default (event).
    let explicit_wait = args.role.wait != rotorloop_common::ipc::wait::Wait::Event;
    let args = &with_preset(args, explicit_wait)?;
    let scenario = args.role.scenario()?;
    for w in &scenario.warnings {
        eprintln!("warning: {w}");
    }
    let corrupt = args
        .corrupt
        .iter()
        .map(|c| crate::run::fault::parse_corrupt(c))
        .collect::<Result<Vec<_>, _>>()?;
    let limit: RestartLimit =
        args.restart_limit.parse().map_err(|e| UsageError(format!("--restart-limit {e}")))?;
    let supervisor = Supervisor::new(parse_restart(&args.restart)?, limit);
    let mut role_args = args.role.clone();
    role_args.domain.get_or_insert_with(|| format!("run-{}", std::process::id()));
    role_args.record = match args.no_record {
        true => None,
        false => {
            Some(role_args.record.clone().unwrap_or_else(|| staging_dir(&role_args, &args.out)))
        }
    };
    let split = args.split.as_deref().map(|s| Split::parse(s, !args.no_monitor)).transpose()?;
    let faults = checked_faults(args, split.as_ref())?;
    if split.is_some() {
        crate::run::split::link_binary()?;
    }
    let hosts: Vec<Option<&str>> = match &split {
        Some(s) => s.hosts().iter().map(|h| Some(h.as_str())).collect(),
        None => vec![role_args.host.as_deref()],
    };
    let domains = hosts
        .iter()
        .map(|h| Domain::on_host(role_args.domain(), *h).map_err(|e| UsageError(e.to_string())))
        .collect::<Result<Vec<_>, _>>()?;
    let pins = args.pin.as_deref().map(parse_pins).transpose()?.unwrap_or_default();
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    if let Some(dir) = &role_args.record {
        // An earlier run's records in the same directory are not this run's to continue.
        clear_flight_records(dir)?;
        clear_flight_records(&args.out.join("flight"))?;
    }
    let exe = std::env::current_exe().context("cannot find the rotorloop executable")?;
    install_signal_handlers();
    prepare_domains(&domains, &args.out)?;
    let link_port = if split.is_some() { crate::run::split::free_port()? } else { 0 };
    let launch = Launch {
        args,
        domains,
        split,
        link_port,
        faults: faults.clone(),
        supervisor,
        role_args,
        pins,
        corrupt,
        exe,
        ticks: scenario.ticks(),
    };
    // What `rotorloop recover` needs should this launcher not end normally.
    let record = crate::run::recover::LaunchRecord {
        domain: launch.role_args.domain().to_owned(),
        hosts: launch.monitor_hosts(),
        role_args: launch.role_args.to_args(),
        scenario: scenario.file.clone(),
        staging: launch.role_args.record.clone(),
        moved: args.role.record.is_none(),
        launcher_pid: std::process::id(),
    };
    record.write(&args.out)?;
    let mut rss = RssLog::create(&args.out);
    let mut children = Children::default();
    let started = start(&launch, &mut children, &mut rss);
    let supervised = started
        .and_then(|()| supervise(&launch, &mut children, &mut rss, FaultSchedule::new(faults)));
    stop_gateways(&mut children);
    drop(children);
    // Everything of this domain is gone now: remove what iceoryx2 keeps after its nodes.
    for domain in &launch.domains {
        if let Err(e) = domain.cleanup() {
            eprintln!("warning: cleaning up domain {}: {e}", domain.name());
        }
    }
    for h in launch.split.iter().flat_map(|s| s.hosts()) {
        let _ = std::fs::remove_file(crate::run::split::ready_file(&args.out, h));
    }
    let flight = launch.keep_flight_records();
    // A failure stops the run, but its report (the faults that led to it among them) is
    // written as for any other end.
    let (events, failure) = supervised?;
    let reported = report(&launch, &scenario, &rss, &events, flight.as_deref());
    match failure {
        Some(f) => Err(f),
        None => reported,
    }
}

/// Writes each host's iceoryx2 configuration for `iox2`, and clears what an earlier, killed
/// run of the domain left (resume slots included, which would otherwise be taken for a
/// restart); a domain still in use by a live process is refused.
fn prepare_domains(domains: &[Domain], out: &std::path::Path) -> anyhow::Result<()> {
    for domain in domains {
        let dir = match domain.host() {
            Some(h) => out.join(format!("host-{h}")),
            None => out.to_path_buf(),
        };
        if let Err(e) = domain.write_iox2_config(&dir) {
            eprintln!("warning: cannot write {}/config/iceoryx2.toml: {e}", dir.display());
        }
        let (_, alive) = domain.cleanup()?;
        if alive > 0 {
            let name = domain.name();
            let msg = format!(
                "domain `{name}` is in use by {alive} running process(es); choose another --domain"
            );
            return Err(UsageError(msg).into());
        }
    }
    Ok(())
}

/// Where the roles record during a run: a directory of the domain on tmpfs
/// (`/dev/shm/rotorloop-flight-DOMAIN`), moved into `OUT/flight` at the end. A mapped
/// page of a disk file is write-protected until its first write and again after each
/// writeback, so one record in eight would take a page fault into the filesystem
/// (measured on ext4: p99 of a record 2.5 µs instead of 50 ns); tmpfs has no writeback.
/// Without `/dev/shm`, `OUT/flight` itself.
fn staging_dir(role: &RoleArgs, out: &std::path::Path) -> PathBuf {
    rotorloop_common::flight::staging_dir(role.domain()).unwrap_or_else(|| out.join("flight"))
}

/// Removes the flight records an earlier run left in `dir`, naming each.
fn clear_flight_records(dir: &std::path::Path) -> anyhow::Result<()> {
    use rotorloop_common::flight::{Stream, segments};
    let files =
        Stream::ALL.into_iter().flat_map(|s| segments(dir, s).into_iter().chain([s.path(dir)]));
    for path in files {
        match std::fs::remove_file(&path) {
            Ok(()) => eprintln!("launcher: removed an earlier run's {}", path.display()),
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(e).with_context(|| format!("cannot remove {}", path.display()));
            }
            Err(_) => {}
        }
    }
    Ok(())
}

/// Starts the roles (and, split, the gateways first: see [`crate::run::split`]).
fn start(launch: &Launch, children: &mut Children, rss: &mut RssLog) -> anyhow::Result<()> {
    let args = launch.args;
    let roles: Vec<&str> = Role::ALL
        .iter()
        .filter(|r| **r != Role::Monitor || !args.no_monitor)
        .map(|r| r.name())
        .collect();
    let Some(split) = &launch.split else {
        for role in roles {
            children.0.push((role.to_string(), launch.spawn(role, rss)?));
        }
        return Ok(());
    };
    for g in split.gateways() {
        children.0.push((g.clone(), launch.spawn(&g, rss)?));
    }
    let gone = |c: &mut Children| c.0.iter_mut().any(|(_, c)| !matches!(c.try_wait(), Ok(None)));
    wait_until(Duration::from_secs(30), || split.gateways_ready(&args.out) || gone(children));
    if gone(children) || !split.gateways_ready(&args.out) {
        anyhow::bail!("the link gateways did not connect (their messages are above)");
    }
    let plant_host = split.host_of(Role::Plant.name()).unwrap_or_default().to_owned();
    for role in roles.iter().filter(|r| split.host_of(r) != Some(&plant_host)) {
        children.0.push((role.to_string(), launch.spawn(role, rss)?));
    }
    let at_plant = launch.domain_of(Role::Plant.name());
    let needed = split.topics_needed_at_plant();
    if !wait_until(Duration::from_secs(30), || needed.iter().all(|t| at_plant.topic_exists(*t))) {
        anyhow::bail!(
            "the services of host `{plant_host}`'s peer did not reach it through the link within 30 s"
        );
    }
    for role in roles.iter().filter(|r| split.host_of(r) == Some(&plant_host)) {
        children.0.push((role.to_string(), launch.spawn(role, rss)?));
    }
    Ok(())
}

/// Stops the gateways once the roles are done (SIGTERM, SIGKILL after 5 s).
fn stop_gateways(children: &mut Children) {
    for (name, c) in children.0.iter_mut().filter(|(n, _)| n.starts_with("link-")) {
        crate::run::split::stop(name, c);
    }
}

/// Where each role stands, from the resume slots (what the watchdog reads).
struct Progress {
    plant: ResumeSlot<StateSample>,
    controller: ResumeSlot<ControllerResume>,
    reference: ResumeSlot<ReferenceResume>,
    monitor: ResumeSlot<MonitorResume>,
}

impl Progress {
    /// Each role's slot on its own host.
    fn open(launch: &Launch) -> anyhow::Result<Self> {
        let ctx = "the resume slots";
        let d = |role| launch.domain_of(role);
        Ok(Self {
            plant: ResumeSlot::open(d(Role::Plant.name()), Role::Plant.name()).context(ctx)?,
            controller: ResumeSlot::open(d(Role::Controller.name()), Role::Controller.name())
                .context(ctx)?,
            reference: ResumeSlot::open(d(Role::Reference.name()), Role::Reference.name())
                .context(ctx)?,
            monitor: ResumeSlot::open(d(Role::Monitor.name()), Role::Monitor.name())
                .context(ctx)?,
        })
    }

    fn marks(&self) -> Marks {
        Marks {
            plant: self.plant.load().map(|s| s.tick),
            controller: self.controller.load().map(|r| r.last.tick),
            reference_next: self.reference.load().map(|r| r.next()),
            monitor_next: self.monitor.load().map(|m| m.next_row),
        }
    }

    /// The plant has published its last tick: the control loop is complete.
    fn loop_complete(&self) -> bool {
        self.plant.load().is_some_and(|s| s.flags & FLAG_LAST != 0)
    }
}

/// What the supervision loop keeps between polls.
struct Watch {
    events: Vec<FaultEvent>,
    failures: Vec<String>,
    /// Roles waiting to be started again, and when (s after tick 0).
    restarts: BTreeMap<String, f64>,
    /// Pids whose end has been dealt with.
    handled: std::collections::BTreeSet<u32>,
    /// Pids killed by the schedule or the watchdog (their SIGKILL is not a new fault).
    planned: std::collections::BTreeSet<u32>,
    /// The pid stopped by each `stop` fault.
    stopped: BTreeMap<String, u32>,
    /// The stops not yet ended, whoever sent them: pid → index of its event.
    open_stops: BTreeMap<u32, usize>,
    /// The restart policy's state.
    supervisor: Supervisor,
    /// The hang watchdog's state.
    watchdog: Watchdog,
    /// Split: whether the link carries the loop again after a restart.
    link: LinkWatch,
    /// Torque samples the plant has received so far.
    torques_received: u64,
    /// Copies the finished halves of the flight records' rings into `OUT/flight` (a run
    /// longer than the rings).
    mover: Option<rotorloop_common::flight::Mover>,
    /// The plant has published its last tick.
    loop_complete: bool,
}

impl Watch {
    fn new(launch: &Launch) -> Self {
        let watchdog_s = launch.args.watchdog_ms as f64 / 1e3;
        Self {
            events: Vec::new(),
            failures: Vec::new(),
            restarts: BTreeMap::new(),
            handled: Default::default(),
            planned: Default::default(),
            stopped: BTreeMap::new(),
            open_stops: BTreeMap::new(),
            supervisor: launch.supervisor.clone(),
            watchdog: Watchdog::new(watchdog_s),
            link: LinkWatch::new(START_TIMEOUT_S.max(watchdog_s)),
            torques_received: 0,
            mover: launch.mover(),
            loop_complete: false,
        }
    }

    /// After the supervision loop: the last records moved, the stops still open ended.
    fn finish(&mut self, progress: &Progress) {
        move_due_records(self, progress); // what became due in the last pass
        if let Some(m) = self.mover.as_ref().filter(|m| m.lost > 0) {
            eprintln!(
                "warning: flight records: {} record(s) lost: the rings came round before the \
                 launcher moved them (it was not running for that long); a longer \
                 --flight-ring-ticks keeps them",
                m.lost
            );
        }
        for pid in self.open_stops.keys().copied().collect::<Vec<_>>() {
            end_stop(self, pid, "still stopped when the launcher ended");
        }
    }
}

/// Runs the fault schedule, the restart policy and the watchdog, samples memory, and
/// waits for every child; on a signal or a failure, forwards SIGTERM, then SIGKILL after
/// 10 s. Returns the faults as they happened, and the failure that stopped the run, if
/// one did.
fn supervise(
    launch: &Launch,
    children: &mut Children,
    rss: &mut RssLog,
    mut schedule: FaultSchedule,
) -> anyhow::Result<(Vec<FaultEvent>, Option<anyhow::Error>)> {
    let lockstep = launch.role_args.mode == Mode::Lockstep;
    // The fault clock starts when the plant has published tick 0 (its resume slot is
    // written just before each publish).
    let progress = Progress::open(launch)?;
    let (mut run_t0, mut term_sent_at): (Option<u64>, Option<u64>) = (None, None);
    let mut plant_ended_at: Option<u64> = None;
    let mut w = Watch::new(launch);
    let launched_ns = now_ns();
    let mut dead_after_end = 0;
    loop {
        if run_t0.is_none() && progress.plant.load().is_some() {
            run_t0 = Some(now_ns());
        }
        // Seconds since tick 0 (before it: negative, since the launch).
        let now_s = (now_ns() as f64 - run_t0.unwrap_or(launched_ns) as f64) / 1e9;
        w.loop_complete = progress.loop_complete();
        if w.loop_complete {
            continue_stopped_after_the_end(children, &mut w, now_s);
        }
        let stopping = term_sent_at.is_some();
        let elapsed = run_t0.map(|_| now_s).filter(|_| !stopping);
        for action in schedule.due(elapsed) {
            injected(launch, children, rss, &mut w, action, now_s)?;
        }
        if !stopping && run_t0.is_some() && !w.loop_complete {
            w.torques_received = progress.plant.load().map_or(0, |s| s.torques_received);
            watch_the_link(&mut w, now_s);
        }
        if !stopping && run_t0.is_some() && !w.loop_complete && w.failures.is_empty() {
            watch_for_hangs(launch, children, &mut w, &progress.marks(), lockstep, now_s);
        }
        let due: Vec<String> = w
            .restarts
            .iter()
            .filter(|(_, at)| **at <= now_s && !stopping)
            .map(|(r, _)| r.clone())
            .collect();
        for role in due {
            w.restarts.remove(&role);
            restart(launch, children, rss, &mut w, &role, now_s)?;
        }
        rss.sample_if_due();
        move_due_records(&mut w, &progress);
        watch_for_stops(children, &mut w, now_s);
        let running = reap(children, &mut w, &progress, stopping, now_s);
        remove_dead_ports_after_the_end(launch, &w, &mut dead_after_end);
        if launch.split.is_some() && w.loop_complete && !stopping {
            term_sent_at = stop_far_roles_after_the_end(children, &mut plant_ended_at);
        }
        // Restarts still to come keep the launcher waiting, but only until the last tick:
        // after it nobody is started again (see `restart`).
        let awaiting = (schedule.awaiting_restart() || !w.restarts.is_empty()) && !w.loop_complete;
        if running == 0 && (!awaiting || stopping) {
            break;
        }
        if (shutdown_requested() || !w.failures.is_empty()) && !stopping {
            term_sent_at = Some(now_ns());
            children.signal_all(libc::SIGCONT); // a stopped child must see the SIGTERM
            children.signal_all(libc::SIGTERM);
        }
        if term_sent_at.is_some_and(|t| now_ns() - t > 10_000_000_000) {
            children.signal_all(libc::SIGKILL);
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    for f in schedule.not_done() {
        eprintln!("launcher: --fault {f}: not carried out, the run ended first");
    }
    w.finish(&progress);
    let failure = w
        .failures
        .first()
        .map(|f| anyhow::anyhow!("{f}; the run was stopped ({} failed)", w.failures.join(", ")));
    Ok((w.events, failure))
}

/// Split: a role on another host than the plant cannot read the plant's resume slot (it
/// learns the end from the last state). If that state was lost with a gateway, it would
/// wait for ever: once the plant has ended, the rest get their linger time, then SIGTERM
/// (a clean end, not a fault). Returns when the SIGTERM was sent, if it was.
fn stop_far_roles_after_the_end(children: &mut Children, since: &mut Option<u64>) -> Option<u64> {
    let plant_gone =
        children.get_mut(Role::Plant.name()).is_none_or(|c| !matches!(c.try_wait(), Ok(None)));
    let since = *since.get_or_insert_with(now_ns);
    if !plant_gone || now_ns() - since <= (LINGER_S + 5) * 1_000_000_000 {
        return None;
    }
    eprintln!("launcher: the plant ended {} s ago; stopping the roles still waiting", LINGER_S + 5);
    children.signal_all(libc::SIGTERM);
    Some(now_ns())
}

/// After the last tick the schedule is moot: a role it stopped and has not continued
/// would never see the end, and the launcher would wait for it for ever (seen: a
/// controller killed by hand at 4.9 s, restarted, stopped at 5 s before its first
/// progress, so under the start timeout, and the 8 s loop ended before the watchdog
/// judged it). It is continued, sees the end and exits as the others do.
fn continue_stopped_after_the_end(children: &mut Children, w: &mut Watch, now_s: f64) {
    for (role, pid) in std::mem::take(&mut w.stopped) {
        let Some(c) = children.get_mut(&role).filter(|c| c.id() == pid) else { continue };
        if w.planned.contains(&pid) || !matches!(c.try_wait(), Ok(None)) {
            continue;
        }
        continue_stopped(c, stop_event(&mut w.events, &role), "; SIGCONT at the end of the loop");
        eprintln!("launcher: continued {role} (SIGCONT) at {now_s:.3} s: the loop has ended");
    }
}

/// Continues (SIGCONT) a role the schedule stopped, and marks its `stop` fault continued
/// now, `how` added to its detail.
fn continue_stopped(c: &mut Child, stop: Option<&mut FaultEvent>, how: &str) {
    signal(c, libc::SIGCONT);
    if let Some(e) = stop {
        e.restart_ns = Some(now_ns());
        e.detail.push_str(how);
    }
}

/// The newest `stop` fault of `role`.
fn stop_event<'a>(events: &'a mut [FaultEvent], role: &str) -> Option<&'a mut FaultEvent> {
    events.iter_mut().rev().find(|e| e.role == role && e.kind == "stop")
}

/// Copies the halves of the flight records' rings that are due into `OUT/flight`.
fn move_due_records(w: &mut Watch, progress: &Progress) {
    if let (Some(m), Some(p)) = (&mut w.mover, progress.plant.load()) {
        for e in m.pass(p.tick) {
            eprintln!("warning: flight records: {e}; the loop goes on");
        }
    }
}

/// Split: a restart after which the link does not carry the loop again within the start
/// timeout ends the run (see [`LinkWatch`]), with a fault of its own in the report.
fn watch_the_link(w: &mut Watch, now_s: f64) {
    let Some((role, why)) = w.link.check(w.torques_received, now_s) else { return };
    eprintln!("launcher: {why} ({now_s:.3} s)");
    w.events.push(FaultEvent::now(role, "link-lost", why.clone()));
    w.failures.push(why);
}

/// Every stop and continue of a child, whoever sent the signal (the fault schedule, the
/// user's `kill -STOP`, a debugger's SIGTSTP): a stop the schedule did not make is a fault
/// of its own, listed with its signal, and every stop is ended in the report as continued,
/// killed, judged hung, or with the run. A stop and its continue both between two looks
/// (2 ms apart) show only as the continue, and are listed as a stop of under 2 ms.
fn watch_for_stops(children: &mut Children, w: &mut Watch, now_s: f64) {
    for (role, c) in &children.0 {
        let pid = c.id();
        match job_control_event(pid) {
            None => {}
            Some(JobControl::Stopped(sig)) => {
                if let Some(&i) = w.open_stops.get(&pid) {
                    w.events[i].signal.get_or_insert(signal_name(sig));
                    continue;
                }
                let name = signal_name(sig);
                eprintln!("launcher: {role} was stopped ({name}) at {now_s:.3} s, not by --fault");
                let detail = format!("{name} from outside the launcher");
                w.open_stops.insert(pid, w.events.len());
                let e = FaultEvent {
                    signal: Some(name),
                    ..FaultEvent::now(role.as_str(), "stop", detail)
                };
                w.events.push(e);
            }
            Some(JobControl::Continued) => {
                if !w.open_stops.contains_key(&pid) {
                    let detail = "stopped and continued within 2 ms, not by --fault".to_owned();
                    w.open_stops.insert(pid, w.events.len());
                    w.events.push(FaultEvent::now(role.as_str(), "stop", detail));
                }
                eprintln!("launcher: {role} continued at {now_s:.3} s");
                end_stop(w, pid, "continued");
            }
        }
    }
}

/// Ends the open stop of `pid`, if any, `how` and now (a continue is also its restart).
fn end_stop(w: &mut Watch, pid: u32, how: &'static str) {
    let Some(i) = w.open_stops.remove(&pid) else { return };
    let e = &mut w.events[i];
    let now = now_ns();
    e.ended.get_or_insert((how, now));
    if how == "continued" {
        e.restart_ns.get_or_insert(now);
    }
}

/// A change of a child's job-control state.
enum JobControl {
    /// Stopped by this signal.
    Stopped(libc::c_int),
    /// Continued (SIGCONT).
    Continued,
}

/// The child's newest stop or continue not yet seen, if any. `waitid` without `WEXITED`
/// consumes only job-control events and leaves an exit for `Child::try_wait`.
fn job_control_event(pid: u32) -> Option<JobControl> {
    // SAFETY: an all-zero siginfo_t is valid; waitid fills it for our own child's pid.
    let mut info: libc::siginfo_t = unsafe { std::mem::zeroed() };
    let opts = libc::WSTOPPED | libc::WCONTINUED | libc::WNOHANG;
    // SAFETY: as above; a pid that is not (or no longer) our child gives ECHILD.
    let rc = unsafe { libc::waitid(libc::P_PID, pid as libc::id_t, &mut info, opts) };
    // SAFETY: si_pid and si_status are set by a successful waitid.
    if rc != 0 || unsafe { info.si_pid() } == 0 {
        return None;
    }
    match info.si_code {
        libc::CLD_STOPPED => Some(JobControl::Stopped(unsafe { info.si_status() })),
        libc::CLD_CONTINUED => Some(JobControl::Continued),
        _ => None,
    }
}

/// The name of signal `sig` (`SIGSTOP`), or `signal N`.
fn signal_name(sig: libc::c_int) -> &'static str {
    match sig {
        libc::SIGSTOP => "SIGSTOP",
        libc::SIGTSTP => "SIGTSTP",
        libc::SIGTTIN => "SIGTTIN",
        libc::SIGTTOU => "SIGTTOU",
        libc::SIGKILL => "SIGKILL",
        libc::SIGTERM => "SIGTERM",
        libc::SIGINT => "SIGINT",
        libc::SIGSEGV => "SIGSEGV",
        libc::SIGABRT => "SIGABRT",
        libc::SIGBUS => "SIGBUS",
        libc::SIGHUP => "SIGHUP",
        libc::SIGPIPE => "SIGPIPE",
        libc::SIGQUIT => "SIGQUIT",
        libc::SIGFPE => "SIGFPE",
        libc::SIGILL => "SIGILL",
        _ => "another signal",
    }
}

/// After the last tick nobody is started again: the ports of a dead role would keep the
/// finished publishers lingering for subscribers that never leave (up to `LINGER_S`), so
/// they are removed as soon as a role is seen dead (`dead` counts the ends dealt with).
/// Not in a split run: there the launcher stops the far host's roles itself after the
/// plant's end (their gateways hold ports of their own), and this was not tested there.
fn remove_dead_ports_after_the_end(launch: &Launch, w: &Watch, dead: &mut usize) {
    if launch.split.is_none() && w.loop_complete && w.handled.len() != *dead {
        *dead = w.handled.len();
        for d in &launch.domains {
            let _ = d.cleanup();
        }
    }
}

/// The watchdog's pass: a role with work waiting and no progress for `--watchdog-ms` is
/// hung: killed (SIGKILL), recorded as a fault, and handed to the restart policy.
fn watch_for_hangs(
    launch: &Launch,
    children: &mut Children,
    w: &mut Watch,
    marks: &Marks,
    lockstep: bool,
    now_s: f64,
) {
    for r in Role::ALL {
        let role = r.name();
        let pid = children.get_mut(role).map(|c| c.id());
        // A pid already killed (by the schedule or by this watchdog) is not judged again:
        // a stopped process that got its SIGKILL may take a while to die and be reaped on
        // a loaded machine, and each pass over it counted as another hang (seen: one
        // SIGSTOP counted six times 2 ms apart, over the restart limit, the run stopped).
        let alive = pid.is_some_and(|p| !w.handled.contains(&p) && !w.planned.contains(&p));
        let pending = alive && marks.work_waiting(r, lockstep, REFERENCE_LEAD);
        if !w.watchdog.check(role, marks.of(r), pending, now_s) {
            continue;
        }
        let c = children.get_mut(role).expect("alive");
        if !matches!(c.try_wait(), Ok(None)) {
            // It has ended already (the launcher itself was descheduled past the limit on a
            // loaded machine, seen: 1.5 s): not a hang; `reap` gives its end its own name.
            continue;
        }
        let pid = c.id();
        w.planned.insert(pid);
        signal(c, libc::SIGKILL);
        end_stop(w, pid, "hung");
        let ms = launch.args.watchdog_ms;
        eprintln!(
            "launcher: {role} made no progress for {ms} ms with work waiting: hung; killed (SIGKILL) at {now_s:.3} s"
        );
        let detail = format!("no progress for {ms} ms; killed by the watchdog");
        let hang = FaultEvent { signal: Some("SIGKILL"), ..FaultEvent::now(role, "hang", detail) };
        w.events.push(hang);
        let verdict = w.supervisor.on_end(role, Ending::Hang, "hung", None, now_s, false);
        decide(role, verdict, w, now_s);
    }
}

/// Reaps the children that ended: an end nobody planned is a fault (unless it is a clean
/// exit), and goes to the restart policy. Returns how many children still run.
fn reap(
    children: &mut Children,
    w: &mut Watch,
    progress: &Progress,
    stopping: bool,
    now_s: f64,
) -> usize {
    let mut running = 0;
    for (role, c) in &mut children.0 {
        let pid = c.id();
        match c.try_wait() {
            // The gateways run until the roles are done (then they are stopped).
            Ok(None) => running += usize::from(!role.starts_with("link-")),
            Ok(Some(st)) if w.open_stops.contains_key(&pid) || !w.handled.contains(&pid) => {
                let how = Ending::of(st);
                end_stop(w, pid, how.name());
                if !w.handled.insert(pid) || w.planned.contains(&pid) || stopping {
                    continue;
                }
                if how != Ending::Exited {
                    eprintln!("launcher: {role} {} ({st}) at {now_s:.3} s", how.name());
                    let detail = st.to_string();
                    let signal = st.signal().map(signal_name);
                    let e =
                        FaultEvent { signal, ..FaultEvent::now(role.as_str(), how.name(), detail) };
                    w.events.push(e);
                }
                let what = format!("exited with {st}");
                let complete = progress.loop_complete();
                let verdict = w.supervisor.on_end(role, how, &what, st.code(), now_s, complete);
                decide(role, verdict, w, now_s);
            }
            _ => {}
        }
    }
    running
}

/// Carries out the supervisor's verdict on `role`. The monitor is an observer: when it may
/// not be restarted again, the loop goes on without it.
fn decide(role: &str, verdict: Verdict, w: &mut Watch, now_s: f64) {
    match verdict {
        Verdict::Done => {}
        Verdict::Restart { at_s } => {
            if at_s > now_s {
                eprintln!("launcher: restarting {role} in {:.1} s (backoff)", at_s - now_s);
            }
            w.restarts.insert(role.to_owned(), at_s);
        }
        Verdict::Fail(msg) if role == Role::Monitor.name() => {
            eprintln!("launcher: {msg}; the loop goes on without a monitor");
            if let Some(e) = w.events.last_mut().filter(|e| e.role == role) {
                e.detail = format!("{}; given up: {msg}", e.detail);
            }
        }
        Verdict::Fail(msg) => w.failures.push(msg),
    }
}

/// Starts `role` again (reaping the dead one first), at `at` s: the watchdog's clock starts
/// again, and the newest fault event of the role gets its restart time.
fn restart(
    launch: &Launch,
    children: &mut Children,
    rss: &mut RssLog,
    w: &mut Watch,
    role: &str,
    at: f64,
) -> anyhow::Result<()> {
    if let Some(c) = children.get_mut(role) {
        let _ = c.wait();
    }
    // After the last tick a role has nothing left to do: started again it would only
    // wait for states that never come (a plant would even start a new run). A monitor
    // that is down then has its report assembled by the launcher from the flight records.
    if w.loop_complete {
        eprintln!("launcher: {role} not restarted at {at:.3} s: the run has ended");
        if let Some(e) = w.events.iter_mut().rev().find(|e| e.role == role) {
            e.detail = format!("{}; not restarted: the run had ended", e.detail);
        }
        return Ok(());
    }
    let child = launch.spawn(role, rss).with_context(|| format!("cannot restart {role}"))?;
    if let Some(c) = children.get_mut(role) {
        *c = child;
    }
    w.watchdog.reset(role, at);
    if let Some(split) = &launch.split {
        let plant_host = split.host_of(Role::Plant.name());
        let far = role != Role::Monitor.name() && split.host_of(role) != plant_host;
        if far || role.starts_with("link-") {
            w.link.restarted(role, at, w.torques_received);
        }
    }
    if let Some(e) = w.events.iter_mut().rev().find(|e| e.role == role) {
        e.restart_ns = Some(now_ns());
    }
    eprintln!("launcher: restarted {role} at {at:.3} s");
    Ok(())
}

/// Carries out one action of the `--fault` schedule, as its row of `fault::KINDS` says.
fn injected(
    launch: &Launch,
    children: &mut Children,
    rss: &mut RssLog,
    w: &mut Watch,
    action: Action,
    at: f64,
) -> anyhow::Result<()> {
    let (kind, role) = (action.kind.spec().start, action.role.as_str());
    match action.apply() {
        Apply::Signal(sig, name) if sig == libc::SIGCONT => {
            let stopped = w.stopped.remove(role);
            let event = stop_event(&mut w.events, role);
            match children.get_mut(role) {
                Some(c) if Some(c.id()) == stopped && !w.planned.contains(&c.id()) => {
                    continue_stopped(c, event, &format!("; {name} (--fault)"));
                    eprintln!("launcher: continued {role} ({name}) at {at:.3} s");
                }
                _ => {
                    eprintln!(
                        "launcher: {role} was restarted by the watchdog before its {name} at {at:.3} s"
                    );
                    if let Some(e) = event {
                        e.detail
                            .push_str(&format!("; the watchdog restarted it before the {name}"));
                    }
                }
            }
        }
        Apply::Signal(sig, name) => {
            let Some(c) = children.get_mut(role) else { return Ok(()) };
            let pid = c.id();
            let e = FaultEvent {
                signal: Some(name),
                ..FaultEvent::now(role, kind, format!("{name} (--fault)"))
            };
            if sig == libc::SIGKILL {
                w.planned.insert(pid);
            }
            signal(c, sig);
            if sig == libc::SIGKILL {
                let _ = c.wait(); // reap: an unreaped zombie can delay dead-node detection
                w.handled.insert(pid);
                end_stop(w, pid, "killed");
            } else if sig == libc::SIGSTOP {
                w.stopped.insert(role.to_owned(), pid);
                w.watchdog.stopped(role);
                w.open_stops.insert(pid, w.events.len());
            }
            let verb = match sig {
                libc::SIGKILL => "killed",
                libc::SIGSTOP => "stopped",
                _ => "signalled",
            };
            eprintln!("launcher: {verb} {role} ({name}) at {at:.3} s");
            w.events.push(e);
        }
        Apply::Restart => {
            w.restarts.remove(role); // the schedule's restart replaces a supervisor's
            restart(launch, children, rss, w, role, at)?;
        }
        Apply::ByTheRole(flag) if action.starts => {
            let FaultKind::Delay(d) = action.kind else { return Ok(()) };
            let ms = d * 1e3;
            eprintln!("launcher: {role} answers {ms} ms late from {at:.3} s ({flag})");
            let detail = format!("each answer sent {ms} ms late (--fault {kind})");
            w.events.push(FaultEvent::now(role, kind, detail));
        }
        Apply::ByTheRole(_) => {
            eprintln!("launcher: {role}'s {kind} ends at {at:.3} s");
            if let Some(e) = w.events.iter_mut().rev().find(|e| e.role == role && e.kind == kind) {
                e.restart_ns = Some(now_ns());
            }
        }
    }
    Ok(())
}

/// After the run: memory figures into `summary.json` and on the console, the fault report.
fn report(
    launch: &Launch,
    scenario: &rotorloop_common::Scenario,
    rss: &RssLog,
    events: &[FaultEvent],
    flight: Option<&std::path::Path>,
) -> anyhow::Result<()> {
    let args = launch.args;
    launch.report_without_monitor(scenario, flight);
    if !args.no_monitor {
        if let Err(e) = add_resources(&args.out, &rss.tracks) {
            eprintln!("warning: resource report not added to summary.json: {e:#}");
        }
    }
    if !args.quiet {
        for (role, r) in &rss.tracks {
            let [a0, f0, s0] = r.start_parts_kib;
            let [a1, f1, s1] = r.end_parts_kib;
            println!(
                "{role:<10} RSS {:>7} KiB at {:>6.1} s → {:>7} KiB at {:>8.1} s (max {} KiB); \
                 anon {a0} → {a1}, file {f0} → {f1}, shmem {s0} → {s1} KiB",
                r.start_kib, r.start_at_s, r.end_kib, r.end_at_s, r.max_kib
            );
        }
    }
    if !events.is_empty() && !args.no_monitor {
        if let Err(e) = crate::run::fault::report::report(&args.out, scenario, events) {
            eprintln!("warning: no fault report: {e:#}");
            for e in events {
                eprintln!("  {} {}: {}", e.kind, e.role, e.detail);
            }
        }
    }
    if shutdown_requested() {
        eprintln!("stopped by signal; partial report in {}", args.out.display());
        return Err(RunEnd::StoppedBySignal.into());
    }
    if !args.no_monitor && !args.quiet {
        match args.out.join("summary.json").exists() {
            true => println!("report: {}", args.out.display()),
            false => println!(
                "report: no summary.json in {} (see the monitor's messages above)",
                args.out.display()
            ),
        }
    }
    Ok(())
}

/// Each role's resident memory, sampled once a second into `rss.csv`. A file that cannot
/// be written (a full disk) is given up with a warning: memory figures are an observer's,
/// never a reason to stop the loop.
struct RssLog {
    tracks: BTreeMap<String, RssTrack>,
    csv: Option<std::io::BufWriter<std::fs::File>>,
    t0: u64,
    next_ns: u64,
}

impl RssLog {
    fn create(out: &std::path::Path) -> Self {
        use std::io::Write;
        let path = out.join("rss.csv");
        let csv = std::fs::File::create(&path).map(std::io::BufWriter::new).and_then(|mut f| {
            writeln!(f, "t_s,role,pid,rss_kib,anon_kib,file_kib,shmem_kib")?;
            Ok(f)
        });
        let csv = csv.map_err(|e| eprintln!("warning: cannot write {}: {e}", path.display())).ok();
        Self { tracks: BTreeMap::new(), csv, t0: now_ns(), next_ns: now_ns() }
    }

    /// A new life of `role` (its figures are of its last life).
    fn track(&mut self, role: &str, pid: u32) {
        self.tracks.insert(role.to_owned(), RssTrack::new(pid));
    }

    fn sample_if_due(&mut self) {
        use std::io::Write;
        if now_ns() < self.next_ns {
            return;
        }
        self.next_ns += 1_000_000_000;
        let t = (now_ns() - self.t0) as f64 / 1e9;
        let mut rows = String::new();
        for (role, track) in self.tracks.iter_mut() {
            if let Some((kib, [anon, file, shmem])) = track.sample() {
                rows += &format!("{t:.1},{role},{},{kib},{anon},{file},{shmem}\n", track.pid);
            }
        }
        if let Some(csv) = &mut self.csv {
            if let Err(e) = csv.write_all(rows.as_bytes()).and_then(|()| csv.flush()) {
                eprintln!(
                    "warning: cannot write rss.csv any more ({e}); memory figures go on in memory"
                );
                self.csv = None;
            }
        }
    }
}

/// Adds the per-role memory figures to `out/summary.json` as `resources`.
fn add_resources(out: &std::path::Path, rss: &BTreeMap<String, RssTrack>) -> anyhow::Result<()> {
    rotorloop_common::output::patch_summary(out, |j| {
        j["resources"] = serde_json::json!({ "rss": rss, "rss_csv": "rss.csv" })
    })
}
