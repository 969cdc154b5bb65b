//! The `monitor` process: a thin shell over [`RowJoiner`] (the rules, in
//! [`crate::policy`]) and [`Recording`] (the files). It is passive: it has no event
//! listener (publishers never wait for it or wake it), it polls its large ring buffers
//! every `--poll-us`, and if it falls behind the oldest samples are overwritten: it
//! counts the ticks lost and says so in the report.

mod args;

use std::io::IsTerminal;

use anyhow::Context;
use rotorloop_common::ipc::{MAX_BUFFER, Topic, now_ns, shutdown_requested};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::role::{PlantEnd, write_json};
use rotorloop_common::wire::{ReferenceSample, StateSample, TorqueSample};

pub use args::MonitorArgs;

use crate::policy::{END_QUIET_NS, MonitorResume, RowJoiner};
use crate::recording::{Recording, with_fallback};
use crate::report::{console_summary, summary};

/// Runs the monitor until it has the last row, or a termination signal.
pub fn run(args: &MonitorArgs) -> anyhow::Result<()> {
    let (role, scenario) = (&args.role, args.role.scenario()?);
    role.setup("monitor");
    let domain = role.open_domain()?;
    let node = domain.node("monitor").context("monitor")?;
    // Subscribe to the state last: the plant starts when it sees its state subscribers,
    // so everything else must already be connected by then.
    let refs = domain.inbox::<ReferenceSample>(&node, Topic::Reference, MAX_BUFFER, false)?;
    let torques = domain.inbox::<TorqueSample>(&node, Topic::Torque, MAX_BUFFER, false)?;
    let states = domain.inbox::<StateSample>(&node, Topic::State, MAX_BUFFER, false)?;
    let slot = ResumeSlot::<MonitorResume>::open(&domain, "monitor").context("monitor")?;
    let plant_end = PlantEnd::open(&domain).context("monitor")?;
    // iceoryx2's own CLI finds the domain from here: `cd OUT && iox2 service list`.
    let _ = domain.write_iox2_config(&args.out);
    // A restart continues the report in the same directory.
    let (mut rec, resumed) = Recording::open(&args.out, &scenario, slot.load(), now_ns());
    let limit = TorqueSample::absurd_limit(scenario.limits_for(scenario.actuation()).rotor_torque);
    let mut joiner = RowJoiner::new(scenario.ticks(), limit, now_ns());
    if let Some(r) = &resumed {
        joiner.resume(r);
        eprintln!("monitor: restarted; continuing the report from tick {}", r.next_row);
    }
    let status = args.status && std::io::stderr().is_terminal();
    loop {
        states.drain(|s| joiner.take_state(s))?;
        refs.drain(|r| joiner.take_reference(r))?;
        torques.drain(|t| joiner.take_torque(t))?;
        // The plant has ended (seen here, or in its resume slot by a monitor restarted
        // after the end) and nothing has arrived for a while: what is missing now never
        // comes (a role killed at the very end, say), so settle the rest.
        let quiet = joiner.quiet_ns(now_ns()) > END_QUIET_NS;
        let drained = quiet && (joiner.plant_ended() || plant_end.ended());
        let stopping = shutdown_requested() || drained;
        while let Some(row) = joiner.next_row(stopping) {
            rec.write(&row);
        }
        if drained {
            joiner.settle_rest();
        }
        if let Some(r) = rec.flush(&joiner) {
            slot.store(&r);
        }
        if status {
            rec.status_line(joiner.last_state(), now_ns());
        }
        if joiner.done() || stopping {
            break;
        }
        std::thread::sleep(std::time::Duration::from_micros(args.poll_us));
    }
    let fallback = std::env::temp_dir().join(format!("rotorloop-report-{}", domain.name()));
    let (files, dir) = rec.finish(&scenario.file.name, &fallback);
    if joiner.done() {
        slot.clear(); // finished: a later monitor in this domain starts a new report
    }
    let mut summary = summary(&scenario, role, &joiner, &rec, files);
    summary.report_dir = (dir != args.out).then(|| dir.display().to_string());
    println!("{}", console_summary(&summary));
    let write = |d: &std::path::Path| write_json(&d.join("summary.json"), &summary);
    match with_fallback(&args.out, &fallback, write) {
        Ok(((), d)) if d != args.out => {
            eprintln!("monitor: summary.json written to {}", d.display())
        }
        Ok(_) => {}
        Err(e) => {
            // Nowhere to write: the summary goes to stderr, so it is not lost.
            eprintln!("monitor: summary.json not written ({e:#}); here it is:");
            eprintln!("{}", serde_json::to_string_pretty(&summary)?);
        }
    }
    Ok(())
}
