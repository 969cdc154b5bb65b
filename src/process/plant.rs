//! The `plant` process: steps the body with the newest rotor torque (zero-order hold)
//! and publishes its state every tick.
//!
//! Lockstep: publish state k, wait for torque k, step. Real time: wake at the absolute
//! grid time of tick k, publish state k, then wait for torque k until the next grid time;
//! step as soon as it arrives (so sense-to-actuate measures the loop, not the period).
//! If it does not arrive in time, hold the last torque and count a miss; after
//! `--hold-ticks` ticks without a fresh torque, enter safe mode: zero torque (the rotors
//! coast and momentum is conserved) until a fresh torque arrives.
//!
//! **Rejected torque.** Every torque sample is validated ([`TorqueSample::validate`]):
//! NaN, infinity, or a magnitude beyond [`TorqueSample::absurd_limit`] of the scenario's
//! rotor torque limit is rejected and counted (`torques_rejected`). A rejected torque,
//! like a controller's [`TORQUE_SKIPPED`] answer, is a missing torque: the plant holds
//! the last good one, counts a miss, and enters safe mode after `--hold-ticks` such
//! ticks, in lockstep as in real time. Nothing of a rejected sample reaches the state.
//!
//! **Actuators.** The held rotor torque goes through the scenario's actuator limits every
//! tick (torque saturation, rotor speed limit); the state sample carries the torque
//! actually applied and [`FLAG_SATURATED`] / `saturated_ticks`. A constant disturbance
//! torque from the scenario is added to the body torque of every step.
//!
//! Restart: a plant started while its resume slot holds an unfinished run (its
//! predecessor was killed) continues from the last state it published, at the same tick
//! index, bit for bit (the slot carries the integrator's own state).

use anyhow::Context;
use clap::Args;
use glam::DVec3;
use rotorloop_common::Actuation;
use rotorloop_common::ipc::{Topic, now_ns, shutdown_requested, sleep_until_ns};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::wire::{
    FLAG_LAST, FLAG_REALTIME, FLAG_SAFE_MODE, FLAG_SATURATED, NO_TICK, StateSample, TORQUE_SKIPPED,
    TorqueSample,
};
use rotorloop_plant::{Body, BodyInput};

use super::{Mode, RoleArgs, SeqCounter, corrupted, linger};

/// `plant` arguments.
#[derive(Debug, Clone, Args)]
pub struct PlantArgs {
    #[command(flatten)]
    pub role: RoleArgs,
    /// Fault injection: publish this tick's sample corrupted (`nan@TICK`, `inf@TICK`,
    /// `huge@TICK`, `skew@TICK`). Repeatable. Set by `rotorloop run --corrupt`.
    #[arg(long)]
    pub corrupt: Vec<super::Corrupt>,
    /// Wait for this many subscribers to the state before tick 0 (controller and
    /// reference; 3 with a monitor that must see every tick).
    #[arg(long, allow_negative_numbers = true, default_value_t = 2)]
    pub subscribers: usize,
    /// In real time, sleep until this many µs before each grid time and spin the rest.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
    pub spin_before_tick_us: u64,
    /// Real time: ticks to hold the last torque without a fresh one before safe mode.
    #[arg(long, allow_negative_numbers = true, default_value_t = 50)]
    pub hold_ticks: u64,
    /// Also record sense-to-actuate in the plant itself and write
    /// `DIR/plant_sense_to_actuate.hgrm` at the end (works without a monitor).
    #[arg(long)]
    pub latency_out: Option<std::path::PathBuf>,
}

fn input_of(t: &TorqueSample, actuation: Actuation) -> BodyInput {
    match actuation {
        Actuation::Internal => BodyInput {
            rotor_torque: DVec3::from_array(t.rotor_torque_nm),
            body_torque: DVec3::ZERO,
        },
        Actuation::External => BodyInput {
            rotor_torque: DVec3::ZERO,
            body_torque: DVec3::from_array(t.body_torque_nm),
        },
    }
}

/// Runs the plant until its last tick or a termination signal.
pub fn run(args: &PlantArgs) -> anyhow::Result<()> {
    let role = &args.role;
    let scenario = role.scenario()?;
    role.setup("plant");
    let domain = role.open_domain()?;
    let node = domain.node("plant").context("plant")?;
    let states = domain.outbox::<StateSample>(&node, Topic::State).context("plant")?;
    let torques = domain
        .inbox::<TorqueSample>(&node, Topic::Torque, 16, role.wait.listens())
        .context("plant")?;
    let slot = ResumeSlot::<StateSample>::open(&domain, "plant").context("plant")?;

    let actuation = scenario.actuation();
    let params = scenario.plant_params(actuation);
    let ticks = scenario.ticks();
    let dt = scenario.dt();
    let realtime = role.mode == Mode::Realtime;
    let period_ns = 1e9 / scenario.file.run.rate_hz;

    let mut body = Body::new(params, scenario.plant_init);
    let mut first = 0u64;
    let mut held = BodyInput::default();
    let mut held_tick = NO_TICK;
    let mut held_recv_ns = 0u64;
    let mut seq = SeqCounter::default();
    let mut misses = 0u64;
    let mut safe_ticks = 0u64;
    let mut rejected = 0u64;
    let mut saturated_ticks = 0u64;
    let mut saturated = false;
    let limits = scenario.limits_for(actuation);
    let torque_limit = TorqueSample::absurd_limit(limits.rotor_torque);
    let disturbance = scenario.disturbance;
    let resumed = slot.load().filter(|s| s.flags & FLAG_LAST == 0 && s.tick <= ticks);
    if let Some(s) = resumed {
        let x = s.body_state();
        body = Body::from_internal(
            params,
            x.r,
            DVec3::from_array(s.internal_h),
            DVec3::from_array(s.internal_p),
            x.theta,
        );
        first = s.tick;
        held = BodyInput {
            rotor_torque: DVec3::from_array(s.applied_rotor_torque_nm),
            body_torque: DVec3::from_array(s.applied_body_torque_nm),
        };
        held_tick = s.applied_torque_tick;
        held_recv_ns = s.applied_torque_recv_ns;
        misses = s.misses;
        safe_ticks = s.safe_mode_ticks;
        rejected = s.torques_rejected;
        saturated_ticks = s.saturated_ticks;
        saturated = s.flags & FLAG_SATURATED != 0;
        seq = match s.applied_torque_tick {
            NO_TICK => SeqCounter { received: s.torques_received, lost: s.torques_lost, ..seq },
            t => SeqCounter::resume(s.torques_received, s.torques_lost, t),
        };
        eprintln!("plant: resuming at tick {first} from the last state published before a restart");
    } else {
        // Wait for the subscribers that must see tick 0.
        while states.subscribers() < args.subscribers {
            if shutdown_requested() {
                return Ok(());
            }
            states.update_connections();
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
    }
    states.update_connections();

    let start_ns = now_ns() + 20_000_000;
    let grid = |k: u64| start_ns + ((k - first) as f64 * period_ns).round() as u64;
    let spin_last = args.spin_before_tick_us * 1000;
    let mut last_update = now_ns();
    let mut s2a = hdrhistogram::Histogram::<u64>::new_with_bounds(1, 3_600_000_000_000, 3)?;
    let mut publish_ns = 0u64;
    let mut stale = 0u64; // ticks since the last fresh torque
    let mut safe = resumed.is_some_and(|s| s.flags & FLAG_SAFE_MODE != 0);
    let mut waiting_logged = false;
    let mut rejection_logged = false;
    let mut applied = held;

    for k in first..=ticks {
        let deadline = if realtime { grid(k) } else { 0 };
        if realtime {
            sleep_until_ns(deadline, spin_last);
        }
        let wake = now_ns();
        let x = body.state();
        let mut sample = StateSample::of(k, k as f64 * dt, &x);
        let (_, h, p, _) = body.internal();
        sample.internal_h = h.to_array();
        sample.internal_p = p.to_array();
        sample.applied_rotor_torque_nm = applied.rotor_torque.to_array();
        sample.applied_body_torque_nm = applied.body_torque.to_array();
        sample.applied_torque_tick = held_tick;
        sample.applied_torque_recv_ns = held_recv_ns;
        sample.deadline_ns = deadline;
        sample.wake_ns = wake;
        sample.misses = misses;
        sample.safe_mode_ticks = safe_ticks;
        sample.torques_received = seq.received;
        sample.torques_lost = seq.lost;
        sample.torques_rejected = rejected;
        sample.saturated_ticks = saturated_ticks;
        sample.flags = if k == ticks { FLAG_LAST } else { 0 }
            | if realtime { FLAG_REALTIME } else { 0 }
            | if safe { FLAG_SAFE_MODE } else { 0 }
            | if saturated { FLAG_SATURATED } else { 0 };
        // Slot first: killed between the two, the restart publishes this very state,
        // which the controller answers (or answers again). The other order would let a
        // restart re-publish tick k−1 after the controller has moved past it: deadlock.
        slot.store(&sample);
        states
            .send(corrupted(&args.corrupt, sample), |s| {
                s.publish_ns = now_ns();
                publish_ns = s.publish_ns;
            })
            .context("plant: publishing state")?;

        let wait_until = if realtime { grid(k + 1).saturating_sub(spin_last) } else { u64::MAX };
        let since = now_ns();
        let got = torques.wait_for(role.wait, wait_until, |inbox| {
            let mut found = None;
            while let Some(t) = inbox.take()? {
                seq.see(t.tick);
                let fault = t.validate(torque_limit).err();
                if fault.is_some() {
                    rejected += 1;
                }
                if t.tick == k {
                    // A rejected or skipped answer ends the wait too: the controller
                    // will not send another for this tick.
                    found = Some((t, now_ns(), fault));
                }
            }
            if found.is_none() && now_ns() - last_update > 5_000_000 {
                // Late joiners (a controller started after us) get the state from history.
                states.update_connections();
                last_update = now_ns();
                if !realtime && !waiting_logged && now_ns() - since > 1_000_000_000 {
                    eprintln!("plant: no torque for tick {k} for 1 s (controller gone?); waiting");
                    waiting_logged = true;
                }
            }
            Ok(found)
        })?;
        let got = match got {
            Some((t, _, Some(fault))) => {
                if !rejection_logged {
                    eprintln!(
                        "plant: rejected the torque of tick {}: {fault} (holding; counted)",
                        t.tick
                    );
                    rejection_logged = true;
                }
                None
            }
            Some((t, _, None)) if t.flags & TORQUE_SKIPPED != 0 => None,
            Some((t, recv, None)) => Some((t, recv)),
            None => None,
        };
        match got {
            Some((t, recv)) => {
                if waiting_logged || safe {
                    eprintln!("plant: fresh torque at tick {k}; control resumed");
                }
                waiting_logged = false;
                safe = false;
                stale = 0;
                held = input_of(&t, actuation);
                held_tick = t.tick;
                held_recv_ns = recv;
                s2a.saturating_record(recv.saturating_sub(publish_ns).max(1));
            }
            None if shutdown_requested() => break,
            None => {
                misses += 1;
                stale += 1;
                if stale > args.hold_ticks && !safe {
                    safe = true;
                    eprintln!(
                        "plant: no fresh torque for {} ticks at tick {k}: safe mode (zero torque, rotors coast)",
                        args.hold_ticks
                    );
                }
                if safe {
                    safe_ticks += 1;
                    held = BodyInput::default();
                    held_tick = NO_TICK;
                }
            }
        }
        if k < ticks {
            // The motors deliver what their limits allow at the current rotor rates.
            // At the rates of the state published this tick (the body has not moved since).
            let (u, sat) = limits.apply(held.rotor_torque, x.omega_r);
            saturated = sat;
            saturated_ticks += u64::from(sat);
            applied = BodyInput { rotor_torque: u, body_torque: held.body_torque };
            body.step(
                BodyInput { rotor_torque: u, body_torque: held.body_torque + disturbance },
                dt,
            );
            if !body.is_finite() {
                // Publish nothing non-finite: stop, as the simulator does.
                return Err(crate::sim::diverged(k + 1, (k + 1) as f64 * dt).into());
            }
        }
    }
    drop(torques);
    if let Some(dir) = &args.latency_out {
        let path = dir.join("plant_sense_to_actuate.hgrm");
        let mut f = std::fs::File::create(&path)
            .with_context(|| format!("plant: cannot write {}", path.display()))?;
        rotorloop_monitor::latency::write_percentile_distribution(&s2a, &mut f)?;
    }
    linger(|| states.subscribers() == 0);
    Ok(())
}
