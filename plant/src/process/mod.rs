//! The `plant` process: a thin shell over [`PlantTicker`] (the rules, in
//! [`crate::policy`]). Opens the services, resumes from the resume slot or waits for the
//! subscribers that must see tick 0, then per tick: (real time: sleep to the absolute grid
//! time) publish the state, wait for its torque (until the next grid time, or for ever in
//! lockstep), hand what arrived to the hold rule, step.

pub mod args;
mod gate;
mod wait;

use rotorloop_common::clock::{TickGrid, now_ns, sleep_until_ns};
use rotorloop_common::role::args::Mode;
use rotorloop_common::role::end::linger_publisher;
use rotorloop_common::signals::shutdown_requested;
use rotorloop_common::wire::SendCost;

use crate::ROLE;
use crate::policy::{Answer, PlantTicker};
use wait::{Ports, SenseToActuate, TorqueWait, made, publish};

/// Runs the plant until its last tick or a termination signal.
pub fn run(args: &args::PlantArgs) -> anyhow::Result<()> {
    let (role, scenario) = (&args.role, args.role.scenario()?);
    role.setup(ROLE);
    let ports = Ports::open(role, scenario.ticks())?;
    let realtime = role.mode == Mode::Realtime;
    let mut plant = PlantTicker::new(&scenario, args.hold_ticks, realtime, args.actuation_delay);
    let resumed = ports.slot.load_for(ROLE, scenario.ticks());
    let resumed = resumed.filter(|s| plant.can_resume(s));
    match resumed {
        Some(s) => plant.resume(&s),
        None if !ports.states.wait_for_subscribers(args.subscribers) => return Ok(()),
        None => {}
    }
    // Its refusals by kind continue with it; a fresh plant's start from none.
    plant.hold.resume_refusals(resumed.and_then(|_| ports.refusals.load()).unwrap_or_default());
    ports.refusals.store(&plant.hold.refusals());
    if plant.first() > 0 {
        eprintln!("plant: resuming at tick {} from its last published state", plant.first());
    }
    let (spin_ns, early) = (args.spin_before_tick_us * 1000, !role.plain_hot_path);
    let mut grid = TickGrid::new(now_ns() + 20_000_000, plant.first(), scenario.file.run.rate_hz);
    let pause = realtime && args.plant_stall == args::PlantStall::Pause;
    let (mut s2a, mut wait) = (SenseToActuate::new()?, TorqueWait::new(realtime));
    let mut cost = SendCost::default(); // what publishing the previous state cost
    let gates = if realtime { &[][..] } else { &args.gate_ticks[..] };
    let mut gate = gate::Gate::new(gates, plant.first(), resumed.is_some());
    for k in plant.first()..=plant.last() {
        let mut deadline = if realtime { grid.at(k) } else { 0 };
        let ahead = early.then(|| made(&ports, &plant, k, deadline, &args.corrupt)).transpose()?;
        if realtime {
            sleep_until_ns(deadline, spin_ns);
        } else {
            ports.hold_for_mover(k);
        }
        let woke = now_ns();
        if pause && grid.pause_if_late(k, woke) {
            deadline = woke;
        }
        // Made before the sleep (`wait::made`), or now with `--plain-hot-path`.
        let sample = ahead.map_or_else(|| made(&ports, &plant, k, deadline, &args.corrupt), Ok)?;
        cost = publish(&ports, sample, (deadline, woke, cost), &mut s2a)?;
        gate.pass(k); // lockstep: held here while the launcher carries out a fault
        let until = if realtime { grid.at(k + 1).saturating_sub(spin_ns) } else { u64::MAX };
        let answer = wait.answer(&ports, &mut plant, role, (k, deadline, until))?;
        if !matches!(answer, Some(Answer::Fresh(..))) && shutdown_requested() {
            break;
        }
        let settled = plant.settle(answer);
        s2a.record(answer);
        wait.report(&settled, k, args.hold_ticks);
        plant.step(k)?;
    }
    let Ports { states, torques, .. } = ports;
    drop(torques);
    s2a.write(args.latency_out.as_deref());
    linger_publisher(&states, role);
    Ok(())
}
