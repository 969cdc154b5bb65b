//! The `reference` process: a thin shell over [`LeadWindow`] (the rule, in [`crate::policy`]).
//! It publishes `R_d, Ω_d, Ω̇_d` up to the lead ahead of the newest state, so the controller
//! never waits for it; a restart re-publishes its window and continues. It reads only the
//! tick and flags of states, so it needs no validation. It never spins, whatever `--wait`
//! says (it is off the hot path; a spinning loop must not get a third busy process).

pub mod args;

use anyhow::Context;
use rotorloop_common::flight::Stream;
use rotorloop_common::graph::Topic;
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::role::{end::PlantWatch, end::linger_publisher, inject::corrupted};
use rotorloop_common::wire::{FLAG_LAST, ReferenceSample, StateSample};
use rotorloop_common::{clock::now_ns, signals::shutdown_requested};

use crate::ROLE;
use crate::policy::{LeadWindow, ReferenceResume};

/// Runs the reference generator until the plant's last tick or a termination signal.
pub fn run(args: &args::ReferenceArgs) -> anyhow::Result<()> {
    let (role, scenario) = (&args.role, args.role.scenario()?);
    role.setup(ROLE);
    let domain = role.open_domain()?;
    let node = domain.node(ROLE).context(ROLE)?;
    let out = domain.outbox::<ReferenceSample>(&node, Topic::Reference).context(ROLE)?;
    let wait = args.wait(scenario.dt());
    let states = domain.inbox::<StateSample>(&node, Topic::State, 8, wait.listens())?;
    let slot = ResumeSlot::<ReferenceResume>::open(&domain, ROLE).context(ROLE)?;
    let mut plant = PlantWatch::open(&domain, ROLE).context(ROLE)?;
    let mut lead = LeadWindow::new(&scenario);
    let flight = role.flight(Stream::Reference, scenario.ticks(), ROLE);
    let send =
        |s: ReferenceSample| out.send_stamped(s, |s, t1| s.publish_ns = t1, |s| flight.record(s));
    let resumed = slot.load_for(ROLE, scenario.ticks());
    if let Some(r) = resumed.filter(|r| lead.can_resume(r)) {
        for again in lead.resume(&scenario, &r) {
            send(again).context("reference: re-publishing")?;
        }
        eprintln!("reference: resuming after tick {} (its window re-published)", lead.next() - 1);
    } else if let Some(ms) = args.role.hooks.test_reference_late_ms {
        // Test hook: a first incarnation starts late; states reach the controller first.
        std::thread::sleep(std::time::Duration::from_millis(ms));
    }
    let mut saw_last = false;
    loop {
        let mut batch = false;
        while let Some(sample) = lead.next_due() {
            send(corrupted(&args.corrupt, sample)).context("reference: publishing")?;
            batch = true;
        }
        if batch {
            slot.store(lead.window()); // once per batch: the window is a few KiB
        }
        if saw_last || shutdown_requested() {
            break;
        }
        let newest = states.wait_for(wait, now_ns() + 100_000_000, |inbox| {
            let mut newest = None;
            inbox.drain(|s| {
                saw_last |= s.flags & FLAG_LAST != 0;
                newest = newest.max(Some(s.tick));
            })?;
            if newest.is_none() {
                out.update_connections();
            }
            Ok(newest)
        })?;
        match newest {
            Some(tick) => (lead.saw_state(tick), plant.saw_state(tick, now_ns())).1,
            None if plant.run_over() => break,
            None => {}
        }
    }
    drop(states);
    linger_publisher(&out, role);
    Ok(())
}
