//! The `monitor` process: a thin shell over [`RowJoiner`] (the rules, in
//! [`crate::policy`]) and [`Recording`] (the files). It is passive: it has no event
//! listener (publishers never wait for it or wake it), it polls its large ring buffers
//! every `--poll-us`, and if it falls behind the oldest samples are overwritten: it
//! counts the ticks lost and says so in the report.

pub mod args;
mod ports;

use rotorloop_common::clock::now_ns;
use rotorloop_common::signals::shutdown_requested;

use crate::ROLE;
use crate::assemble::final_report;
use crate::policy::{END_QUIET_AFTER_END_NS, END_QUIET_NS, RowJoiner};
use crate::recording::{Recording, fallback_dir};
use crate::report::{console_summary, write_summary};
use ports::Ports;

/// Runs the monitor until it has the last row, or a termination signal.
pub fn run(args: &args::MonitorArgs) -> anyhow::Result<()> {
    let (role, scenario) = (&args.role, args.role.scenario()?);
    args.check()?;
    role.setup(ROLE);
    let ports = Ports::open(role, &args.out)?;
    // A restart continues the report in the same directory.
    let stall = role.hooks.test_files_stall_ms.map(std::time::Duration::from_millis);
    let resumed = ports.slot.load_for(ROLE, scenario.ticks());
    let (mut rec, resumed) =
        Recording::open(&args.out, &scenario, resumed, (now_ns(), stall), !args.no_csv);
    rec.hosts = args.hosts.clone().unwrap_or_default();
    let mut joiner = RowJoiner::for_scenario(&scenario, now_ns());
    if let Some(r) = &resumed {
        joiner.resume(r);
        eprintln!("monitor: restarted; continuing the report from tick {}", r.next_row);
    }
    rec.begin(&joiner);
    // As asked: its launcher asks only where its own output is a terminal (the monitor's
    // stderr is then the launcher's relay, a pipe).
    let status = args.status;
    role.hooks.start_stall(resumed.is_none());
    // Started after the plant's last state: a shorter quiet period settles the rest (not
    // none: the controller's last answer may still be coming, policy::END_QUIET_AFTER_END_NS).
    let quiet_limit = if ports.plant_end.ended() { END_QUIET_AFTER_END_NS } else { END_QUIET_NS };
    loop {
        ports.drain(&mut joiner)?;
        // The plant has ended (seen here, or in its resume slot by a monitor restarted
        // after the end) and nothing has arrived for a while: what is missing now never
        // comes (a role killed at the very end, say), so settle the rest.
        let quiet = joiner.quiet_ns(now_ns()) > quiet_limit;
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
            rec.status_line(joiner.last_state(), scenario.ticks() as f64 * scenario.dt(), now_ns());
        }
        if joiner.done() || stopping {
            break;
        }
        std::thread::sleep(std::time::Duration::from_micros(args.poll_us));
    }
    if joiner.done() {
        ports.slot.clear(); // finished: a later monitor in this domain starts a new report
    }
    let fallback = fallback_dir(&ports.domain);
    let record = args.role.record.as_deref();
    let summary =
        final_report(&args.out, record, &fallback, (&scenario, role, !args.no_csv), &joiner, rec);
    println!("{}", console_summary(&summary));
    write_summary(&args.out, &fallback, &summary)
}
