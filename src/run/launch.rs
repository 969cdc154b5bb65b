//! `rotorloop run`: starts the four processes from this very executable (so they are
//! always the same build), pins them, shows the monitor's live status line, stops them
//! cleanly at the end or on Ctrl-C/SIGTERM, and leaves the report in `--out`.

use anyhow::Context;
use rotorloop_common::signals::{install_signal_handlers, shutdown_requested};

use rotorloop_common::ipc::domain::Domain;

use crate::observe::foxglove::Beside;
use crate::run::args::{RunArgs, pin_text, pins, with_preset};
use crate::run::fault::{Fault, FaultEvent, FaultSchedule, RunShape, parse_fault};
use crate::run::policy::{Children, RestartLimit, Supervisor, parse_restart};
use crate::run::resources::{RssLog, add_resources};
use crate::run::spawn::{
    Launch, clear_flight_records, make_staging, prepare_domains, staging_dir, start, stop_gateways,
};
use crate::run::split::Split;
use crate::run::supervise::supervise;
use rotorloop_common::graph::Role;
use rotorloop_common::role::UsageError;
use rotorloop_common::role::args::{Mode, RoleArgs};
use rotorloop_controller::law::AnyLaw;
/// How a run ended without completing its control loop (mapped to exit codes by the CLI).
#[derive(Debug, thiserror::Error)]
pub enum RunEnd {
    /// SIGINT or SIGTERM before the plant's last tick: exit code 3.
    #[error("the run was stopped by a signal before its last tick")]
    StoppedBySignal,
}

/// The `--fault`s, checked against each other, against the run (a fault that cannot
/// happen in it is refused) and against the placement of the roles, and their schedule.
fn checked_faults(
    args: &RunArgs,
    split: Option<&Split>,
    scenario: &rotorloop_common::scenario::Scenario,
) -> anyhow::Result<(Vec<Fault>, FaultSchedule)> {
    let rate_hz = scenario.file.run.rate_hz;
    let faults =
        args.fault.iter().map(|f| parse_fault(f, rate_hz)).collect::<Result<Vec<_>, _>>()?;
    crate::run::fault::check_overlaps(&args.fault, &faults)?;
    let shape = RunShape {
        ticks: scenario.ticks(),
        rate_hz,
        lockstep: args.role.mode == Mode::Lockstep,
        no_watchdog: args.watchdog_ms == 0,
    };
    crate::run::fault::check_against_run(&args.fault, &faults, shape)?;
    for f in &faults {
        match split {
            Some(s) => s.check_fault_target(&f.role)?,
            None if f.role.role().is_none() => {
                return Err(UsageError(format!(
                    "--fault {}: gateways exist only with --split",
                    f.role
                ))
                .into());
            }
            None => {}
        }
    }
    let schedule = FaultSchedule::new(faults.clone(), args.role.mode == Mode::Lockstep);
    if args.no_gate && !schedule.gate_ticks().is_empty() {
        let why = "--no-gate: a lockstep --fault needs the plant's gate to land at its tick";
        return Err(UsageError(why.into()).into());
    }
    Ok((faults, schedule))
}

/// The domain of a run without `--domain`: `run-` and 7 random characters (36 bits from
/// the kernel), so another user cannot make its files ahead of it (an earlier
/// `run-<pid>` could be: the next 500 pids' names were planted and a plain run fell into
/// one). A name of which anything already exists in `/dev/shm` is drawn again.
fn default_domain() -> String {
    loop {
        let name = format!("run-{}", rotorloop_common::private::random_name(7));
        let prefix = Domain::prefix_of(&name);
        let staged = rotorloop_common::flight::staging_dir(&name);
        let taken = staged.is_some_and(|d| std::fs::symlink_metadata(d).is_ok())
            || std::fs::read_dir("/dev/shm")
                .into_iter()
                .flatten()
                .flatten()
                .any(|e| e.file_name().to_string_lossy().starts_with(&prefix));
        if !taken {
            return name;
        }
    }
}

/// What the run makes its own before any role starts. First whether the domain is in use:
/// a launch refused touches nothing of a live run. Then the launcher's staging directory
/// in `/dev/shm` (made privately, or this user's own from an earlier run:
/// `rotorloop_common::private`), cleared of an earlier run's records, and each domain's
/// directory and iceoryx2 global segment, made privately.
fn claim(
    args: &RunArgs,
    record: Option<&std::path::Path>,
    domains: &[Domain],
) -> anyhow::Result<()> {
    prepare_domains(domains, &args.out)?;
    let held = hold(args, record, domains);
    if held.is_err() {
        // A refused start leaves nothing of its own behind (another user's is never
        // touched), and nothing of a live run: the domain was free (above).
        release(args, record, domains);
    }
    held
}

/// The resume slots every role opens (`rl_<D>_resume_<role>`): made by the launcher,
/// privately, before any role starts, so that no name a role will open is left for
/// another user to make once the domain's name is public.
const SLOTS: [&str; 5] = [
    Role::ALL[0].name(),
    Role::ALL[1].name(),
    Role::ALL[2].name(),
    Role::ALL[3].name(),
    rotorloop_common::wire::Refusals::SLOT,
];

/// [`claim`]'s part that makes things: the staging directory first (the domain's private
/// directory), then each domain's directory, global segment and resume slots; then
/// whether anything of the domain is another user's (made in the meantime).
fn hold(
    args: &RunArgs,
    record: Option<&std::path::Path>,
    domains: &[Domain],
) -> anyhow::Result<()> {
    if let Some(dir) = record {
        if args.role.record.is_none() {
            make_staging(dir)?;
            // Where the records are moved: a directory of OUT's own (never a link), 0700
            // when new, as the records are the run's user's alone.
            rotorloop_common::outdir::OutDir::open(&args.out)?.subdir_mode("flight", 0o700)?;
        }
        // An earlier run's records in the same directory are not this run's to continue.
        clear_flight_records(dir)?;
        clear_flight_records(&args.out.join("flight"))?;
    }
    for domain in domains {
        domain.make_private()?;
        for role in SLOTS {
            let path = format!("/dev/shm/{}resume_{role}", domain.prefix());
            rotorloop_common::private::open_or_create_file(std::path::Path::new(&path))?;
        }
        if let Some(f) = domain.foreign_files().into_iter().next() {
            return Err(rotorloop_common::private::PrivateError::from(f).into());
        }
    }
    Ok(())
}

/// Removes what this launcher made of `domains` and of its staging directory `record`,
/// after a refused start: only this user's own (another user's is never followed or
/// removed). Nothing of the domain runs (the launcher checked before making anything).
fn release(args: &RunArgs, record: Option<&std::path::Path>, domains: &[Domain]) {
    use std::os::unix::fs::MetadataExt;
    let me = rotorloop_common::private::euid();
    let mine = |p: &std::path::Path| std::fs::symlink_metadata(p).is_ok_and(|m| m.uid() == me);
    if let Some(dir) = record.filter(|_| args.role.record.is_none()) {
        let in_shm = dir.parent().is_some_and(|p| p == std::path::Path::new("/dev/shm"));
        if in_shm && mine(dir) && std::fs::symlink_metadata(dir).is_ok_and(|m| m.is_dir()) {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
    for domain in domains {
        release_domain(domain);
    }
}

/// Removes this user's own files of `domain` (its directory, its `/dev/shm` files), none
/// of another user's; for a domain none of whose processes runs.
fn release_domain(domain: &Domain) {
    use std::os::unix::fs::MetadataExt;
    let me = rotorloop_common::private::euid();
    let mine = |p: &std::path::Path| std::fs::symlink_metadata(p).is_ok_and(|m| m.uid() == me);
    let root = domain.root_dir();
    if mine(&root) && std::fs::symlink_metadata(&root).is_ok_and(|m| m.is_dir()) {
        let _ = std::fs::remove_dir_all(&root);
    }
    for e in std::fs::read_dir("/dev/shm").into_iter().flatten().flatten() {
        let named = e.file_name().to_string_lossy().starts_with(domain.prefix());
        if named && mine(&e.path()) && e.file_type().is_ok_and(|t| !t.is_dir()) {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

/// [`claim`], and for a run without `--domain` (`defaulted`), a name of which another
/// user made anything (seen as soon as the staging directory appears) is given up (what
/// this launcher made of it removed) and another drawn: a planted default domain is
/// never a refusal. Returns the domains held; `role_args` names the one drawn.
fn claim_drawing(
    args: &RunArgs,
    role_args: &mut RoleArgs,
    split: Option<&Split>,
    defaulted: bool,
) -> anyhow::Result<Vec<Domain>> {
    const DRAWS: usize = 64;
    let mut draw = 0;
    loop {
        let domains = domains_of(split, role_args)?;
        let claimed = claim(args, role_args.record.as_deref(), &domains);
        match claimed {
            Ok(()) => return Ok(domains),
            Err(e) if defaulted && draw < DRAWS && foreign(&e) => {
                draw += 1;
                eprintln!(
                    "launcher: another user made files of domain `{}` ({e:#}); drawing another \
                     name",
                    role_args.domain()
                );
                role_args.domain = Some(default_domain());
                if args.role.record.is_none() && !args.no_record {
                    role_args.record = Some(staging_dir(role_args, &args.out));
                }
            }
            Err(e) => return Err(e),
        }
    }
}

/// Whether `e` refuses something another user made.
fn foreign(e: &anyhow::Error) -> bool {
    use rotorloop_common::private::{Foreign, PrivateError};
    e.downcast_ref::<Foreign>().is_some()
        || matches!(e.downcast_ref::<PrivateError>(), Some(PrivateError::Foreign(_)))
        || e.downcast_ref::<rotorloop_common::ipc::IpcError>().is_some_and(|i| i.is_foreign())
}

/// `--corrupt`'s corruptions and the supervisor of `--restart` and `--restart-limit`.
#[allow(clippy::type_complexity)]
fn corruptions_and_supervisor(
    args: &RunArgs,
    scenario: &rotorloop_common::scenario::Scenario,
) -> Result<(Vec<(String, rotorloop_common::role::inject::Corrupt)>, Supervisor), UsageError> {
    let (rate_hz, ticks) = (scenario.file.run.rate_hz, scenario.ticks());
    let corrupt = args
        .corrupt
        .iter()
        .map(|c| crate::run::fault::parse_corrupt(c, rate_hz, ticks))
        .collect::<Result<Vec<_>, _>>()?;
    let limit: RestartLimit =
        args.restart_limit.parse().map_err(|e| UsageError(format!("--restart-limit {e}")))?;
    Ok((corrupt, Supervisor::new(parse_restart(&args.restart)?, limit)))
}

/// The run's domain as each of its hosts sees it (one, with no host, unless split).
fn domains_of(split: Option<&Split>, role_args: &RoleArgs) -> Result<Vec<Domain>, UsageError> {
    let hosts: Vec<Option<&str>> = match split {
        Some(s) => s.hosts().iter().map(|h| Some(h.as_str())).collect(),
        None => vec![role_args.host.as_deref()],
    };
    hosts
        .iter()
        .map(|h| Domain::on_host(role_args.domain(), *h).map_err(|e| UsageError(e.to_string())))
        .collect()
}

/// Runs the four processes to the end of the scenario.
pub fn run(args: &RunArgs) -> anyhow::Result<()> {
    // `--wait` has a default, so "explicit" means: not the default (event).
    let explicit_wait = args.role.wait != rotorloop_common::ipc::wait::Wait::Event;
    let args = &with_preset(args, explicit_wait)?;
    // Held to the end of the run (and by the kernel to this launcher's death).
    let _idle = rotorloop_common::rt::CpuDmaLatency::hold_or_warn(args.cpu_dma_latency);
    let scenario = args.role.scenario()?;
    Beside::check(args.foxglove.as_deref(), args.split.is_some())?;
    // The law is the controller's to name: refused here, before any process starts.
    AnyLaw::for_scenario(&scenario, scenario.actuation()).map_err(UsageError::from)?;
    for w in &scenario.warnings {
        eprintln!("warning: {w}");
    }
    crate::run::budget::check(args, &scenario)?;
    let (corrupt, supervisor) = corruptions_and_supervisor(args, &scenario)?;
    let mut role_args = args.role.clone();
    let defaulted = role_args.domain.is_none();
    role_args.domain.get_or_insert_with(default_domain);
    role_args.record = match args.no_record {
        true => None,
        false => {
            Some(role_args.record.clone().unwrap_or_else(|| staging_dir(&role_args, &args.out)))
        }
    };
    let split = args.split.as_deref().map(|s| Split::parse(s, !args.no_monitor)).transpose()?;
    let duration_s = scenario.ticks() as f64 * scenario.dt();
    let (faults, schedule) = checked_faults(args, split.as_ref(), &scenario)?;
    let external = crate::run::external::check(args, &faults)?.map(|e| (e, scenario.clone()));
    if split.is_some() {
        crate::run::split::link_binary()?;
    }
    let topology = crate::cpus::run_topology(args.cpus.as_deref())?;
    let pins = pins(args, &topology)?;
    // OUT must be this user's alone (exit 2 naming it, its owner and mode otherwise): made
    // with the user's umask where missing, before anything is written into it.
    rotorloop_common::outdir::OutDir::make(&args.out)?;
    // The machine state the run's figures were taken in.
    crate::doctor::write_into(&args.out, 1.0 / scenario.dt(), duration_s, Some(&topology.allowed));
    let domains = claim_drawing(args, &mut role_args, split.as_ref(), defaulted)?;
    if let Some(s) = &split {
        // The link's one-time credentials, before any gateway: a run that cannot make
        // them privately stops here, naming why.
        s.credentials(role_args.domain()).map_err(anyhow::Error::msg)?;
    }
    if args.controller_cmd.is_some() {
        crate::run::external::write_run_files(&args.out, &scenario)?;
    }
    let exe = std::env::current_exe().context("cannot find the rotorloop executable")?;
    install_signal_handlers();
    let link_port = split.as_ref().map_or(Ok(0), |_| crate::run::split::port(args.link_port))?;
    let mut launch = Launch {
        args,
        shm_need: crate::run::budget::estimate(args, &scenario).staging,
        domains,
        split,
        link_port,
        faults: faults.clone(),
        supervisor,
        role_args,
        pins,
        cpus: args.cpus.is_some().then(|| crate::cpus::cpu_set(&topology.allowed)),
        corrupt,
        exe,
        ticks: scenario.ticks(),
        rate_hz: scenario.file.run.rate_hz,
        gates: schedule.gate_ticks(),
        external,
    };
    // In lockstep the plant waits for this launcher's mover rather than lose records.
    launch.role_args.flight_moved = launch.mover().is_some();
    // What `rotorloop recover` needs should this launcher not end normally.
    let record = crate::run::recover::LaunchRecord {
        domain: launch.role_args.domain().to_owned(),
        hosts: launch.monitor_hosts(),
        role_args: launch.role_args.to_args(),
        scenario: scenario.file.clone(),
        staging: launch.role_args.record.clone(),
        moved: args.role.record.is_none(),
        csv: !args.no_csv,
        launcher_pid: std::process::id(),
    };
    record.write(&args.out)?;
    let (mut rss, traced) = observers(args, launch.role_args.domain())?;
    let mut children = Children::default();
    let domain = launch.role_args.domain();
    let live = args.foxglove.as_deref().map(|a| Beside::start(&launch.exe, domain, a, &args.out));
    let live = live.transpose()?;
    let launched_ns = rotorloop_common::clock::now_ns();
    let started = start(&launch, &mut children, &mut rss);
    if started.is_ok() {
        crate::run::spawn::write_record(
            &args.out,
            &topology.allowed,
            pin_text(args, &launch.pins).as_deref(),
            &children,
        );
    }
    let supervised = started.and_then(|()| supervise(&launch, &mut children, &mut rss, schedule));
    stop_gateways(&mut children, args.quiet);
    drop(children);
    // A live view not served is a warning of the report too (the run still exits 0).
    let _ = live.and_then(Beside::stop).inspect(|w| warn_in_summary(&args.out, w));
    launch.clean_up();
    // sched.csv and the trace complete before the incidents read them.
    (rss.sched, _) = (None, traced);
    let flight = launch.keep_flight_records();
    // A failure stops the run, but its report (the faults that led to it among them) is
    // written as for any other end.
    let crate::run::supervise::Supervised { events, failure, durable_lag_max } = supervised?;
    let ran = (&events[..], launched_ns, durable_lag_max);
    let reported = report(&launch, &scenario, &rss, ran, flight.as_deref());
    match failure {
        Some(f) => Err(refusal_or(f)),
        None => reported,
    }
}

/// `summary.json` `flight.durable_lag_max_s`: the longest the record's newest ticks were
/// from the disk (`Mover::durable_lag_max`), where the run kept a journal.
fn note_durable_lag(out: &std::path::Path, lag: Option<std::time::Duration>) {
    let Some(lag) = lag else { return };
    let _ = rotorloop_monitor::summary::patch(out, |j| {
        if j["flight"].is_object() {
            j["flight"]["durable_lag_max_s"] = lag.as_secs_f64().into();
        }
    });
}

/// Adds `w` to `summary.json`'s `warnings` (made if need be).
fn warn_in_summary(out: &std::path::Path, w: &str) {
    let warned = rotorloop_monitor::summary::patch(out, |j| match j["warnings"].as_array_mut() {
        Some(all) => all.push(w.into()),
        None => j["warnings"] = serde_json::json!([w]),
    });
    if let Err(e) = warned {
        eprintln!("warning: not in summary.json ({e:#}): {w}");
    }
}

/// A run stopped by a role that refused its input or diverged (it exited 2:
/// [`crate::run::policy::REFUSED`]) is the user's to mend (exit 2), as in `sim`.
fn refusal_or(failure: anyhow::Error) -> anyhow::Error {
    match failure.to_string().contains(crate::run::policy::REFUSED) {
        true => UsageError(format!("{failure:#}")).into(),
        false => failure,
    }
}

/// What watches the roles from the launcher: memory (`rss.csv`), scheduling
/// (`sched.csv`) and, with `--trace-sched`, the kernel's scheduler trace.
fn observers(
    args: &RunArgs,
    domain: &str,
) -> anyhow::Result<(RssLog, Option<crate::run::tracesched::TraceSched>)> {
    let rss = RssLog::create(&args.out, !args.no_sched_sample, args.no_csv);
    let traced = match args.trace_sched {
        true => Some(crate::run::tracesched::TraceSched::start(&args.out, domain)?),
        false => None,
    };
    Ok((rss, traced))
}

impl Launch<'_> {
    /// After the roles: everything of the run's domains is gone, so remove what iceoryx2
    /// keeps after its nodes, and the split run's ready files.
    fn clean_up(&self) {
        for domain in &self.domains {
            if let Err(e) = domain.cleanup() {
                // Another user's file among them: this user's own are removed all the same
                // (no process of the run is left), the other user's stay.
                eprintln!("warning: cleaning up domain {}: {e}", domain.name());
                release_domain(domain);
            }
        }
        for h in self.split.iter().flat_map(|s| s.hosts()) {
            let _ = std::fs::remove_file(crate::run::split::ready_file(&self.args.out, h));
        }
    }
}

/// After the run: memory figures into `summary.json` and on the console, the fault report.
fn report(
    launch: &Launch,
    scenario: &rotorloop_common::scenario::Scenario,
    rss: &RssLog,
    (events, launched_ns, durable_lag): (&[FaultEvent], u64, Option<std::time::Duration>),
    flight: Option<&std::path::Path>,
) -> anyhow::Result<()> {
    let args = launch.args;
    let lockstep = args.role.mode == Mode::Lockstep;
    launch.report_without_monitor(scenario, flight);
    // Before `run.mcap`, which attaches the summary.
    note_durable_lag(&args.out, durable_lag);
    let schedule: Vec<serde_json::Value> = launch.faults.iter().map(|f| f.scheduled()).collect();
    if let Err(e) = rotorloop_monitor::summary::patch(&args.out, |j| {
        j["fault_schedule"] = serde_json::json!(schedule);
        j["plant_stall"] = serde_json::json!(args.plant_stall.to_string());
    }) {
        eprintln!("warning: the fault schedule is not in summary.json: {e:#}");
    }
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
        if let Err(e) =
            crate::run::fault::report::report(&args.out, scenario, events, (launched_ns, lockstep))
        {
            eprintln!("warning: no fault report: {e:#}");
            for e in events {
                eprintln!("  {} {}: {}", e.kind, e.role, e.detail);
            }
        }
    }
    if flight.is_some() {
        let steps = crate::pipeline::Steps {
            incidents: !args.no_monitor,
            mcap: !args.no_mcap,
            quiet: args.quiet,
        };
        crate::pipeline::finish(&args.out, steps);
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
