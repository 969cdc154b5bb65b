//! The closed loop in one process: plant, reference, control law and metrics, stepped
//! together. The same algorithm structs run in the four-process loop; this is the
//! in-process simulator's core and the unit the benchmark measures.

use glam::DVec3;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rotorloop_common::params::ActuatorLimits;
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
        let k = self.tick;
        let t = k as f64 * self.dt;
        let x = self.plant.state();
        let rd = self.reference.sample(t);
        let out = match self.open_loop {
            None => self.law.step(&x, &rd, self.dt),
            Some(u) => ControlOutput { rotor_torque: u, ..ControlOutput::default() },
        };
        // The motors deliver what their limits allow (the trace keeps the command).
        let input = BodyInput::of(self.actuation, out.rotor_torque, out.body_torque);
        // The rotor torque commanded: none for a gas-jet body.
        let u_traced = input.rotor_torque;
        let mut row =
            self.metrics.observe_work(k, t, &x, &rd, u_traced, out.body_torque, self.work);
        let drawn = self.drawn.as_mut().map(DrawnDelays::draw);
        self.line.arrive(k, input, k, 0.0, 0, drawn);
        let step =
            integrate_tick(&mut self.plant, &mut self.line, k, &self.limits, self.disturbance);
        self.work = step.work;
        self.saturated_ticks += u64::from(step.saturated);
        if k < self.last {
            row.delay_s = step.effects.first_delay_s(k, self.dt);
        }
        self.reference.step(t, self.dt);
        self.tick += 1;
        row
    }
}
