//! The `controller` process: answers each state sample with rotor and body torques from
//! the geometric PID law, pairing it with the reference sample of the same tick.
//!
//! The reference is published ahead, so it is normally there when the state arrives.
//! When it is not (a reference miss, counted): in lockstep the controller waits for it,
//! so the run stays deterministic; in real time it skips the tick (the plant holds the
//! last torque), because a late answer is useless to it.

use anyhow::Context;
use clap::Args;
use rotorloop_common::Actuation;
use rotorloop_common::ipc::{Topic, now_ns, shutdown_requested};
use rotorloop_common::wire::{FLAG_LAST, ReferenceSample, StateSample, TorqueSample};
use rotorloop_controller::GeometricPid;

use super::{Mode, RoleArgs, SeqCounter, linger};

/// `controller` arguments.
#[derive(Debug, Clone, Args)]
pub struct ControllerArgs {
    #[command(flatten)]
    pub role: RoleArgs,
}

const RING: usize = 256;

/// Runs the controller until the plant's last tick or a termination signal.
pub fn run(args: &ControllerArgs) -> anyhow::Result<()> {
    let role = &args.role;
    let scenario = role.scenario()?;
    role.setup("controller");
    let domain = role.open_domain()?;
    let node = domain.node("controller").context("controller")?;
    let out = domain.outbox::<TorqueSample>(&node, Topic::Torque).context("controller")?;
    // Subscribe to the state last: the plant starts when it sees its state subscribers.
    let refs = domain
        .inbox::<ReferenceSample>(&node, Topic::Reference, 128, false)
        .context("controller")?;
    let states = domain
        .inbox::<StateSample>(&node, Topic::State, 8, role.wait.listens())
        .context("controller")?;

    let model = match scenario.actuation() {
        Actuation::Internal => scenario.plant,
        Actuation::External => scenario.plant.without_rotors(),
    };
    let mut pid = GeometricPid::new(scenario.gains, model);
    let dt = scenario.dt();
    let lockstep = role.mode == Mode::Lockstep;
    let mut ring: Vec<Option<ReferenceSample>> = vec![None; RING];
    let mut state_seq = SeqCounter::default();
    let mut reference_misses = 0u64;
    let mut skipped = 0u64;
    let mut published = 0u64;

    let drain_refs = |ring: &mut Vec<Option<ReferenceSample>>| -> anyhow::Result<()> {
        while let Some(r) = refs.take()? {
            ring[r.tick as usize % RING] = Some(r);
        }
        Ok(())
    };
    let lookup = |ring: &Vec<Option<ReferenceSample>>, k: u64| {
        ring[k as usize % RING].filter(|r| r.tick == k)
    };

    loop {
        let deadline = now_ns() + 100_000_000;
        let state = states.wait_for(role.wait, deadline, |inbox| {
            let mut newest = None;
            while let Some(s) = inbox.take()? {
                state_seq.see(s.tick);
                if newest.is_some() {
                    skipped += 1;
                }
                newest = Some((s, now_ns()));
            }
            Ok(newest)
        })?;
        let Some((state, recv_ns)) = state else {
            if shutdown_requested() {
                break;
            }
            continue;
        };
        let k = state.tick;
        drain_refs(&mut ring)?;
        let mut rd = lookup(&ring, k);
        if rd.is_none() {
            reference_misses += 1;
            if lockstep {
                while rd.is_none() && !shutdown_requested() {
                    std::thread::sleep(std::time::Duration::from_micros(100));
                    drain_refs(&mut ring)?;
                    rd = lookup(&ring, k);
                }
            }
        }
        let Some(rd) = rd else {
            if shutdown_requested() {
                break;
            }
            continue; // real time: no answer this tick; the plant holds the last torque
        };
        let out_k = pid.step(&state.body_state(), &rd.reference_state(), dt);
        published += 1;
        let sample = TorqueSample {
            tick: k,
            rotor_torque_nm: out_k.rotor_torque.to_array(),
            body_torque_nm: out_k.body_torque.to_array(),
            xi_i: pid.integral_state().to_array(),
            state_recv_ns: recv_ns,
            publish_ns: 0,
            states_received: state_seq.received,
            states_lost: state_seq.lost,
            states_skipped: skipped,
            reference_misses,
            published,
        };
        out.send(sample, |s| s.publish_ns = now_ns()).context("controller: publishing torque")?;
        if state.flags & FLAG_LAST != 0 {
            break;
        }
    }
    drop(states);
    drop(refs);
    linger(|| out.subscribers() == 0);
    Ok(())
}
