//! What the launcher starts and how (`Launch`): each role's command line from this very
//! executable (so the four are always the same build), its pins, corruptions and faults
//! the role applies itself, the run's domains on each host, the gateways of a split run,
//! and the flight records' staging.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use anyhow::Context;
use rotorloop_monitor::hosts::Hosts;

use rotorloop_common::graph::{Role, Topic};
use rotorloop_common::ipc::domain::Domain;

use crate::run::args::RunArgs;
use crate::run::fault::Fault;
use crate::run::policy::{Children, Supervisor};
use crate::run::resources::RssLog;
use crate::run::split::{Split, wait_until};
use rotorloop_common::role::UsageError;
use rotorloop_common::role::args::RoleArgs;
use rotorloop_common::role::inject::Corrupt;

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

/// Gives the child `set` as its CPU affinity (`--cpus`) before it runs anything.
fn on_cpus(cmd: &mut Command, set: Option<libc::cpu_set_t>) {
    use std::os::unix::process::CommandExt;
    let Some(set) = set else { return };
    // SAFETY: runs in the child between fork and exec, calling only sched_setaffinity
    // (a plain syscall) with a set made before the fork.
    unsafe {
        cmd.pre_exec(move || {
            if libc::sched_setaffinity(0, size_of::<libc::cpu_set_t>(), &set) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}

/// What the launcher starts, and how: the roles' arguments, pins, corruptions, and the
/// executable they run from (this one, so the four are always the same build).
pub(crate) struct Launch<'a> {
    pub(crate) args: &'a RunArgs,
    /// What the run needs on `/dev/shm` while it goes on (bytes: its flight rings), named
    /// when a role dies where `/dev/shm` is full.
    pub(crate) shm_need: u64,
    /// The run's domain as each host sees it (one, with no host, unless split).
    pub(crate) domains: Vec<Domain>,
    pub(crate) split: Option<Split>,
    /// The first host's gateway listens on this loopback port.
    pub(crate) link_port: u16,
    pub(crate) faults: Vec<Fault>,
    pub(crate) supervisor: Supervisor,
    pub(crate) role_args: RoleArgs,
    pub(crate) pins: BTreeMap<Role, usize>,
    /// `--cpus`: every child's affinity, set between fork and exec.
    pub(crate) cpus: Option<libc::cpu_set_t>,
    pub(crate) corrupt: Vec<(String, Corrupt)>,
    pub(crate) exe: PathBuf,
    /// The run's ticks.
    pub(crate) ticks: u64,
    /// The run's rate (Hz).
    pub(crate) rate_hz: f64,
    /// Lockstep: the ticks the plant holds at for the fault schedule (`--gate-ticks`).
    pub(crate) gates: Vec<u64>,
    /// `--controller-cmd`: the user's controller, and the scenario as run it is told of.
    pub(crate) external:
        Option<(crate::run::external::ExternalController, rotorloop_common::scenario::Scenario)>,
}

impl Launch<'_> {
    /// The command line of `role`: `rotorloop role ROLE` with the run's arguments.
    pub(crate) fn command(&self, role: &str) -> Command {
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
            on_cpus(&mut cmd, self.cpus);
            return cmd;
        }
        let mut r = self.role_args.clone();
        r.core = role.parse::<Role>().ok().and_then(|r| self.pins.get(&r)).copied();
        r.host = self.split.as_ref().and_then(|s| s.host_of(role)).map(str::to_owned);
        if let (Some((ext, scenario)), Ok(Role::Controller)) = (&self.external, role.parse()) {
            let mut cmd = ext.command(&r, &args.out, scenario);
            cmd.stdin(Stdio::null());
            stop_with_parent(&mut cmd);
            on_cpus(&mut cmd, self.cpus);
            if args.quiet {
                cmd.stdout(Stdio::null());
            }
            return cmd;
        }
        let mut cmd = Command::new(&self.exe);
        cmd.arg("role").arg(role).args(r.to_args()).stdin(Stdio::null());
        stop_with_parent(&mut cmd);
        on_cpus(&mut cmd, self.cpus);
        for (_, c) in self.corrupt.iter().filter(|(r, _)| r == role) {
            cmd.arg("--corrupt").arg(c.to_string());
        }
        if args.quiet {
            cmd.stdout(Stdio::null());
        }
        match role.parse::<Role>() {
            Ok(Role::Monitor) => {
                cmd.arg("--out").arg(&args.out);
                if args.no_csv {
                    cmd.arg("--no-csv");
                }
                if let Some(hosts) = self.monitor_hosts() {
                    cmd.arg("--hosts").arg(hosts);
                }
                // On a terminal (the launcher's stderr is a relay's pipe by now).
                if !args.quiet && rotorloop_common::relay::stderr_was_terminal() {
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
                cmd.arg("--plant-stall").arg(args.plant_stall.to_string());
                if !self.gates.is_empty() {
                    let gates: Vec<String> = self.gates.iter().map(u64::to_string).collect();
                    cmd.arg("--gate-ticks").arg(gates.join(","));
                } else if args.no_gate {
                    cmd.arg("--no-gate");
                }
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
    pub(crate) fn monitor_hosts(&self) -> Option<String> {
        let s = self.split.as_ref()?;
        let hosts: Vec<String> =
            Role::ALL.iter().filter_map(|r| s.host(*r).map(|h| format!("{r}={h}"))).collect();
        Some(hosts.join(","))
    }

    /// A monitor that left no report (killed for good, or its restart refused): the
    /// report from the flight records, without a live view.
    pub(crate) fn report_without_monitor(
        &self,
        scenario: &rotorloop_common::scenario::Scenario,
        dir: Option<&std::path::Path>,
    ) {
        let (out, Some(dir)) = (&self.args.out, dir) else { return };
        if self.args.no_monitor || out.join("summary.json").exists() {
            return;
        }
        let records = match rotorloop_monitor::assemble::FlightRecords::read(dir, scenario.ticks())
        {
            Ok(r) => r,
            Err(e) => return eprintln!("launcher: no summary.json and no report from {e}"),
        };
        let hosts = self.monitor_hosts().and_then(|h| Hosts::parse(&h).ok()).unwrap_or_default();
        let summary = rotorloop_monitor::assemble::report(
            out,
            dir,
            &records,
            (scenario, &self.role_args, !self.args.no_csv),
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
    pub(crate) fn keep_flight_records(&self) -> Option<PathBuf> {
        let staged = self.role_args.record.clone()?;
        let kept = self.args.out.join("flight");
        if self.args.role.record.is_some() || staged == kept {
            return Some(staged); // recorded where the user asked
        }
        if let Err(e) =
            rotorloop_common::flight::move_records(&staged, &kept, !self.args.raw_segments)
        {
            let (s, k) = (staged.display(), kept.display());
            eprintln!("warning: the flight records stay in {s}: cannot move them into {k}: {e}");
            return Some(staged);
        }
        let _ = rotorloop_monitor::summary::patch(&self.args.out, |j| {
            if j["flight"].is_object() {
                j["flight"]["dir"] = kept.display().to_string().into();
            }
        });
        Some(kept)
    }

    /// The mover of the records into `OUT/flight` while the run goes on, when the records
    /// are the launcher's to move (see `common::flight`): the finished halves of rings
    /// shorter than the run, and the journal of every stream's newest ticks.
    pub(crate) fn mover(&self) -> Option<rotorloop_common::flight::Mover> {
        use rotorloop_common::flight::{Mover, ring_capacity, ring_wraps};
        let staged = self.role_args.record.as_ref()?;
        let ring = ring_capacity(self.ticks, self.role_args.flight_ring_ticks);
        let mover = Mover::new(staged, &self.args.out.join("flight"));
        let mover = if ring_wraps(self.ticks, ring) {
            mover.with_half(ring / 2)
        } else {
            mover.whole_run()
        };
        self.args
            .role
            .record
            .is_none()
            .then_some(mover)
            .map(|m| if self.args.raw_segments { m.raw() } else { m })
            .map(|m| if self.args.no_journal { m.without_journal() } else { m })
    }

    /// The domain as `role`'s host sees it.
    pub(crate) fn domain_of(&self, role: &str) -> &Domain {
        let host = self.split.as_ref().and_then(|s| s.host_of(role));
        self.domains.iter().find(|d| d.host() == host).unwrap_or(&self.domains[0])
    }

    pub(crate) fn spawn(&self, role: &str, rss: &mut RssLog) -> anyhow::Result<Child> {
        let child = self.command(role).spawn().with_context(|| format!("cannot start {role}"))?;
        rss.track(role, child.id());
        Ok(child)
    }
}

/// Writes each host's iceoryx2 configuration for `iox2`, and clears what an earlier, killed
/// run of the domain left (resume slots included, which would otherwise be taken for a
/// restart); a domain still in use by a live process is refused.
pub(crate) fn prepare_domains(domains: &[Domain], out: &std::path::Path) -> anyhow::Result<()> {
    for domain in domains {
        let dir = match domain.host() {
            Some(h) => {
                // Made in OUT, never through a link ([`rotorloop_common::outdir`]).
                let name = format!("host-{h}");
                rotorloop_common::outdir::OutDir::open(out)?.subdir(&name)?;
                out.join(name)
            }
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

/// Makes the launcher's staging directory in `/dev/shm` (mode 0700), or takes this
/// user's own private one an earlier run of the domain left; anything else there
/// (another user's directory, a link) is refused, exit 2, naming it and its owner.
pub(crate) fn make_staging(dir: &std::path::Path) -> anyhow::Result<()> {
    match dir.parent().is_some_and(|p| p == std::path::Path::new("/dev/shm")) {
        true => rotorloop_common::private::dir(dir).map_err(anyhow::Error::from),
        false => {
            std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))
        }
    }
}

/// Where the roles record during a run: a directory of the domain on tmpfs
/// (`/dev/shm/rotorloop-flight-DOMAIN`), moved into `OUT/flight` at the end. A mapped
/// page of a disk file is write-protected until its first write and again after each
/// writeback, so one record in eight would take a page fault into the filesystem
/// (measured on ext4: p99 of a record 2.5 µs instead of 50 ns); tmpfs has no writeback.
/// Without `/dev/shm`, `OUT/flight` itself.
pub(crate) fn staging_dir(role: &RoleArgs, out: &std::path::Path) -> PathBuf {
    rotorloop_common::flight::staging_dir(role.domain()).unwrap_or_else(|| out.join("flight"))
}

/// Removes the flight records an earlier run left in `dir`, naming each.
pub(crate) fn clear_flight_records(dir: &std::path::Path) -> anyhow::Result<()> {
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
pub(crate) fn start(
    launch: &Launch,
    children: &mut Children,
    rss: &mut RssLog,
) -> anyhow::Result<()> {
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
    // The listener first, holding its port, then the one that dials it.
    for (i, g) in split.gateways().into_iter().enumerate() {
        children.0.push((g.clone(), launch.spawn(&g, rss)?));
        if i == 0 {
            let (_, listener) = children.0.last_mut().expect("just pushed");
            crate::run::split::wait_listening(listener, launch.link_port)?;
        }
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

/// Stops the gateways once the roles are done: SIGTERM to all at once, then each is
/// waited for (SIGKILL after 5 s). Unless `quiet`, it first says so on the launcher's own
/// stderr: whatever a gateway says after that line (one may see the other's offers go
/// before its own SIGTERM lands, and say `no longer bridging`) is the shutdown, not the
/// run.
pub(crate) fn stop_gateways(children: &mut Children, quiet: bool) {
    let mut gateways: Vec<_> = children
        .0
        .iter_mut()
        .filter(|(n, _)| n.starts_with("link-"))
        .filter_map(|(n, c)| running(c).then_some((n, c)))
        .collect();
    if gateways.is_empty() {
        return;
    }
    if !quiet {
        eprintln!("launcher: the roles are done; stopping the link gateways");
    }
    for (_, c) in gateways.iter_mut() {
        crate::run::policy::signal(c, libc::SIGTERM);
    }
    for (name, c) in gateways {
        crate::run::split::stop(name, c);
    }
}

fn running(c: &mut std::process::Child) -> bool {
    matches!(c.try_wait(), Ok(None))
}

/// `OUT/cpus.json`: the run's CPU set, its `--pin`, and each child's affinity as the
/// kernel gave it just after the start (before a pinned role has pinned itself, its
/// run's set; after, its core). Not written is no matter to the run (a warning).
pub fn write_record(
    out: &std::path::Path,
    cpus: &[usize],
    pin: Option<&str>,
    children: &crate::run::policy::Children,
) {
    let roles: serde_json::Map<String, serde_json::Value> = children
        .0
        .iter()
        .map(|(name, c)| {
            let allowed = crate::cpus::allowed_of(c.id());
            (name.clone(), serde_json::json!({ "pid": c.id(), "cpus_allowed_list": allowed }))
        })
        .collect();
    let j =
        serde_json::json!({ "cpus": crate::cpus::format_list(cpus), "pin": pin, "roles": roles });
    if let Err(e) = rotorloop_common::outdir::write_file(&out.join("cpus.json"), format!("{j:#}\n"))
    {
        eprintln!("warning: cannot write {}: {e}", out.join("cpus.json").display());
    }
}
