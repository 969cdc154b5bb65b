//! The `plant` process: a thin shell over [`PlantTicker`](crate::policy::PlantTicker).
//! Opens the services, resumes from the resume slot or waits for the subscribers that
//! must see tick 0, then per tick: (real time: sleep to the absolute grid time) publish
//! the state, wait for its torque (until the next grid time, or for ever in lockstep),
//! hand what arrived to the hold rule, step. The rules are in [`crate::policy`].

mod args;

use anyhow::Context;
use rotorloop_common::hgrm::write_percentile_distribution;
use rotorloop_common::ipc::{Outbox, Topic, now_ns, shutdown_requested, sleep_until_ns};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::role::{Mode, corrupted, linger};
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
    let mut plant = PlantTicker::new(&scenario, args.hold_ticks, realtime);
    match slot.load().filter(|s| plant.can_resume(s)) {
        Some(s) => plant.resume(&s),
        None if !wait_for_subscribers(&states, args.subscribers) => return Ok(()),
        None => {}
    }
    if plant.first() > 0 {
        eprintln!(
            "plant: resuming at tick {} from the last state published before a restart",
            plant.first()
        );
    }
    let (period_ns, spin_ns) = (1e9 / scenario.file.run.rate_hz, args.spin_before_tick_us * 1000);
    let (start_ns, first) = (now_ns() + 20_000_000, plant.first());
    let grid = |k: u64| start_ns + ((k - first) as f64 * period_ns).round() as u64;
    let mut s2a = hdrhistogram::Histogram::<u64>::new_with_bounds(1, 3_600_000_000_000, 3)?;
    let (mut publish_ns, mut last_update, mut waiting_logged) = (0u64, now_ns(), false);
    for k in plant.first()..=plant.last() {
        let deadline = if realtime { grid(k) } else { 0 };
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
        let until = if realtime { grid(k + 1).saturating_sub(spin_ns) } else { u64::MAX };
        let since = now_ns();
        let answer = torques.wait_for(role.wait, until, |inbox| {
            let mut answer: Option<Answer> = None;
            while let Some(t) = inbox.take()? {
                answer = plant.hold.take(&t, k, now_ns()).or(answer);
            }
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
        match plant.hold.settle(answer) {
            Settled::Fresh { after_safe_mode } => {
                if let Some(Answer::Fresh(_, recv)) = answer {
                    s2a.saturating_record(recv.saturating_sub(publish_ns).max(1));
                }
                if std::mem::take(&mut waiting_logged) | after_safe_mode {
                    eprintln!("plant: fresh torque at tick {k}; control resumed");
                }
            }
            Settled::Miss { entered_safe_mode, first_rejection } => {
                if let Some((tick, fault)) = first_rejection {
                    eprintln!(
                        "plant: rejected the torque of tick {tick}: {fault} (holding; counted)"
                    );
                }
                if entered_safe_mode {
                    eprintln!(
                        "plant: no fresh torque for {} ticks at tick {k}: safe mode (zero torque, rotors coast)",
                        args.hold_ticks
                    );
                }
            }
        }
        plant.step(k)?;
    }
    drop(torques);
    if let Some(dir) = &args.latency_out {
        let path = dir.join("plant_sense_to_actuate.hgrm");
        let mut f = std::fs::File::create(&path)
            .with_context(|| format!("plant: cannot write {}", path.display()))?;
        write_percentile_distribution(&s2a, &mut f)?;
    }
    linger(|| states.subscribers() == 0);
    Ok(())
}

/// Waits until `n` subscribers to the state are connected (they must see tick 0); false
/// on a termination signal.
fn wait_for_subscribers(states: &Outbox<StateSample>, n: usize) -> bool {
    while states.subscribers() < n {
        if shutdown_requested() {
            return false;
        }
        states.update_connections();
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    states.update_connections();
    true
}
