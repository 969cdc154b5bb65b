//! The `monitor` process: a thin shell over [`RowJoiner`] (the rules, in
//! [`crate::policy`]) and [`Recording`] (the files). It is passive: it has no event
//! listener (publishers never wait for it or wake it), it polls its large ring buffers
//! every `--poll-us`, and if it falls behind the oldest samples are overwritten: it
//! counts the ticks lost and says so in the report.

mod args;
mod ports;

use std::io::IsTerminal;

use rotorloop_common::ipc::{now_ns, shutdown_requested};
use rotorloop_common::wire::TorqueSample;

pub use args::MonitorArgs;

use crate::assemble::{FlightRecords, LiveView, report, unusable};
use crate::policy::{END_QUIET_NS, RowJoiner};
use crate::recording::Recording;
use crate::report::{console_summary, summary, write_summary};
use ports::Ports;

/// Runs the monitor until it has the last row, or a termination signal.
pub fn run(args: &MonitorArgs) -> anyhow::Result<()> {
    let (role, scenario) = (&args.role, args.role.scenario()?);
    role.setup("monitor");
    let ports = Ports::open(role, &args.out)?;
    // A restart continues the report in the same directory.
    let (mut rec, resumed) = Recording::open(&args.out, &scenario, ports.slot.load(), now_ns());
    rec.hosts = args.hosts.clone().unwrap_or_default();
    let limit = TorqueSample::absurd_limit(scenario.limits_for(scenario.actuation()).rotor_torque);
    let mut joiner = RowJoiner::new(scenario.ticks(), limit, now_ns());
    if let Some(r) = &resumed {
        joiner.resume(r);
        eprintln!("monitor: restarted; continuing the report from tick {}", r.next_row);
    }
    let status = args.status && std::io::stderr().is_terminal();
    // Started after the plant's last tick (a restart after the end): what is still in
    // the buffers is all there is; no need to wait for a quiet period.
    let ended_before = ports.plant_end.ended();
    loop {
        ports.drain(&mut joiner)?;
        // The plant has ended (seen here, or in its resume slot by a monitor restarted
        // after the end) and nothing has arrived for a while: what is missing now never
        // comes (a role killed at the very end, say), so settle the rest.
        let quiet = ended_before || joiner.quiet_ns(now_ns()) > END_QUIET_NS;
        let drained = quiet && (joiner.plant_ended() || ports.plant_end.ended());
        let stopping = shutdown_requested() || drained;
        while let Some(row) = joiner.next_row(stopping) {
            rec.write(&row);
        }
        if drained {
            joiner.settle_rest();
        }
        if let Some(r) = rec.flush(&joiner) {
            ports.slot.store(&r);
        }
        if status {
            rec.status_line(joiner.last_state(), now_ns());
        }
        if joiner.done() || stopping {
            break;
        }
        std::thread::sleep(std::time::Duration::from_micros(args.poll_us));
    }
    if joiner.done() {
        ports.slot.clear(); // finished: a later monitor in this domain starts a new report
    }
    if let Some(dir) = args.role.record.as_deref() {
        wait_for_records(dir, &joiner);
    }
    let records = args.role.record.as_deref().map(|d| (d, FlightRecords::read(d)));
    let summary = match records {
        // The run's files from the roles' own records: complete whatever was killed.
        Some((dir, Ok(records))) => {
            let hosts = rec.hosts.clone();
            drop(rec); // its buffered rows go to disk before the files are rewritten
            let live = Some(LiveView { joiner: &joiner });
            report(&args.out, dir, &records, &scenario, role, &hosts, live).0
        }
        _ => {
            let fallback = std::env::temp_dir().join(format!("rotorloop-report-{}", ports.domain));
            let (files, dir) = rec.finish(&scenario.file.name, &fallback);
            let mut summary = summary(&scenario, role, &joiner, &rec, files);
            summary.report_dir = (dir != args.out).then(|| dir.display().to_string());
            if let Some((dir, Err(e))) = &records {
                eprintln!("monitor: the report is the live view only: {e}");
                summary.flight = Some(unusable(dir, e));
            }
            summary
        }
    };
    println!("{}", console_summary(&summary));
    let fallback = std::env::temp_dir().join(format!("rotorloop-report-{}", ports.domain));
    write_summary(&args.out, &fallback, &summary)
}

/// Waits (at most 2 s) until the roles' records hold the newest state and torque this
/// monitor saw: a role records a sample just after publishing it, and a writer preempted
/// between the two would otherwise miss the report by microseconds. A writer killed in
/// between never writes it; the bound covers that.
fn wait_for_records(dir: &std::path::Path, joiner: &RowJoiner) {
    use rotorloop_common::flight::{Stream, has_record};
    use rotorloop_common::wire::StateSample;
    let until = now_ns() + 2_000_000_000;
    let state = joiner.last_state().map(|s| s.tick);
    let torque = joiner.last_torque().map(|t| t.tick);
    while now_ns() < until
        && !(state.is_none_or(|k| has_record::<StateSample>(dir, Stream::PlantState, k))
            && torque.is_none_or(|k| {
                has_record::<TorqueSample>(dir, Stream::ControllerTorque, k)
                    || has_record::<TorqueSample>(dir, Stream::PlantTorque, k)
            }))
    {
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
}
