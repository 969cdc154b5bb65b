//! What an incident cost the control: the run against the loop that had no incident.
//!
//! From the incident's first tick, the same plant (its integrator's exact state, from the
//! state sample), the same law state (the law run in process over every answer the
//! controller computed before it; checked against the recorded answers bit for bit) and
//! the same reference samples (an answer that tracked an earlier reference propagated,
//! the reference of its own tick being late, tracks it again) are stepped again in
//! process. Every tick of the incident
//! that was abnormal becomes an undisturbed one: the answer to its own state takes effect
//! at the run's median actuation delay. Every other tick, within the incident or after it,
//! does what the run did: the same sources take effect at the same offsets (a held torque
//! stays held, a later incident happens again), but each source is this loop's own answer
//! to its own state. Where nothing was abnormal (a monitor killed) the counterfactual is
//! the run itself, and the deviation is exactly zero.
//!
//! The cost is the peak attitude deviation between the run and the counterfactual, the
//! angle of `R_run R_cfᵀ` (from `‖R_run − R_cf‖_F = 2√2 sin(θ/2)`, exact at zero and
//! accurate for small angles), and the time from the incident's start until the deviation
//! falls below 10 % of its peak after it.

use std::collections::BTreeMap;

use glam::DVec3;
use rotorloop_common::params::ReferenceState;
use rotorloop_common::wire::{FLAG_SAFE_MODE, StateSample};
use rotorloop_controller::law::{AnyLaw, Law};
use rotorloop_controller::policy::propagate;
use rotorloop_plant::actuator::{ActuationDelay, DelayLine, integrate_tick};
use rotorloop_plant::{Body, BodyInput};

use super::load::{RunRecord, Spans};
use super::ticks::{LOOP, TickFlags};

/// How long a recovered deviation is watched before the counterfactual stops (s).
const WATCH_AFTER_S: f64 = 1.0;
/// The longest a counterfactual goes on after its incident (s): a deviation not back
/// below a tenth of its peak by then is "not within the run" (an hour's soak would
/// otherwise re-run the rest of the hour for each incident).
const HORIZON_S: f64 = 60.0;
/// How many earlier paired ticks' references are tried for an answer that tracked a
/// propagated one.
const PROPAGATED_TRIES: u64 = 16;
/// The ticks of a deviation kept for the figure.
const CURVE_TICKS: usize = 10_000;
/// This loop's answers kept, the newest (an answer takes effect within its delay; one
/// older than this takes effect as the run's own answer did: what is held does not grow
/// with an incident's length).
const ANSWERS_KEPT: usize = 65_536;

/// An incident's cost.
#[derive(Debug, Clone, PartialEq)]
pub struct Cost {
    /// The peak deviation (deg).
    pub peak_deg: f64,
    /// The tick of the peak.
    pub peak_tick: u64,
    /// From the incident's start until the deviation falls below 10 % of its peak (s);
    /// `None`: not within the run.
    pub recovery_s: Option<f64>,
    /// The deviation, tick by tick from the incident's start (deg; the first
    /// 10 000), for the figure.
    pub curve: Vec<f64>,
    /// The ticks the counterfactual stepped (at most [`most_ticks`]).
    pub ticks: u64,
}

/// The reference an answer tracked: its own tick's, or (its own missing) an earlier one
/// propagated to it (`rotorloop_controller::policy::propagate`).
pub fn reference(run: &RunRecord, k: u64, from: Option<u64>) -> Option<ReferenceState> {
    match from {
        None => run.references.get(k).map(|r| r.reference_state()),
        Some(j) => run.references.get(j).map(|r| propagate(&r, k, run.dt)),
    }
}

/// The law in process over every answer the controller computed.
#[derive(Debug, Clone)]
pub struct LawPass {
    /// The law's state before each of the starts asked for.
    pub before: Vec<AnyLaw>,
    /// For each tick whose answer tracked an earlier reference propagated, that tick.
    pub propagated: BTreeMap<u64, u64>,
    /// Answers the law reproduced bit for bit.
    pub same: u64,
    /// Answers the controller computed.
    pub computed: u64,
}

/// Runs the law over the run's answers, and keeps its state before the start of each of
/// `costed` (the windows to be costed, by ascending first tick). Where an answer differs
/// from the law's with its own tick's reference, the earlier references propagated to it
/// (as the controller does when a reference is late) are tried, and the one that gives the
/// answer bit for bit is taken; which one is kept only for the ticks a counterfactual of
/// `costed` can reach ([`cost`] goes at most 60 s past its window), so what is
/// held does not grow with the run's late references.
///
/// Each tick `0..=last` is handed to `visit` first, as the pass comes to it (for what
/// else is computed a tick at a time: one pass over a day of records, not two).
pub fn law_pass(
    run: &RunRecord,
    costed: &[[u64; 2]],
    visit: &mut dyn FnMut(u64),
) -> anyhow::Result<LawPass> {
    let mut reach = Spans::default();
    costed.iter().for_each(|w| reach.add([w[0], w[0] + most_ticks(*w, run.last, run.dt) - 1]));
    let starts: Vec<u64> = costed.iter().map(|w| w[0]).collect();
    let actuation = run.scenario.actuation();
    let mut law = AnyLaw::for_scenario(&run.scenario, actuation)?;
    let mut pass = LawPass {
        before: Vec::with_capacity(starts.len()),
        propagated: BTreeMap::new(),
        same: 0,
        computed: 0,
    };
    let mut next = starts.iter().peekable();
    let mut paired: Vec<u64> = Vec::new();
    for k in 0..=run.last {
        visit(k);
        while next.next_if(|s| **s <= k).is_some() {
            pass.before.push(law);
        }
        if paired.len() > 2 * PROPAGATED_TRIES as usize {
            paired.drain(..PROPAGATED_TRIES as usize);
        }
        let (Some(t), Some(s)) = (run.torque(k), run.state(k)) else { continue };
        if !t.computed() {
            continue;
        }
        pass.computed += 1;
        let x = s.body_state();
        // The controller propagates the reference of the last tick it paired with its own.
        let tries = std::iter::once(None)
            .chain(paired.iter().rev().take(PROPAGATED_TRIES as usize).map(|j| Some(*j)));
        let mut chosen = None;
        for from in tries {
            let Some(rd) = reference(run, k, from) else { continue };
            let mut l = law;
            if l.step(&x, &rd, run.dt).rotor_torque.to_array() == t.rotor_torque_nm {
                chosen = Some((l, from));
                break;
            }
        }
        match chosen {
            Some((l, from)) => {
                law = l;
                pass.same += 1;
                match from {
                    Some(j) if reach.contains(k) => drop(pass.propagated.insert(k, j)),
                    Some(_) => {}
                    None => paired.push(k),
                }
            }
            None => {
                if let Some(rd) = reference(run, k, None) {
                    law.step(&x, &rd, run.dt);
                    paired.push(k);
                }
            }
        }
    }
    pass.before.extend(next.map(|_| law));
    Ok(pass)
}

/// The most ticks [`cost`] steps for the window `w` of a run whose last tick is `last`:
/// from its start to the run's end, or to a minute (`HORIZON_S`) past the window.
pub fn most_ticks(w: [u64; 2], last: u64, dt: f64) -> u64 {
    let horizon = (HORIZON_S / dt).ceil() as u64 + 1;
    last.min(w[1].saturating_add(horizon)).saturating_sub(w[0]) + 1
}

/// The angle between two attitudes (deg), exactly zero for equal ones.
pub fn deviation_deg(a: &StateSample, b: &Body) -> f64 {
    let d = a.body_state().r - b.state().r;
    let f =
        (d.x_axis.length_squared() + d.y_axis.length_squared() + d.z_axis.length_squared()).sqrt();
    (2.0 * (f / (2.0 * std::f64::consts::SQRT_2)).min(1.0).asin()).to_degrees()
}

/// The cost of the incident `[start, end]` with the law's state `law` before `start`;
/// `disturbed`: whether its abnormal ticks are the incident's (not for a fault outside
/// the loop, whose counterfactual is the run itself).
pub fn cost(
    run: &RunRecord,
    flags: &TickFlags,
    [start, end]: [u64; 2],
    mut law: AnyLaw,
    propagated: &BTreeMap<u64, u64>,
    disturbed: bool,
) -> Option<Cost> {
    let s0 = run.state(start)?;
    let params = run.scenario.plant_params(run.scenario.actuation());
    let [h, p] = [s0.internal_h, s0.internal_p].map(DVec3::from_array);
    let x0 = s0.body_state();
    let mut body = Body::from_internal(params, x0.r, h, p, x0.theta);
    let limits = run.scenario.limits_for(run.scenario.actuation());
    let actuation = run.scenario.actuation();
    let dt = run.dt;
    let mut line = DelayLine::new(ActuationDelay::Instant, dt);
    let held = BodyInput {
        rotor_torque: DVec3::from_array(s0.applied_rotor_torque_nm),
        body_torque: DVec3::from_array(s0.applied_body_torque_nm),
    };
    line.resume(held, s0.applied_torque_tick, 0);
    // This loop's answers by the state tick they answer, in tick order, the newest
    // [`ANSWERS_KEPT`]; before `start`, the run's.
    let mut answers: std::collections::VecDeque<(u64, BodyInput)> = Default::default();
    let recorded = |j: u64| {
        run.torque(j).map(|t| {
            let (u, tau) = (t.rotor_torque_nm, t.body_torque_nm);
            BodyInput::of(actuation, DVec3::from_array(u), DVec3::from_array(tau))
        })
    };
    let delay = flags.median_delay_s.max(0.0);
    let (late_ticks, late_offset) = ((delay / dt).floor() as u64, delay % dt);
    let mut pending: Vec<(u64, f64, u64)> = Vec::new();
    // What takes effect in the tick at hand: one buffer for the whole counterfactual.
    let mut due: Vec<(f64, u64)> = Vec::new();
    let mut curve = Vec::new();
    let (mut peak, mut peak_tick, mut below_since) = (0.0f64, start, None::<u64>);
    // The run's state of the tick at hand: the previous tick's `next`.
    let mut real = run.state(start)?;
    for k in start..=run.last {
        let d = deviation_deg(&real, &body);
        if curve.len() < CURVE_TICKS {
            curve.push(d);
        }
        if d > peak {
            (peak, peak_tick, below_since) = (d, k, None);
        } else if d <= 0.1 * peak {
            below_since.get_or_insert(k);
        } else {
            below_since = None;
        }
        let watched = below_since.is_some_and(|b| (k - b) as f64 * dt > WATCH_AFTER_S);
        let beyond = k.saturating_sub(end) as f64 * dt > HORIZON_S;
        if k == run.last || (k > end && (watched || beyond || (peak == 0.0 && k - end > 1000))) {
            break;
        }
        let next = run.state(k + 1)?;
        let replaced = disturbed && k <= end && flags.get(run, k) & LOOP != 0;
        let real_answer = run.torque(k).is_some_and(|t| t.computed());
        if replaced || real_answer {
            // An undisturbed tick has its own reference; another tracks what the run's did.
            let from = if replaced { None } else { propagated.get(&k).copied() };
            let rd = reference(run, k, from)?;
            let o = law.step(&body.state(), &rd, dt);
            if answers.len() == ANSWERS_KEPT {
                answers.pop_front();
            }
            answers.push_back((k, BodyInput::of(actuation, o.rotor_torque, o.body_torque)));
        }
        due.clear();
        if replaced {
            pending.push((k + late_ticks, late_offset, k));
        } else {
            if next.flags & FLAG_SAFE_MODE != 0 {
                line.clear();
            }
            let n = (next.effects as usize).min(next.effect_ticks.len());
            due.extend((0..n).map(|i| (next.effect_offsets_s[i], next.effect_ticks[i])));
        }
        pending.retain(|(tick, offset, source)| match *tick <= k {
            true => {
                due.push((*offset, *source));
                false
            }
            false => true,
        });
        due.sort_by(|a, b| a.0.total_cmp(&b.0));
        for &(offset, source) in &due {
            let ours = answers.binary_search_by_key(&source, |(j, _)| *j).ok();
            let input = ours.map(|i| answers[i].1).or_else(|| recorded(source))?;
            line.schedule(k, offset, source, input);
        }
        integrate_tick(&mut body, &mut line, k, &limits, run.scenario.disturbance);
        real = next;
    }
    let recovery_s = below_since.filter(|_| peak > 0.0).map(|b| (b - start) as f64 * dt);
    let recovery_s = if peak == 0.0 { Some(0.0) } else { recovery_s };
    let ticks = real.tick + 1 - start;
    Some(Cost { peak_deg: peak, peak_tick, recovery_s, curve, ticks })
}
