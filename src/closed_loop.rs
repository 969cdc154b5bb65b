//! The closed loop in one process: plant, reference, control law and metrics, stepped
//! together. The same algorithm structs run in the four-process loop; this is the
//! in-process simulator's core and the unit the benchmark measures.

use glam::DVec3;
use rotorloop_common::{Actuation, ActuatorLimits, Scenario};
use rotorloop_controller::{ControlOutput, GeometricPid};
use rotorloop_monitor::{Metrics, TraceRow};
use rotorloop_plant::{Body, BodyInput};
use rotorloop_reference::Reference;

/// Plant + reference + controller + metrics at a fixed tick.
#[derive(Debug, Clone)]
pub struct ClosedLoop {
    plant: Body,
    reference: Reference,
    pid: GeometricPid,
    /// The controller switched off and this rotor torque held (N m): for checking the
    /// physics against other simulators.
    open_loop: Option<DVec3>,
    metrics: Metrics,
    actuation: Actuation,
    limits: ActuatorLimits,
    disturbance: DVec3,
    dt: f64,
    tick: u64,
    held: DVec3,
    saturated_ticks: u64,
}

impl ClosedLoop {
    /// The loop of a validated scenario. The reference is momentum-matched to the
    /// rotor-actuated plant in both actuations, so an internal and an external run track
    /// the same reference. `open_loop` replaces the controller by a constant rotor torque.
    pub fn new(scenario: &Scenario, actuation: Actuation, open_loop: Option<DVec3>) -> Self {
        let reference = Reference::for_scenario(scenario);
        let body = scenario.plant_params(actuation);
        let plant = Body::new(body, scenario.plant_init);
        let limits = scenario.limits_for(actuation);
        let pid = GeometricPid::new(scenario.gains, scenario.controller_params(actuation))
            .with_limits(limits, scenario.anti_windup);
        let metrics = Metrics::new(body, &plant.state()).with_disturbance(scenario.disturbance);
        Self {
            plant,
            reference,
            pid,
            open_loop,
            metrics,
            actuation,
            limits,
            disturbance: scenario.disturbance,
            dt: scenario.dt(),
            tick: 0,
            held: DVec3::ZERO,
            saturated_ticks: 0,
        }
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
    /// record the row, then advance plant (torque held) and reference to `t_k+1`.
    /// Allocation-free.
    #[inline]
    pub fn tick(&mut self) -> TraceRow {
        let k = self.tick;
        let t = k as f64 * self.dt;
        let x = self.plant.state();
        let rd = self.reference.sample(t);
        let out = match self.open_loop {
            None => self.pid.step(&x, &rd, self.dt),
            Some(u) => ControlOutput { rotor_torque: u, ..ControlOutput::default() },
        };
        let (input, u_traced) = match self.actuation {
            Actuation::Internal => {
                // The motors deliver what their limits allow (the trace keeps the command).
                let (u, saturated) = self.limits.apply(out.rotor_torque, x.omega_r);
                self.saturated_ticks += u64::from(saturated);
                (BodyInput { rotor_torque: u, body_torque: self.disturbance }, out.rotor_torque)
            }
            Actuation::External => (
                BodyInput {
                    rotor_torque: DVec3::ZERO,
                    body_torque: out.body_torque + self.disturbance,
                },
                DVec3::ZERO,
            ),
        };
        let row = self.metrics.observe(k, t, &x, &rd, u_traced, out.body_torque, self.held);
        self.held = input.rotor_torque;
        self.plant.step(input, self.dt);
        self.reference.step(t, self.dt);
        self.tick += 1;
        row
    }
}
