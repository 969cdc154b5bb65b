//! The actuator model (spec, "Actuation delay"): the delayed zero-order hold and one
//! tick's piecewise integration through the actuator limits, shared by the plant process
//! and the in-process simulator (and its replay).
//!
//! - [`DelayLine`]: each accepted torque takes effect at an instant inside some tick and
//!   stays in force until the next takes effect. [`ActuationDelay`] says when: at the start
//!   of the tick it arrives in (`Instant`, the zero-order hold of earlier versions), `d`
//!   after its own tick's time but never before it arrived (`Fixed(d)`, any length: a
//!   queue), or when it arrives (`Measured`, real time). With every effect at offset 0
//!   there is one piece of length `dt`: the numbers are those of the plain zero-order
//!   hold, bit for bit.
//! - [`integrate_tick`]: one RKMK4 step per piece, split exactly at those instants, each
//!   through the actuator limits at the rotor rates at the piece's start, with the
//!   scenario's body disturbance; it returns the rotor work and what took effect
//!   ([`TickOutcome`], [`Effects`]).

use std::collections::VecDeque;

use glam::DVec3;
use rotorloop_common::params::ActuatorLimits;
use rotorloop_common::wire::{MAX_EFFECTS, NO_TICK};

use crate::{Body, BodyInput};

/// When an accepted torque takes effect (module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ActuationDelay {
    /// At the start of the tick it arrives in: the zero-order hold of earlier versions
    /// (`--actuation-delay 0` in real time).
    Instant,
    /// `d` seconds after its own tick's time, and not before it arrives (any length).
    Fixed(f64),
    /// When it arrives (real time; in lockstep a torque arrives at its own tick's time).
    Measured,
}

impl std::str::FromStr for ActuationDelay {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "measured" => Ok(Self::Measured),
            _ => match s.parse::<f64>() {
                Ok(0.0) => Ok(Self::Instant),
                Ok(d) if d.is_finite() && d > 0.0 && d <= 3600.0 => Ok(Self::Fixed(d)),
                _ => Err(format!(
                    "`{s}` is not allowed: `measured`, or seconds from 0 to 3600 (0: at the start of the tick it arrives in)"
                )),
            },
        }
    }
}

impl std::fmt::Display for ActuationDelay {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Instant => f.write_str("0"),
            Self::Fixed(d) => write!(f, "{d}"),
            Self::Measured => f.write_str("measured"),
        }
    }
}

/// A torque waiting to take effect: in tick `tick`, `offset_s` after its start.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Pending {
    tick: u64,
    offset_s: f64,
    source: u64,
    input: BodyInput,
    recv_ns: u64,
}

/// The torques that took effect in one tick (the first [`MAX_EFFECTS`], and how many).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Effects {
    /// How many took effect.
    pub count: u64,
    /// Their torque ticks.
    pub ticks: [u64; MAX_EFFECTS],
    /// Their offsets from the tick's start (s).
    pub offsets_s: [f64; MAX_EFFECTS],
}

impl Default for Effects {
    fn default() -> Self {
        Self { count: 0, ticks: [NO_TICK; MAX_EFFECTS], offsets_s: [f64::NAN; MAX_EFFECTS] }
    }
}

impl Effects {
    /// The actuation delay of the first of them, which took effect in tick `k` (s); NaN
    /// when none did.
    pub fn first_delay_s(&self, k: u64, dt: f64) -> f64 {
        match self.count {
            0 => f64::NAN,
            _ => rotorloop_common::wire::effect_delay_s(k, self.ticks[0], self.offsets_s[0], dt),
        }
    }

    fn push(&mut self, source: u64, offset_s: f64) {
        if let Some(i) = (self.count < MAX_EFFECTS as u64).then_some(self.count as usize) {
            (self.ticks[i], self.offsets_s[i]) = (source, offset_s);
        }
        self.count += 1;
    }
}

/// The delayed zero-order hold (module docs): the torque in force and those waiting.
#[derive(Debug, Clone)]
pub struct DelayLine {
    delay: ActuationDelay,
    dt: f64,
    queue: VecDeque<Pending>,
    in_force: BodyInput,
    in_force_tick: u64,
    in_force_recv_ns: u64,
}

impl DelayLine {
    /// An empty line (zero torque in force) for ticks of `dt`. Room for the whole queue a
    /// fixed delay makes is reserved now: nothing allocates per tick.
    pub fn new(delay: ActuationDelay, dt: f64) -> Self {
        let room = match delay {
            ActuationDelay::Fixed(d) => (d / dt).ceil() as usize + 8,
            _ => 8,
        };
        Self {
            delay,
            dt,
            queue: VecDeque::with_capacity(room),
            in_force: BodyInput::default(),
            in_force_tick: NO_TICK,
            in_force_recv_ns: 0,
        }
    }

    /// The torque of tick `source` arrived during tick `now`, `arrived_s` after its start
    /// (0 in lockstep and in process), at `recv_ns`: it is queued to take effect by the
    /// rule. A [`ActuationDelay::Fixed`] delay is counted from the source tick's time; for
    /// a given delay `d` a caller may pass `Some(d)` to override the rule for this torque
    /// (a delay drawn from a distribution, or replayed).
    pub fn arrive(
        &mut self,
        source: u64,
        input: BodyInput,
        now: u64,
        arrived_s: f64,
        recv_ns: u64,
        d: Option<f64>,
    ) {
        // An arrival at (or rounded past) the tick's end belongs to the next tick.
        let arrived = if arrived_s >= self.dt { (now + 1, 0.0) } else { (now, arrived_s.max(0.0)) };
        let scheduled = |d: f64| {
            let whole = (d / self.dt).floor();
            (source + whole as u64, d - whole * self.dt)
        };
        let (tick, offset_s) = match (d, self.delay) {
            (Some(d), _) | (None, ActuationDelay::Fixed(d)) => {
                let s = scheduled(d);
                if s.0 > arrived.0 || (s.0 == arrived.0 && s.1 >= arrived.1) { s } else { arrived }
            }
            (None, ActuationDelay::Instant) => (now, 0.0),
            (None, ActuationDelay::Measured) => arrived,
        };
        // A torque that would take effect after this newer one arrives after it: the
        // actuator drops it then (it only ever takes a command newer than its own).
        while self.queue.back().is_some_and(|b| (b.tick, b.offset_s) > (tick, offset_s)) {
            self.queue.pop_back();
        }
        self.queue.push_back(Pending { tick, offset_s, source, input, recv_ns });
    }

    /// Queues the torque of tick `source` to take effect in tick `tick`, `offset_s` after
    /// its start, as recorded (a replay).
    pub fn schedule(&mut self, tick: u64, offset_s: f64, source: u64, input: BodyInput) {
        self.queue.push_back(Pending { tick, offset_s, source, input, recv_ns: 0 });
    }

    /// Safe mode: zero torque in force from now, nothing waiting.
    pub fn clear(&mut self) {
        self.queue.clear();
        self.in_force = BodyInput::default();
        self.in_force_tick = NO_TICK;
    }

    /// Continues with `input` of tick `source` (received at `recv_ns`) in force.
    pub fn resume(&mut self, input: BodyInput, source: u64, recv_ns: u64) {
        (self.in_force, self.in_force_tick, self.in_force_recv_ns) = (input, source, recv_ns);
    }

    /// The torque in force now, its tick and when it was received.
    pub fn in_force(&self) -> (BodyInput, u64, u64) {
        (self.in_force, self.in_force_tick, self.in_force_recv_ns)
    }

    /// Integrates tick `k` piecewise: `step(input, h)` for each piece in order (the
    /// input in force on it, its length), and returns the torques that took effect.
    pub fn pieces(&mut self, k: u64, mut step: impl FnMut(BodyInput, f64)) -> Effects {
        let mut effects = Effects::default();
        let mut at = 0.0;
        while let Some(p) = self.queue.front().copied().filter(|p| p.tick <= k) {
            self.queue.pop_front();
            let offset = if p.tick < k { 0.0 } else { p.offset_s };
            if offset > at {
                step(self.in_force, offset - at);
                at = offset;
            }
            (self.in_force, self.in_force_tick, self.in_force_recv_ns) =
                (p.input, p.source, p.recv_ns);
            effects.push(p.source, offset);
        }
        if self.dt > at {
            step(self.in_force, self.dt - at);
        }
        effects
    }
}

/// What one tick's piecewise integration did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TickOutcome {
    /// Rotor work over the tick (J): the sum over pieces of `u · ΔΘ`.
    pub work: f64,
    /// The actuator limits changed the torque on some piece.
    pub saturated: bool,
    /// What the motors delivered on the last piece (after their limits).
    pub applied: BodyInput,
    /// The torques that took effect, and when.
    pub effects: Effects,
}

/// Integrates tick `k` of `body` piecewise with the torques of `line` (module docs): each
/// piece through the actuator `limits` at the rotor rates at its start, with the body
/// disturbance added. The plant process and the in-process simulator both step with this.
pub fn integrate_tick(
    body: &mut Body,
    line: &mut DelayLine,
    k: u64,
    limits: &ActuatorLimits,
    disturbance: DVec3,
) -> TickOutcome {
    let (mut work, mut saturated) = (0.0, false);
    let mut applied = BodyInput::default();
    let effects = line.pieces(k, |held, h| {
        let x = body.state();
        let (u, sat) = limits.apply(held.rotor_torque, x.omega_r);
        saturated |= sat;
        applied = BodyInput { rotor_torque: u, body_torque: held.body_torque };
        body.step(BodyInput { rotor_torque: u, body_torque: held.body_torque + disturbance }, h);
        work += u.dot(body.theta - x.theta);
    });
    TickOutcome { work, saturated, applied, effects }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plant catching up after a stall sees several torques take effect in one tick;
    /// each is recorded with its offset (what a replay needs), up to [`MAX_EFFECTS`], and
    /// all are counted.
    #[test]
    fn every_torque_that_takes_effect_in_a_tick_is_recorded_up_to_max_effects() {
        let mut e = Effects::default();
        for (i, source) in (866..866 + MAX_EFFECTS as u64 + 2).enumerate() {
            e.push(source, i as f64 * 1e-5);
        }
        assert_eq!(e.count, MAX_EFFECTS as u64 + 2);
        const { assert!(MAX_EFFECTS >= 4, "four in one tick were seen under CI load") };
        for i in 0..MAX_EFFECTS {
            assert_eq!((e.ticks[i], e.offsets_s[i]), (866 + i as u64, i as f64 * 1e-5));
        }
    }

    const DT: f64 = 1e-3;

    /// Lengths and rotor torques of the pieces of tick `k`.
    fn pieces(line: &mut DelayLine, k: u64) -> (Vec<(f64, f64)>, Effects) {
        let mut v = Vec::new();
        let e = line.pieces(k, |i, h| v.push((h, i.rotor_torque.x)));
        (v, e)
    }

    fn input(u: f64) -> BodyInput {
        BodyInput { rotor_torque: DVec3::new(u, 0.0, 0.0), body_torque: DVec3::ZERO }
    }

    #[test]
    fn no_torque_is_in_force_before_the_first_arrives() {
        let mut line = DelayLine::new(ActuationDelay::Measured, DT);
        assert_eq!(line.in_force(), (BodyInput::default(), NO_TICK, 0));
        assert_eq!(pieces(&mut line, 0).0, [(DT, 0.0)]);
    }

    #[test]
    fn zero_delay_is_one_piece_of_a_whole_tick() {
        for delay in [ActuationDelay::Instant, ActuationDelay::Measured, ActuationDelay::Fixed(0.0)]
        {
            let mut line = DelayLine::new(delay, DT);
            line.arrive(3, input(1.5), 3, 0.0, 0, None);
            let (p, e) = pieces(&mut line, 3);
            assert_eq!(p, [(DT, 1.5)], "{delay:?}");
            assert_eq!((e.count, e.ticks[0], e.offsets_s[0]), (1, 3, 0.0));
        }
    }

    #[test]
    fn a_delay_inside_the_tick_splits_it_at_the_arrival() {
        let mut line = DelayLine::new(ActuationDelay::Fixed(3e-4), DT);
        line.arrive(0, input(1.0), 0, 0.0, 0, None);
        assert_eq!(pieces(&mut line, 0).0, [(3e-4, 0.0), (DT - 3e-4, 1.0)]);
        // Measured: where it arrived, 0.4 ms into the tick.
        let mut m = DelayLine::new(ActuationDelay::Measured, DT);
        m.arrive(0, input(1.0), 0, 4e-4, 0, None);
        m.arrive(0, input(9.0), 0, 2e-4, 0, None); // cannot overtake: dropped as older
        assert_eq!(pieces(&mut m, 0).0, [(2e-4, 0.0), (DT - 2e-4, 9.0)]);
        // Instant ignores where in the tick it arrived.
        let mut i = DelayLine::new(ActuationDelay::Instant, DT);
        i.arrive(0, input(1.0), 0, 4e-4, 0, None);
        assert_eq!(pieces(&mut i, 0).0, [(DT, 1.0)]);
    }

    #[test]
    fn a_delay_longer_than_a_tick_is_a_queue() {
        let mut line = DelayLine::new(ActuationDelay::Fixed(2.5e-3), DT);
        for k in 0..6 {
            line.arrive(k, input(k as f64 + 1.0), k, 0.0, 0, None);
            let (p, e) = pieces(&mut line, k);
            if k < 2 {
                assert_eq!(
                    (p.as_slice(), e.count),
                    ([(DT, 0.0)].as_slice(), 0),
                    "tick {k}: nothing yet"
                );
            } else {
                // Torque k − 2 takes effect half way through tick k.
                assert_eq!(e.ticks[0], k - 2);
                assert!((e.offsets_s[0] - 5e-4).abs() < 1e-15);
                assert_eq!(p.len(), 2);
                assert!((p[0].0 + p[1].0 - DT).abs() < 1e-18 && p[1].1 == (k - 1) as f64);
            }
        }
    }

    #[test]
    fn a_fixed_delay_never_applies_a_torque_before_it_arrives() {
        let mut line = DelayLine::new(ActuationDelay::Fixed(1e-4), DT);
        line.arrive(0, input(1.0), 0, 6e-4, 0, None); // arrived later than t_0 + d
        assert_eq!(pieces(&mut line, 0).0, [(6e-4, 0.0), (DT - 6e-4, 1.0)]);
    }
}
