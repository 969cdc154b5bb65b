//! The plant's tick loop, generic over its lockstep gate ([`gate::Pass`]): the loop is
//! compiled once with the gate and once without it (`--no-gate`, only so that `rotorloop
//! bench --before-after gate` measures the loop before the gate was added against the
//! loop with it, in one invocation).

use rotorloop_common::clock::{TickGrid, now_ns, sleep_until_ns};
use rotorloop_common::role::args::RoleArgs;
use rotorloop_common::scenario::Scenario;
use rotorloop_common::signals::shutdown_requested;
use rotorloop_common::wire::SendCost;

use super::args::{PlantArgs, PlantStall};
use super::gate::Pass;
use super::wait::{Ports, SenseToActuate, TorqueWait, made, publish};
use crate::policy::{Answer, PlantTicker};

/// What the loop runs on: the plant's arguments, its ports and its ticker.
pub(super) struct Loop<'a> {
    pub args: &'a PlantArgs,
    pub role: &'a RoleArgs,
    pub scenario: &'a Scenario,
    pub ports: &'a Ports,
    pub plant: &'a mut PlantTicker,
    pub realtime: bool,
    /// The plant's own sense-to-actuate histogram.
    pub s2a: &'a mut SenseToActuate,
}

impl Loop<'_> {
    /// Per tick: (real time: sleep to the absolute grid time) publish the state, pass the
    /// gate, wait for its torque (until the next grid time, or for ever in lockstep), hand
    /// what arrived to the hold rule, step. Until the last tick or a termination signal.
    pub fn run<G: Pass>(self, mut gate: G) -> anyhow::Result<()> {
        let Self { args, role, scenario, ports, plant, realtime, s2a } = self;
        let (spin_ns, early) = (args.spin_before_tick_us * 1000, !role.plain_hot_path);
        let rate = scenario.file.run.rate_hz;
        let mut grid = TickGrid::new(now_ns() + 20_000_000, plant.first(), rate);
        let pause = realtime && args.plant_stall == PlantStall::Pause;
        let mut wait = TorqueWait::new(realtime);
        let mut cost = SendCost::default(); // what publishing the previous state cost
        for k in plant.first()..=plant.last() {
            let mut deadline = if realtime { grid.at(k) } else { 0 };
            let ahead =
                early.then(|| made(ports, plant, k, deadline, &args.corrupt)).transpose()?;
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
            let sample =
                ahead.map_or_else(|| made(ports, plant, k, deadline, &args.corrupt), Ok)?;
            cost = publish(ports, sample, (deadline, woke, cost), s2a)?;
            gate.pass(k); // lockstep: held here while the launcher carries out a fault
            let until = if realtime { grid.at(k + 1).saturating_sub(spin_ns) } else { u64::MAX };
            let answer = wait.answer(ports, plant, role, (k, deadline, until))?;
            if !matches!(answer, Some(Answer::Fresh(..))) && shutdown_requested() {
                break;
            }
            let settled = plant.settle(answer);
            s2a.record(answer);
            wait.report(&settled, k, args.hold_ticks);
            plant.step(k)?;
        }
        Ok(())
    }
}
