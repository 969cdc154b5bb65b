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
use rotorloop_common::ipc::{install_signal_handlers, now_ns, shutdown_requested};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::wire::StateSample;

use crate::UsageError;
use crate::process::RoleArgs;

/// The roles, in start order (the monitor first, so it sees tick 0).
pub const ROLES: [&str; 4] = ["monitor", "reference", "controller", "plant"];

/// `rotorloop run` arguments.
#[derive(Debug, Clone, Args)]
pub struct RunArgs {
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
    /// Real time: the plant sleeps until this many µs before each grid time and spins
    /// the rest (sharper ticks, one core busier).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
    pub spin_before_tick_us: u64,
    /// Real time: ticks the plant holds the last torque before safe mode.
    #[arg(long, allow_negative_numbers = true, default_value_t = 50)]
    pub hold_ticks: u64,
    /// Inject a fault: `ROLE:kill@T[:restart@T2]` (seconds since the plant published tick
    /// 0, so a slow start never moves a fault before the run; ROLE is plant, reference,
    /// controller or monitor). Repeatable.
    #[arg(long)]
    pub fault: Vec<String>,
    /// Inject a corrupted sample: `ROLE:KIND@TICK` makes ROLE (plant, reference or
    /// controller) publish tick TICK with a NaN (`nan`), an infinity (`inf`), an absurd
    /// 1e12 (`huge`) or, for plant and reference, a non-rotation attitude (`skew`).
    /// The receivers must reject it. Repeatable.
    #[arg(long)]
    pub corrupt: Vec<String>,
}

/// Parses `--corrupt ROLE:KIND@TICK`.
pub fn parse_corrupt(s: &str) -> Result<(String, crate::process::Corrupt), UsageError> {
    use crate::process::{Corrupt, CorruptKind};
    let bad = |why: &str| {
        UsageError(format!(
            "--corrupt `{s}` is not allowed: {why} (form ROLE:KIND@TICK, e.g. controller:nan@500)"
        ))
    };
    let (role, rest) = s.split_once(':').ok_or_else(|| bad("no ROLE:"))?;
    if !["plant", "reference", "controller"].contains(&role) {
        return Err(bad("ROLE is plant, reference or controller"));
    }
    let c: Corrupt = rest.parse().map_err(|e: String| bad(&e))?;
    if role == "controller" && c.kind == CorruptKind::Skew {
        return Err(bad("`skew` needs an attitude: plant or reference"));
    }
    Ok((role.to_owned(), c))
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

/// One `--fault`.
#[derive(Debug, Clone, PartialEq)]
pub struct Fault {
    /// The role to kill.
    pub role: String,
    /// When to SIGKILL it (s after the start).
    pub kill_s: f64,
    /// When to start it again (s), if at all.
    pub restart_s: Option<f64>,
    killed: bool,
    restarted: bool,
}

/// A fault as it happened (monotonic ns).
#[derive(Debug, Clone, PartialEq)]
pub struct FaultEvent {
    /// The role killed.
    pub role: String,
    /// When it was killed.
    pub kill_ns: u64,
    /// When it was started again.
    pub restart_ns: Option<u64>,
}

/// Parses `ROLE:kill@T[:restart@T2]`.
pub fn parse_fault(s: &str) -> Result<Fault, UsageError> {
    let bad = |why: &str| {
        UsageError(format!(
            "--fault `{s}` is not allowed: {why} (form ROLE:kill@T[:restart@T2], e.g. controller:kill@2:restart@2.5)"
        ))
    };
    let parts: Vec<&str> = s.split(':').collect();
    if parts.len() < 2 || parts.len() > 3 {
        return Err(bad("two or three parts"));
    }
    if !ROLES.contains(&parts[0]) {
        return Err(bad("ROLE is plant, reference, controller or monitor"));
    }
    let time = |p: &str, key: &str| -> Result<f64, UsageError> {
        p.strip_prefix(key)
            .and_then(|t| t.parse::<f64>().ok())
            .filter(|t| t.is_finite() && *t >= 0.0)
            .ok_or_else(|| bad(&format!("`{p}` must be {key}SECONDS with SECONDS ≥ 0")))
    };
    let kill_s = time(parts[1], "kill@")?;
    let restart_s = parts.get(2).map(|p| time(p, "restart@")).transpose()?;
    if restart_s.is_some_and(|r| r <= kill_s) {
        return Err(bad("the restart must come after the kill"));
    }
    Ok(Fault { role: parts[0].to_owned(), kill_s, restart_s, killed: false, restarted: false })
}

/// Parses `--pin`: `role=core` pairs separated by commas.
pub fn parse_pins(s: &str) -> Result<BTreeMap<String, usize>, UsageError> {
    let mut pins = BTreeMap::new();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    for part in s.split(',').filter(|p| !p.is_empty()) {
        let (role, core) = part.split_once('=').ok_or_else(|| {
            UsageError(format!("--pin `{part}` is not allowed: role=core, e.g. plant=0"))
        })?;
        if !ROLES.contains(&role) {
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

struct Children(Vec<(String, Child)>);

impl Drop for Children {
    fn drop(&mut self) {
        for (_, c) in &mut self.0 {
            if let Ok(None) = c.try_wait() {
                let _ = c.kill();
                let _ = c.wait();
            }
        }
    }
}

fn signal(child: &Child, sig: libc::c_int) {
    // SAFETY: sends a signal to our own child's pid.
    unsafe { libc::kill(child.id() as libc::pid_t, sig) };
}

/// Runs the four processes to the end of the scenario.
pub fn run(args: &RunArgs) -> anyhow::Result<()> {
    let scenario = args.role.scenario()?;
    for w in &scenario.warnings {
        eprintln!("warning: {w}");
    }
    let faults = args.fault.iter().map(|f| parse_fault(f)).collect::<Result<Vec<_>, _>>()?;
    let corrupt = args.corrupt.iter().map(|c| parse_corrupt(c)).collect::<Result<Vec<_>, _>>()?;
    let mut role_args = args.role.clone();
    role_args.domain.get_or_insert_with(|| format!("run-{}", std::process::id()));
    let domain = role_args.open_domain()?;
    let pins = match &args.pin {
        Some(p) => parse_pins(p)?,
        None => BTreeMap::new(),
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let exe = std::env::current_exe().context("cannot find the rotorloop executable")?;
    install_signal_handlers();
    // Nothing of this domain may be alive: clear what an earlier, killed run left
    // (including resume slots, which would otherwise be taken for a restart).
    let (_, alive) = domain.cleanup()?;
    if alive > 0 {
        return Err(UsageError(format!(
            "domain `{}` is in use by {alive} running process(es); choose another --domain",
            domain.name()
        ))
        .into());
    }

    let command = |role: &str| {
        let mut r = role_args.clone();
        r.core = pins.get(role).copied();
        let mut cmd = Command::new(&exe);
        cmd.arg("role").arg(role).args(r.to_args()).stdin(Stdio::null());
        stop_with_parent(&mut cmd);
        for (_, c) in corrupt.iter().filter(|(r, _)| r == role) {
            cmd.arg("--corrupt").arg(c.to_string());
        }
        if args.quiet {
            cmd.stdout(Stdio::null());
        }
        match role {
            "monitor" => {
                cmd.arg("--out").arg(&args.out);
                if !args.quiet {
                    cmd.arg("--status");
                }
            }
            "plant" => {
                cmd.arg("--subscribers").arg(if args.no_monitor { "2" } else { "3" });
                cmd.arg("--spin-before-tick-us").arg(args.spin_before_tick_us.to_string());
                cmd.arg("--hold-ticks").arg(args.hold_ticks.to_string());
                cmd.arg("--latency-out").arg(&args.out);
            }
            _ => {}
        }
        cmd
    };
    let mut children = Children(Vec::new());
    let mut rss: BTreeMap<String, RssTrack> = BTreeMap::new();
    for role in ROLES {
        if role == "monitor" && args.no_monitor {
            continue;
        }
        let child = command(role).spawn().with_context(|| format!("cannot start {role}"))?;
        rss.insert(role.to_owned(), RssTrack::new(child.id()));
        children.0.push((role.to_owned(), child));
    }
    let t0 = now_ns();
    // The fault clock starts when the plant has published tick 0 (its resume slot is
    // written just before each publish).
    let plant_slot =
        ResumeSlot::<StateSample>::open(&domain, "plant").context("the plant's resume slot")?;
    let mut run_t0: Option<u64> = None;
    let mut rss_csv = std::io::BufWriter::new(
        std::fs::File::create(args.out.join("rss.csv"))
            .with_context(|| format!("cannot write {}", args.out.join("rss.csv").display()))?,
    );
    {
        use std::io::Write;
        writeln!(rss_csv, "t_s,role,pid,rss_kib,anon_kib,file_kib,shmem_kib")?;
    }
    let mut next_rss_ns = t0;
    let mut events: Vec<FaultEvent> = Vec::new();
    let mut pending = faults.clone();

    // Wait for all to finish; on a signal, forward SIGTERM, then SIGKILL after 10 s.
    let mut term_sent_at: Option<u64> = None;
    let mut failures = Vec::new();
    loop {
        // Fault injection: SIGKILL at `kill`, the same command again at `restart`.
        if run_t0.is_none() && plant_slot.load().is_some() {
            run_t0 = Some(now_ns());
        }
        let elapsed = run_t0.map_or(f64::NEG_INFINITY, |r| (now_ns() - r) as f64 / 1e9);
        for f in pending.iter_mut() {
            if !f.killed && elapsed >= f.kill_s && term_sent_at.is_none() {
                if let Some((_, c)) = children.0.iter_mut().find(|(r, _)| *r == f.role) {
                    signal(c, libc::SIGKILL);
                    let _ = c.wait(); // reap: an unreaped zombie can delay dead-node detection
                    events.push(FaultEvent {
                        role: f.role.clone(),
                        kill_ns: now_ns(),
                        restart_ns: None,
                    });
                    eprintln!("launcher: killed {} (SIGKILL) at {elapsed:.3} s", f.role);
                }
                f.killed = true;
            }
            if f.killed
                && !f.restarted
                && f.restart_s.is_some_and(|r| elapsed >= r)
                && term_sent_at.is_none()
            {
                let child = command(&f.role)
                    .spawn()
                    .with_context(|| format!("cannot restart {}", f.role))?;
                rss.insert(f.role.clone(), RssTrack::new(child.id()));
                if let Some(entry) = children.0.iter_mut().find(|(r, _)| *r == f.role) {
                    entry.1 = child;
                }
                if let Some(e) = events.iter_mut().rev().find(|e| e.role == f.role) {
                    e.restart_ns = Some(now_ns());
                }
                eprintln!("launcher: restarted {} at {elapsed:.3} s", f.role);
                f.restarted = true;
            }
        }
        if now_ns() >= next_rss_ns {
            use std::io::Write;
            next_rss_ns += 1_000_000_000;
            let t = (now_ns() - t0) as f64 / 1e9;
            for (role, track) in rss.iter_mut() {
                if let Some((kib, [anon, file, shmem])) = track.sample() {
                    writeln!(rss_csv, "{t:.1},{role},{},{kib},{anon},{file},{shmem}", track.pid)?;
                }
            }
            rss_csv.flush()?;
        }
        let waiting_restart =
            pending.iter().any(|f| f.killed && !f.restarted && f.restart_s.is_some());
        let mut running = 0;
        for (role, c) in &mut children.0 {
            match c.try_wait() {
                Ok(None) => running += 1,
                Ok(Some(st)) if !st.success() && term_sent_at.is_none() => {
                    // A child we killed on purpose is not a failure.
                    if st.signal() == Some(libc::SIGKILL) && events.iter().any(|e| e.role == *role)
                    {
                        continue;
                    }
                    let msg = format!("{role} exited with {st}");
                    if !failures.contains(&msg) {
                        failures.push(msg);
                    }
                }
                _ => {}
            }
        }
        if running == 0 && !waiting_restart {
            break;
        }
        if (shutdown_requested() || !failures.is_empty()) && term_sent_at.is_none() {
            term_sent_at = Some(now_ns());
            for (_, c) in &children.0 {
                signal(c, libc::SIGTERM);
            }
        }
        if term_sent_at.is_some_and(|t| now_ns() - t > 10_000_000_000) {
            for (_, c) in &mut children.0 {
                let _ = c.kill();
            }
        }
        if term_sent_at.is_some() && running == 0 {
            break;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    drop(children);
    // Everything of this domain is gone now: remove what iceoryx2 keeps after its nodes.
    if let Err(e) = domain.cleanup() {
        eprintln!("warning: cleaning up domain {}: {e}", domain.name());
    }
    if let Some(f) = failures.first() {
        anyhow::bail!("{f}; the run was stopped ({} failed)", failures.join(", "));
    }
    if !args.no_monitor {
        add_resources(&args.out, &rss).context("resource report")?;
    }
    if !args.quiet {
        for (role, r) in &rss {
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
        crate::faults::report(&args.out, &role_args.scenario()?, &events)
            .context("fault report")?;
    }
    if shutdown_requested() {
        eprintln!("stopped by signal; partial report in {}", args.out.display());
    } else if !args.no_monitor && !args.quiet {
        println!("report: {}", args.out.display());
    }
    Ok(())
}

/// Adds the per-role memory figures to `out/summary.json` as `resources`.
fn add_resources(out: &std::path::Path, rss: &BTreeMap<String, RssTrack>) -> anyhow::Result<()> {
    let path = out.join("summary.json");
    let Ok(text) = std::fs::read_to_string(&path) else {
        return Ok(()); // no summary (the monitor was stopped early): nothing to add to
    };
    let mut j: serde_json::Value = serde_json::from_str(&text)?;
    j["resources"] = serde_json::json!({ "rss": rss, "rss_csv": "rss.csv" });
    crate::sim::write_json(&path, &j)?;
    Ok(())
}
