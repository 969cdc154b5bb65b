//! `rotorloop run`: starts the four processes from this very executable (so they are
//! always the same build), pins them, shows the monitor's live status line, stops them
//! cleanly at the end or on Ctrl-C/SIGTERM, and leaves the report in `--out`.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use anyhow::Context;
use clap::Args;
use rotorloop_common::ipc::{install_signal_handlers, now_ns, shutdown_requested};

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
    #[arg(long, default_value_t = 0)]
    pub spin_before_tick_us: u64,
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

    let mut children = Children(Vec::new());
    for role in ROLES {
        if role == "monitor" && args.no_monitor {
            continue;
        }
        let mut r = role_args.clone();
        r.core = pins.get(role).copied();
        let mut cmd = Command::new(&exe);
        cmd.arg("role").arg(role).args(r.to_args()).stdin(Stdio::null());
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
                cmd.arg("--latency-out").arg(&args.out);
            }
            _ => {}
        }
        let child = cmd.spawn().with_context(|| format!("cannot start {role}"))?;
        children.0.push((role.to_owned(), child));
    }

    // Wait for all to finish; on a signal, forward SIGTERM, then SIGKILL after 10 s.
    let mut term_sent_at: Option<u64> = None;
    let mut failures = Vec::new();
    loop {
        let mut running = 0;
        for (role, c) in &mut children.0 {
            match c.try_wait() {
                Ok(None) => running += 1,
                Ok(Some(st)) if !st.success() && term_sent_at.is_none() => {
                    let msg = format!("{role} exited with {st}");
                    if !failures.contains(&msg) {
                        failures.push(msg);
                    }
                }
                _ => {}
            }
        }
        if running == 0 {
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
        std::thread::sleep(Duration::from_millis(5));
    }
    drop(children);
    // Everything of this domain is gone now: remove what iceoryx2 keeps after its nodes.
    if let Err(e) = domain.cleanup() {
        eprintln!("warning: cleaning up domain {}: {e}", domain.name());
    }
    if let Some(f) = failures.first() {
        anyhow::bail!("{f}; the run was stopped ({} failed)", failures.join(", "));
    }
    if shutdown_requested() {
        eprintln!("stopped by signal; partial report in {}", args.out.display());
    } else if !args.no_monitor && !args.quiet {
        println!("report: {}", args.out.display());
    }
    Ok(())
}
