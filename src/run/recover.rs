//! `rotorloop recover RUN_DIR`: the report of a run whose launcher did not end normally
//! (`kill -9` of `rotorloop run`, a machine's OOM killer), assembled as the launcher would
//! have.
//!
//! When the launcher dies its roles get SIGTERM from the kernel (their parent-death
//! signal) and end, and the monitor writes a partial report of what it had seen. The
//! complete record of the run is the roles' flight records, which nobody moved out of
//! their staging directory on tmpfs. The launcher writes `RUN_DIR/launch.json` before it
//! starts anything (the domain, the hosts, the roles' arguments, the scenario as run, the
//! staging directory), and the staging directory names its run directory, so that:
//!
//! - `rotorloop clean --domain D` says which run directory the kept records belong to;
//! - `rotorloop recover RUN_DIR` refuses a run that still has live processes, moves the
//!   records into `RUN_DIR/flight`, clears what the dead processes left in shared memory,
//!   and writes the report from the records (`trace.csv`, `timing.csv`, histograms,
//!   figures, `summary.json` with `recovered`). `sim --replay RUN_DIR` then works on it.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Parser;
use rotorloop_common::flight::{RUN_DIR_FILE, Stream};
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::role::args::RoleArgs;
use rotorloop_common::scenario::Scenario;
use rotorloop_common::scenario::ScenarioFile;
use rotorloop_monitor::hosts::Hosts;
use serde::{Deserialize, Serialize};

use rotorloop_common::role::UsageError;

/// The file of a run directory that says how the run was launched.
pub const LAUNCH_FILE: &str = "launch.json";

/// How a run was launched: what [`run`] needs to assemble its report without the launcher.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LaunchRecord {
    /// The run's domain.
    pub domain: String,
    /// The hosts of a split run (`role=host,…`, the monitor's `--hosts`), else `None`.
    pub hosts: Option<String>,
    /// The arguments every role got (`RoleArgs::to_args`).
    pub role_args: Vec<String>,
    /// The scenario as run (read under a scenario file's rule for sizes and sections).
    #[serde(deserialize_with = "ScenarioFile::checked")]
    pub scenario: ScenarioFile,
    /// Where the roles recorded during the run (`None`: no flight records).
    pub staging: Option<PathBuf>,
    /// Whether the launcher moves the records into `RUN_DIR/flight` at the end (its own
    /// staging directory), or leaves them where the user's `--record` put them.
    pub moved: bool,
    /// Whether the report writes `trace.csv` and `timing.csv` (not with `--no-csv`).
    #[serde(default = "yes")]
    pub csv: bool,
    /// The launcher's pid.
    pub launcher_pid: u32,
}

fn yes() -> bool {
    true
}

impl LaunchRecord {
    /// Writes `out/launch.json`, and the run directory's name into the staging directory.
    pub fn write(&self, out: &Path) -> anyhow::Result<()> {
        rotorloop_common::output::write_json(&out.join(LAUNCH_FILE), self)?;
        // Durable before anything runs: after a machine crash it is what `recover` starts
        // from (seen: a crash 2 s into a run left it empty, ext4's delayed allocation).
        let durable = std::fs::File::open(out.join(LAUNCH_FILE))
            .and_then(|f| f.sync_all())
            .and_then(|()| std::fs::File::open(out)?.sync_all());
        durable
            .with_context(|| format!("cannot make {} durable", out.join(LAUNCH_FILE).display()))?;
        if let Some(staging) = &self.staging {
            let out = std::fs::canonicalize(out).unwrap_or_else(|_| out.to_path_buf());
            crate::run::spawn::make_staging(staging)?;
            // An earlier run's name is replaced (removing a link removes the link only);
            // the new one is made exclusively, never written through a link.
            let file = staging.join(RUN_DIR_FILE);
            match std::fs::remove_file(&file) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                    return Err(e).with_context(|| format!("cannot replace {}", file.display()));
                }
                _ => {}
            }
            rotorloop_common::private::write_new(&file, out.as_os_str().as_encoded_bytes())?;
        }
        Ok(())
    }

    /// Reads `dir/launch.json`.
    pub fn read(dir: &Path) -> anyhow::Result<Self> {
        let path = dir.join(LAUNCH_FILE);
        // Read as any input: a FIFO in its place is refused, not waited on.
        let text = rotorloop_common::input::read_text(&path, 64 << 20).map_err(|e| {
            UsageError(format!(
                "{}: {e}: not the directory of a `rotorloop run` (its --out)",
                path.display()
            ))
        })?;
        serde_json::from_str(&text)
            .map_err(|e| UsageError(format!("{}: {e}", path.display())).into())
    }

    /// The roles' arguments, parsed back.
    fn role_args(&self) -> anyhow::Result<RoleArgs> {
        #[derive(Parser)]
        struct Wrap {
            #[command(flatten)]
            role: RoleArgs,
        }
        let argv = std::iter::once("role".to_owned()).chain(self.role_args.iter().cloned());
        let w = Wrap::try_parse_from(argv)
            .map_err(|e| UsageError(format!("{LAUNCH_FILE}: role_args: {e}")))?;
        Ok(w.role)
    }
}

/// The run directory whose records a staging directory holds, if it says.
pub fn run_dir_of(staging: &Path) -> Option<PathBuf> {
    std::fs::read_to_string(staging.join(RUN_DIR_FILE)).ok().map(PathBuf::from)
}

/// `rotorloop recover RUN_DIR` (module docs).
pub fn run(dir: &Path) -> anyhow::Result<()> {
    let launch = LaunchRecord::read(dir)?;
    let role = launch.role_args()?;
    let scenario = Scenario::from_file(launch.scenario.clone())
        .map_err(|e| UsageError(format!("{LAUNCH_FILE}: scenario: {e}")))?;
    let hosts = match &launch.hosts {
        Some(h) => Hosts::parse(h).map_err(|e| UsageError(format!("{LAUNCH_FILE}: hosts: {e}")))?,
        None => Hosts::default(),
    };
    let host_names: Vec<Option<String>> = match &launch.hosts {
        Some(h) => {
            let mut names: Vec<String> =
                h.split(',').filter_map(|p| p.split_once('=')).map(|(_, h)| h.to_owned()).collect();
            names.sort();
            names.dedup();
            names.into_iter().map(Some).collect()
        }
        None => vec![role.host.clone()],
    };
    for host in &host_names {
        let domain = Domain::on_host(&launch.domain, host.as_deref())
            .map_err(|e| UsageError(e.to_string()))?;
        let (cleaned, alive) = domain.cleanup()?;
        if alive > 0 {
            return Err(UsageError(format!(
                "the run in {} is still going ({alive} live process(es) in domain `{}`): \
                 recover it once it has ended",
                dir.display(),
                domain.name()
            ))
            .into());
        }
        if cleaned > 0 {
            eprintln!("recover: removed {cleaned} dead node(s) of domain {}", domain.name());
        }
    }
    let mut kept = dir.join("flight");
    // A machine that went down takes tmpfs with it: the staging directory is gone, and the
    // record is what reached `RUN_DIR/flight` (the segments and the journal of the newest
    // ticks, made durable every `flight::JOURNAL_PERIOD`).
    let machine_crash = launch.moved
        && launch.staging.as_ref().is_some_and(|s| !s.is_dir())
        && Stream::ALL.iter().all(|s| !s.path(&kept).exists());
    match &launch.staging {
        Some(staged) if !launch.moved => kept = staged.clone(),
        Some(staged) if staged.is_dir() && *staged != kept => {
            let n =
                rotorloop_common::flight::move_records(staged, &kept, true).with_context(|| {
                    format!(
                        "cannot move the records of {} into {}",
                        staged.display(),
                        kept.display()
                    )
                })?;
            eprintln!(
                "recover: moved {n} record file(s) from {} into {}",
                staged.display(),
                kept.display()
            );
        }
        Some(_) => {}
        None => anyhow::bail!(UsageError(format!(
            "{}: the run had no flight records (--no-record): nothing to recover from",
            dir.display()
        ))),
    }
    // Whatever of the records is sound is read (a missing or damaged file is skipped and
    // named); refused only where nothing is.
    let records = rotorloop_monitor::assemble::FlightRecords::read(&kept, scenario.ticks())
        .map_err(|e| {
            UsageError(format!(
                "{}: nothing of the flight records can be read ({e}): nothing to recover",
                kept.display()
            ))
        })?;
    let how = (&scenario, &role, launch.csv);
    let summary = rotorloop_monitor::assemble::report(dir, &kept, &records, how, &hosts, None);
    let fallback = rotorloop_monitor::recording::fallback_dir(role.domain());
    rotorloop_monitor::report::write_summary(dir, &fallback, &summary)?;
    rotorloop_monitor::summary::patch(dir, |j| {
        let why = if machine_crash {
            "the machine went down during the run (its staging directory on tmpfs is gone): \
             the report is of the record that reached the disk; no fault report, no memory \
             figures"
        } else {
            "the launcher did not end normally: no fault report, no memory figures"
        };
        j["recovered"] = serde_json::json!({
            "by": "rotorloop recover",
            "launcher_pid": launch.launcher_pid,
            "why": why,
            "machine_crash": machine_crash,
        });
    })?;
    crate::pipeline::finish(
        dir,
        crate::pipeline::Steps { incidents: true, mcap: true, quiet: false },
    );
    println!("{}", rotorloop_monitor::report::console_summary(&summary));
    println!(
        "recovered: {} rows from the flight records into {}{}",
        summary.trace_rows,
        dir.display(),
        if summary.completed { "" } else { " (the loop did not reach its last tick)" }
    );
    Ok(())
}
