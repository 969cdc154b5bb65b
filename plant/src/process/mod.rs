//! The `plant` process: a thin shell over [`PlantTicker`] (the rules, in
//! [`crate::policy`]). Opens the services, resumes from the resume slot or waits for the
//! subscribers that must see tick 0, then runs the tick loop (`ticks::Loop`).

pub mod args;
mod gate;
mod ticks;
mod wait;

use rotorloop_common::role::args::Mode;
use rotorloop_common::role::end::linger_publisher;

use crate::ROLE;
use crate::policy::PlantTicker;
use wait::{Ports, SenseToActuate};

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
    let gates = if realtime { &[][..] } else { &args.gate_ticks[..] };
    let gate = gate::Gate::new(gates, plant.first(), resumed.is_some());
    let mut s2a = SenseToActuate::new()?;
    let ticks = ticks::Loop {
        args,
        role,
        scenario: &scenario,
        ports: &ports,
        plant: &mut plant,
        realtime,
        s2a: &mut s2a,
    };
    if args.no_gate {
        ticks.run(gate::NoGate)?;
    } else {
        ticks.run(gate)?;
    }
    let Ports { states, torques, .. } = ports;
    drop(torques);
    s2a.write(args.latency_out.as_deref());
    linger_publisher(&states, role);
    Ok(())
}
