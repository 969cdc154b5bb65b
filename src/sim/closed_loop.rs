//! The closed loop in one process: plant, reference, control law and metrics, stepped
//! together. The same algorithm structs run in the four-process loop; this is the
//! in-process simulator's core and the unit the benchmark measures.

use glam::DVec3;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rotorloop_common::params::{ActuatorLimits, ReferenceState};
use rotorloop_common::scenario::{Actuation, Scenario};
use rotorloop_controller::law::{AnyLaw, ControlOutput, Law, UnknownLaw};
use rotorloop_monitor::metrics::{Metrics, TraceRow};
use rotorloop_plant::actuator::{ActuationDelay, DelayLine, integrate_tick};
use rotorloop_plant::{Body, BodyInput};
use rotorloop_reference::Reference;

/// Delays drawn from a measured latency distribution: `(quantile, seconds)` points of its
/// inverse CDF (from a `.hgrm`), sampled with a seeded generator, so a run is reproducible
/// by its seed.
#[derive(Debug, Clone)]
pub struct DrawnDelays {
    quantiles: Vec<(f64, f64)>,
    rng: ChaCha8Rng,
}

impl DrawnDelays {
    /// Draws from the inverse CDF `quantiles` (increasing in both) with `seed`.
    pub fn new(quantiles: Vec<(f64, f64)>, seed: u64) -> Self {
        use rand::SeedableRng;
        Self { quantiles, rng: ChaCha8Rng::seed_from_u64(seed) }
    }

    /// The next delay (s): the inverse CDF at a uniform draw, linear between points.
    pub fn draw(&mut self) -> f64 {
        let u: f64 = self.rng.random();
        let q = &self.quantiles;
        let i = q.partition_point(|(p, _)| *p < u).min(q.len() - 1);
        if i == 0 {
            return q[0].1;
        }
        let ((p0, v0), (p1, v1)) = (q[i - 1], q[i]);
        if p1 > p0 { v0 + (v1 - v0) * (u - p0) / (p1 - p0) } else { v1 }
    }
}

/// How many reference samples [`ClosedLoop::drive_ahead`] hands over at once.
pub const AHEAD_BLOCK: usize = 1024;
/// How many blocks are in flight: the reference runs at most this many blocks ahead.
const AHEAD_BLOCKS: usize = 4;

/// Plant + reference + controller + metrics at a fixed tick.
#[derive(Debug, Clone)]
pub struct ClosedLoop {
    plant: Body,
    reference: Reference,
    law: AnyLaw,
    /// The controller switched off and this rotor torque held (N m): for checking the
    /// physics against other simulators.
    open_loop: Option<DVec3>,
    metrics: Metrics,
    actuation: Actuation,
    limits: ActuatorLimits,
    disturbance: DVec3,
    dt: f64,
    tick: u64,
    last: u64,
    /// Rotor work over the previous tick (J).
    work: f64,
    saturated_ticks: u64,
    line: DelayLine,
    drawn: Option<DrawnDelays>,
}

impl ClosedLoop {
    /// The loop of a validated scenario. The reference is momentum-matched to the
    /// rotor-actuated plant in both actuations, so an internal and an external run track
    /// the same reference. `open_loop` replaces the controller by a constant rotor torque.
    /// An error if the scenario names no known law.
    pub fn new(
        scenario: &Scenario,
        actuation: Actuation,
        open_loop: Option<DVec3>,
    ) -> Result<Self, UnknownLaw> {
        let reference = Reference::for_scenario(scenario);
        let body = scenario.plant_params(actuation);
        let plant = Body::new(body, scenario.plant_init);
        let limits = scenario.limits_for(actuation);
        let law = AnyLaw::for_scenario(scenario, actuation)?;
        let metrics = Metrics::new(body, &plant.state()).with_disturbance(scenario.disturbance);
        Ok(Self {
            plant,
            reference,
            law,
            open_loop,
            metrics,
            actuation,
            limits,
            disturbance: scenario.disturbance,
            dt: scenario.dt(),
            tick: 0,
            last: scenario.ticks(),
            work: 0.0,
            saturated_ticks: 0,
            line: DelayLine::new(ActuationDelay::Instant, scenario.dt()),
            drawn: None,
        })
    }

    /// Each torque takes effect `delay` after its tick's time (delayed zero-order hold;
    /// `Instant` is the plain zero-order hold).
    pub fn with_delay(mut self, delay: ActuationDelay) -> Self {
        self.line = DelayLine::new(delay, self.dt);
        self
    }

    /// Each torque's delay is drawn from `drawn` (a measured distribution).
    pub fn with_drawn_delays(mut self, drawn: DrawnDelays) -> Self {
        self.drawn = Some(drawn);
        self
    }

    /// The next tick index.
    pub fn tick_index(&self) -> u64 {
        self.tick
    }

    /// The plant.
    pub fn plant(&self) -> &Body {
        &self.plant
    }

    /// The reference generator.
    pub fn reference(&self) -> &Reference {
        &self.reference
    }

    /// Ticks so far whose rotor torque the actuator limits changed.
    pub fn saturated_ticks(&self) -> u64 {
        self.saturated_ticks
    }

    /// The metrics.
    pub fn metrics(&self) -> &Metrics {
        &self.metrics
    }

    /// One tick `k`: read the state and reference at `t_k = k dt`, compute the torques,
    /// record the row, then advance plant (the torques in force, piecewise: delayed
    /// zero-order hold) and reference to `t_k+1`. Allocation-free.
    #[inline]
    pub fn tick(&mut self) -> TraceRow {
        let t = self.tick as f64 * self.dt;
        let rd = self.reference.sample(t);
        let row = self.tick_given(&rd);
        self.reference.step(t, self.dt);
        row
    }

    /// [`ClosedLoop::tick`] with the reference's sample at `t_k` given (`rd`, as
    /// `self.reference().sample(t_k)` makes it) and the reference not stepped: its caller
    /// steps the reference (the reference does not depend on the plant, so it may run
    /// ahead elsewhere: [`ClosedLoop::drive_ahead`]). The same arithmetic as `tick`.
    #[inline]
    fn tick_given(&mut self, rd: &ReferenceState) -> TraceRow {
        let k = self.tick;
        let t = k as f64 * self.dt;
        let x = self.plant.state();
        let out = match self.open_loop {
            None => self.law.step(&x, rd, self.dt),
            Some(u) => ControlOutput { rotor_torque: u, ..ControlOutput::default() },
        };
        // The motors deliver what their limits allow (the trace keeps the command).
        let input = BodyInput::of(self.actuation, out.rotor_torque, out.body_torque);
        // The rotor torque commanded: none for a gas-jet body.
        let u_traced = input.rotor_torque;
        let mut row = self.metrics.observe_work(k, t, &x, rd, u_traced, out.body_torque, self.work);
        let drawn = self.drawn.as_mut().map(DrawnDelays::draw);
        self.line.arrive(k, input, k, 0.0, 0, drawn);
        let step =
            integrate_tick(&mut self.plant, &mut self.line, k, &self.limits, self.disturbance);
        self.work = step.work;
        self.saturated_ticks += u64::from(step.saturated);
        if k < self.last {
            row.delay_s = step.effects.first_delay_s(k, self.dt);
        }
        self.tick += 1;
        row
    }

    /// Ticks from the next one to `last` (inclusive), calling `each` with every row, as
    /// many calls of [`ClosedLoop::tick`] would, but with the reference stepped ahead on a
    /// thread of its own: it depends on nothing the loop does, and it is 40 % of a tick.
    /// Its samples come in blocks of [`AHEAD_BLOCK`] through bounded channels, the blocks
    /// made once and handed back (no allocation a tick). Every number is what `tick` makes,
    /// bit for bit (the same operations on the same values, in another thread). An error
    /// of `each` stops the loop there, with the reference where the ticks done left it.
    pub fn drive_ahead<E>(
        &mut self,
        last: u64,
        mut each: impl FnMut(&mut Self, TraceRow) -> Result<(), E>,
    ) -> Result<(), E> {
        use std::sync::mpsc::sync_channel;
        let (start, dt, mut reference) = (self.tick, self.dt, self.reference);
        let (full_tx, full_rx) = sync_channel::<Vec<ReferenceState>>(AHEAD_BLOCKS);
        let (empty_tx, empty_rx) = sync_channel::<Vec<ReferenceState>>(AHEAD_BLOCKS);
        for _ in 0..AHEAD_BLOCKS {
            empty_tx.send(Vec::with_capacity(AHEAD_BLOCK)).expect("the receiver is here");
        }
        std::thread::scope(|scope| {
            let ahead = scope.spawn(move || {
                let mut k = start;
                while k <= last {
                    let Ok(mut block) = empty_rx.recv() else { break };
                    block.clear();
                    while block.len() < AHEAD_BLOCK && k <= last {
                        let t = k as f64 * dt;
                        block.push(reference.sample(t));
                        reference.step(t, dt);
                        k += 1;
                    }
                    if full_tx.send(block).is_err() {
                        break;
                    }
                }
                reference
            });
            let mut done = Ok(());
            'blocks: for block in full_rx.iter() {
                for rd in &block {
                    let row = self.tick_given(rd);
                    done = each(self, row);
                    if done.is_err() {
                        break 'blocks;
                    }
                }
                // The thread may have stopped: the block is then not needed.
                let _ = empty_tx.send(block);
            }
            drop((full_rx, empty_tx));
            let ahead = ahead.join().unwrap_or_else(|p| std::panic::resume_unwind(p));
            if done.is_ok() {
                self.reference = ahead;
            } else {
                // Stopped early: the reference as the ticks done (`start..self.tick`) left it.
                for k in start..self.tick {
                    self.reference.step(k as f64 * dt, dt);
                }
            }
            done
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paper() -> ClosedLoop {
        let s = Scenario::load("paper-sinusoid").expect("builtin");
        ClosedLoop::new(&s, s.actuation(), None).expect("the default law")
    }

    fn bits(row: &TraceRow) -> Vec<u64> {
        let mut v = vec![row.tick];
        let arrays = [&row.r[..], &row.r_d, &row.omega, &row.omega_d, &row.omega_r, &row.u, &row.h];
        v.extend(arrays.iter().flat_map(|a| a.iter().map(|x| x.to_bits())));
        let scalars = [row.t, row.err_deg, row.werr, row.h_drift_rel, row.energy_residual];
        v.extend(scalars.iter().chain([&row.delay_s]).map(|x| x.to_bits()));
        v
    }

    /// The reference stepped ahead on its own thread gives every row, and leaves the plant
    /// and the reference, bit for bit as ticking one by one does: over several blocks, a
    /// last block cut short, and a second drive continuing the first.
    #[test]
    fn the_reference_ahead_changes_no_bit() {
        let (mut one, mut ahead) = (paper(), paper());
        let mut want = Vec::new();
        for _ in 0..=3 * AHEAD_BLOCK + 17 {
            want.push(bits(&one.tick()));
        }
        let mut got = Vec::new();
        ahead
            .drive_ahead(2 * AHEAD_BLOCK as u64, |_, row| {
                got.push(bits(&row));
                Ok::<(), ()>(())
            })
            .expect("no error");
        ahead
            .drive_ahead(3 * AHEAD_BLOCK as u64 + 17, |_, row| {
                got.push(bits(&row));
                Ok::<(), ()>(())
            })
            .expect("no error");
        assert_eq!(got, want);
        assert_eq!(ahead.plant().internal(), one.plant().internal());
        assert_eq!(ahead.reference().internal(), one.reference().internal());
    }

    /// An error stops the loop at its row, and the reference is where the ticks done left
    /// it (the thread had run ahead).
    #[test]
    fn an_error_leaves_the_reference_of_the_ticks_done() {
        let (mut one, mut ahead) = (paper(), paper());
        let stop = AHEAD_BLOCK as u64 + 5;
        for _ in 0..=stop {
            one.tick();
        }
        let mut rows = 0;
        let r = ahead.drive_ahead(4 * AHEAD_BLOCK as u64, |_, row| {
            rows += 1;
            if row.tick == stop { Err(row.tick) } else { Ok(()) }
        });
        assert_eq!((r, rows), (Err(stop), stop + 1));
        assert_eq!(ahead.tick_index(), one.tick_index());
        assert_eq!(ahead.reference().internal(), one.reference().internal());
        assert_eq!(ahead.tick().t.to_bits(), one.tick().t.to_bits());
    }
}
