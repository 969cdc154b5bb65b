//! `rotorloop role probe`: tries to reach a run from the outside and prints, line by
//! line, what it got: a node in the run's domain, a subscription to the state (and a
//! sample from it), a torque publisher, and plain `open(2)` of every shared-memory and
//! static file of the domain, for reading and for writing. Each line says `granted` or
//! `refused` and why. Used to check who may touch a run (the security test runs it as
//! a second OS user, and as the owner for comparison); always exits 0.

use std::time::Duration;

use clap::Args;
use rotorloop_common::clock::now_ns;
use rotorloop_common::graph::Topic;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::wire::{StateSample, TorqueSample};

/// `probe` arguments.
#[derive(Debug, Clone, Args)]
pub struct ProbeArgs {
    /// The run domain to probe.
    #[arg(long)]
    pub domain: String,
}

fn line(what: &str, result: Result<String, String>) {
    use std::io::Write;
    let text = match result {
        Ok(how) => format!("{what}: granted ({how})"),
        Err(why) => format!("{what}: refused ({why})"),
    };
    let _ = writeln!(std::io::stdout(), "{text}"); // a closed pipe is not an error here
}

/// Probes the domain; see the module documentation.
pub fn run(args: &ProbeArgs) -> anyhow::Result<()> {
    let domain = Domain::new(&args.domain)?;
    match domain.node("probe") {
        Err(e) => {
            let why = format!("{e}");
            line("node", Err(why.clone()));
            line("subscribe state", Err("no node".into()));
            line("publish torque", Err("no node".into()));
        }
        Ok(node) => {
            line("node", Ok("created".into()));
            match domain.inbox::<StateSample>(&node, Topic::State, 8, false) {
                Err(e) => line("subscribe state", Err(e.to_string())),
                Ok(inbox) => {
                    let until = now_ns() + 1_000_000_000;
                    let mut got = None;
                    while got.is_none() && now_ns() < until {
                        got = inbox.take().ok().flatten();
                        std::thread::sleep(Duration::from_millis(5));
                    }
                    line(
                        "subscribe state",
                        Ok(got.map_or("no sample within 1 s".into(), |s| {
                            format!("received tick {}", s.tick)
                        })),
                    );
                }
            }
            line(
                "publish torque",
                domain
                    .outbox::<TorqueSample>(&node, Topic::Torque)
                    .map(|_| "publisher created".into())
                    .map_err(|e| e.to_string()),
            );
        }
    }
    let prefix = Domain::prefix_of(&args.domain);
    let mut files: Vec<std::path::PathBuf> = std::fs::read_dir("/dev/shm")
        .map(|d| {
            d.flatten()
                .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
                .map(|e| e.path())
                .collect()
        })
        .unwrap_or_default();
    files.sort();
    let root = std::path::PathBuf::from(domain.root_path());
    line(
        &format!("list {}", root.display()),
        std::fs::read_dir(&root).map(|_| "listed".into()).map_err(|e| e.to_string()),
    );
    for f in files {
        for (mode, write) in [("read", false), ("write", true)] {
            let r = std::fs::OpenOptions::new().read(!write).write(write).open(&f);
            line(
                &format!("open {} for {mode}", f.display()),
                r.map(|_| "opened".into()).map_err(|e| e.to_string()),
            );
        }
    }
    Ok(())
}
