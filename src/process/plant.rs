//! The `plant` process: steps the body with the newest rotor torque (zero-order hold)
//! and publishes its state every tick.
//!
//! Lockstep: publish state k, wait for torque k, step. Real time: wake at the absolute
//! grid time of tick k, publish state k, then wait for torque k until the next grid time;
//! step as soon as it arrives (so sense-to-actuate measures the loop, not the period).
//! If it does not arrive in time, hold the last torque, count a miss and step at the
//! next grid time.

use anyhow::Context;
use clap::Args;
use glam::DVec3;
use rotorloop_common::Actuation;
use rotorloop_common::ipc::{Topic, now_ns, shutdown_requested, sleep_until_ns};
use rotorloop_common::wire::{FLAG_LAST, FLAG_REALTIME, NO_TICK, StateSample, TorqueSample};
use rotorloop_plant::{Body, BodyInput};

use super::{Mode, RoleArgs, SeqCounter, linger};

/// `plant` arguments.
#[derive(Debug, Clone, Args)]
pub struct PlantArgs {
    #[command(flatten)]
    pub role: RoleArgs,
    /// Wait for this many subscribers to the state before tick 0 (controller and
    /// reference; 3 with a monitor that must see every tick).
    #[arg(long, default_value_t = 2)]
    pub subscribers: usize,
    /// In real time, sleep until this many µs before each grid time and spin the rest.
    #[arg(long, default_value_t = 0)]
    pub spin_before_tick_us: u64,
    /// Also record sense-to-actuate in the plant itself and write
    /// `DIR/plant_sense_to_actuate.hgrm` at the end (works without a monitor).
    #[arg(long)]
    pub latency_out: Option<std::path::PathBuf>,
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

    let actuation = scenario.actuation();
    let params = match actuation {
        Actuation::Internal => scenario.plant,
        Actuation::External => scenario.plant.without_rotors(),
    };
    let mut body = Body::new(params, scenario.plant_init);
    let ticks = scenario.ticks();
    let dt = scenario.dt();
    let realtime = role.mode == Mode::Realtime;
    let period_ns = 1e9 / scenario.file.run.rate_hz;

    // Wait for the subscribers that must see tick 0.
    while states.subscribers() < args.subscribers {
        if shutdown_requested() {
            return Ok(());
        }
        states.update_connections();
        std::thread::sleep(std::time::Duration::from_millis(1));
    }
    states.update_connections();

    let start_ns = now_ns() + 20_000_000;
    let grid = |k: u64| start_ns + (k as f64 * period_ns).round() as u64;
    let spin_last = args.spin_before_tick_us * 1000;
    let mut held = BodyInput::default();
    let mut held_tick = NO_TICK;
    let mut held_recv_ns = 0u64;
    let mut seq = SeqCounter::default();
    let mut misses = 0u64;
    let mut last_update = now_ns();
    let mut s2a = hdrhistogram::Histogram::<u64>::new_with_bounds(1, 3_600_000_000_000, 3)?;
    let mut publish_ns = 0u64;

    for k in 0..=ticks {
        let deadline = if realtime { grid(k) } else { 0 };
        if realtime {
            sleep_until_ns(deadline, spin_last);
        }
        let wake = now_ns();
        let mut sample = StateSample::of(k, k as f64 * dt, &body.state());
        sample.applied_rotor_torque_nm = held.rotor_torque.to_array();
        sample.applied_body_torque_nm = held.body_torque.to_array();
        sample.applied_torque_tick = held_tick;
        sample.applied_torque_recv_ns = held_recv_ns;
        sample.deadline_ns = deadline;
        sample.wake_ns = wake;
        sample.misses = misses;
        sample.torques_received = seq.received;
        sample.torques_lost = seq.lost;
        sample.flags =
            if k == ticks { FLAG_LAST } else { 0 } | if realtime { FLAG_REALTIME } else { 0 };
        states
            .send(sample, |s| {
                s.publish_ns = now_ns();
                publish_ns = s.publish_ns;
            })
            .context("plant: publishing state")?;

        let wait_until = if realtime { grid(k + 1).saturating_sub(spin_last) } else { u64::MAX };
        let got = torques.wait_for(role.wait, wait_until, |inbox| {
            let mut found = None;
            while let Some(t) = inbox.take()? {
                seq.see(t.tick);
                if t.tick == k {
                    found = Some((t, now_ns()));
                }
            }
            // Late joiners (a controller started after us) get the state from history.
            if found.is_none() && now_ns() - last_update > 5_000_000 {
                states.update_connections();
                last_update = now_ns();
            }
            Ok(found)
        })?;
        match got {
            Some((t, recv)) => {
                held = match actuation {
                    Actuation::Internal => BodyInput {
                        rotor_torque: DVec3::from_array(t.rotor_torque_nm),
                        body_torque: DVec3::ZERO,
                    },
                    Actuation::External => BodyInput {
                        rotor_torque: DVec3::ZERO,
                        body_torque: DVec3::from_array(t.body_torque_nm),
                    },
                };
                held_tick = t.tick;
                held_recv_ns = recv;
                s2a.saturating_record(recv.saturating_sub(publish_ns).max(1));
            }
            None if shutdown_requested() => break,
            None => misses += 1, // hold the last torque
        }
        if k < ticks {
            body.step(held, dt);
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
