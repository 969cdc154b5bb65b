//! The `plant` process: a thin shell over [`PlantTicker`] (the rules, in
//! [`crate::policy`]). Opens the services, resumes from the resume slot or waits for the
//! subscribers that must see tick 0, then per tick: (real time: sleep to the absolute grid
//! time) publish the state, wait for its torque (until the next grid time, or for ever in
//! lockstep), hand what arrived to the hold rule, step.

mod args;

use anyhow::Context;
use rotorloop_common::hgrm::write_hgrm_file;
use rotorloop_common::ipc::{Topic, now_ns, shutdown_requested, sleep_until_ns};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::role::{Mode, TickGrid, corrupted, linger};
use rotorloop_common::wire::{StateSample, TorqueSample};

pub use args::PlantArgs;

use crate::policy::{Answer, PlantTicker, Settled};

/// Runs the plant until its last tick or a termination signal.
pub fn run(args: &PlantArgs) -> anyhow::Result<()> {
    let (role, scenario) = (&args.role, args.role.scenario()?);
    role.setup("plant");
    let domain = role.open_domain()?;
    let node = domain.node("plant").context("plant")?;
    let states = domain.outbox::<StateSample>(&node, Topic::State).context("plant")?;
    let torques = domain.inbox::<TorqueSample>(&node, Topic::Torque, 16, role.wait.listens());
    let torques = torques.context("plant")?;
    let slot = ResumeSlot::<StateSample>::open(&domain, "plant").context("plant")?;
    let realtime = role.mode == Mode::Realtime;
    let mut plant = PlantTicker::new(&scenario, args.hold_ticks, realtime, args.actuation_delay);
    match slot.load().filter(|s| plant.can_resume(s)) {
        Some(s) => plant.resume(&s),
        None if !states.wait_for_subscribers(args.subscribers) => return Ok(()),
        None => {}
    }
    if plant.first() > 0 {
        eprintln!("plant: resuming at tick {} from its last published state", plant.first());
    }
    let spin_ns = args.spin_before_tick_us * 1000;
    let grid = TickGrid::new(now_ns() + 20_000_000, plant.first(), scenario.file.run.rate_hz);
    let mut s2a = hdrhistogram::Histogram::<u64>::new_with_bounds(1, 3_600_000_000_000, 3)?;
    let (mut publish_ns, mut last_update, mut waiting_logged) = (0u64, now_ns(), false);
    for k in plant.first()..=plant.last() {
        let deadline = if realtime { grid.at(k) } else { 0 };
        if realtime {
            sleep_until_ns(deadline, spin_ns);
        }
        let sample = plant.state_sample(k, deadline, now_ns());
        // Slot first: killed between the two, the restart publishes this very state,
        // which the controller answers (or answers again). The other order would let a
        // restart re-publish tick k−1 after the controller has moved past it: deadlock.
        slot.store(&sample);
        let stamp = |s: &mut StateSample| (s.publish_ns, publish_ns) = (now_ns(), s.publish_ns);
        states.send(corrupted(&args.corrupt, sample), stamp).context("plant: publishing state")?;
        let until = if realtime { grid.at(k + 1).saturating_sub(spin_ns) } else { u64::MAX };
        let since = now_ns();
        let answer = torques.wait_for(role.wait, until, |inbox| {
            let mut answer: Option<Answer> = None;
            inbox.drain(|t| {
                let took = plant.take(&t, k, deadline, now_ns());
                answer = took.filter(Answer::answers_the_tick).or(answer);
            })?;
            if answer.is_none() && now_ns() - last_update > 5_000_000 {
                // Late joiners (a controller started after us) get the state from history.
                (last_update, _) = (now_ns(), states.update_connections());
                if !realtime && !waiting_logged && now_ns() - since > 1_000_000_000 {
                    eprintln!("plant: no torque for tick {k} for 1 s (controller gone?); waiting");
                    waiting_logged = true;
                }
            }
            Ok(answer)
        })?;
        if !matches!(answer, Some(Answer::Fresh(..))) && shutdown_requested() {
            break;
        }
        let settled = plant.settle(answer);
        if let Some(Answer::Fresh(_, recv)) = answer {
            s2a.saturating_record(recv.saturating_sub(publish_ns).max(1));
        }
        let resumed =
            matches!(settled, Settled::Fresh { .. }) && std::mem::take(&mut waiting_logged);
        match settled.event(k, args.hold_ticks) {
            Some(event) => eprintln!("plant: {event}"),
            None if resumed => eprintln!("plant: fresh torque at tick {k}; control resumed"),
            None => {}
        }
        plant.step(k)?;
    }
    drop(torques);
    if let Some(dir) = &args.latency_out {
        // An optional measurement: a full disk is a warning, never a failed run.
        if let Err(e) = write_hgrm_file(&dir.join("plant_sense_to_actuate.hgrm"), &s2a) {
            eprintln!("plant: warning: {e}");
        }
    }
    linger(|| states.subscribers() == 0);
    Ok(())
}
