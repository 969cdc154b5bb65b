//! Speed of the in-process loop and of the controller's own work per tick, the figures
//! docs/measurements.md says they must hold ("In-process speed"):
//!
//! - `loop`: open-loop plant steps per second; closed-loop ticks per second (plant +
//!   reference + law + metrics); and `sim_loop`, the ticks as `rotorloop sim` drives them
//!   (its statistics, the figures' recorder, the trace's decimation), without the file:
//!   the simulator's speed, which lost 11 % once without anyone seeing it; with the
//!   reference ahead on a second thread (as `sim` runs) and on the loop's
//!   (`sim_loop_one_thread`, `sim --one-thread`).
//! - `controller_stages`: per state, the work of the controller's stages without their
//!   clock reads and IPC: validation (the answer rule and the state's checks), pairing
//!   with the reference (with its taking, and the taking alone: the loop takes the
//!   references after each publish), the law, and the publish preparation (resume record
//!   into its slot, the delay queue).

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::DVec3;
use rotorloop::sim::closed_loop::ClosedLoop;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::scenario::{Actuation, Scenario};
use rotorloop_common::wire::{ReferenceSample, StateSample, TorqueSample};
use rotorloop_controller::policy::{
    ControllerResume, DelayedSends, ReferencePairing, TorqueAnswers,
};
use rotorloop_plant::{Body, BodyInput};
use rotorloop_reference::policy::LeadWindow;

const BATCH: u64 = 10_000;

fn ticks(c: &mut Criterion) {
    let s = Scenario::load("paper-sinusoid").expect("builtin scenario");
    let mut g = c.benchmark_group("loop");
    g.throughput(Throughput::Elements(BATCH));

    g.bench_function("plant_step_open_loop", |b| {
        let mut body = Body::new(s.plant, s.plant_init);
        let input =
            BodyInput { rotor_torque: DVec3::new(0.1, -0.2, 0.05), body_torque: DVec3::ZERO };
        b.iter(|| {
            for _ in 0..BATCH {
                body.step(black_box(input), black_box(1e-3));
            }
            black_box(body.state())
        });
    });

    for (name, actuation) in [
        ("closed_loop_tick_internal", Actuation::Internal),
        ("closed_loop_tick_external", Actuation::External),
    ] {
        g.bench_function(name, |b| {
            let mut lp = ClosedLoop::new(&s, actuation, None).expect("the default law");
            b.iter(|| {
                let mut acc = 0.0;
                for _ in 0..BATCH {
                    acc += lp.tick().err_deg;
                }
                black_box(acc)
            });
        });
    }
    for (name, one_thread) in [("sim_loop", false), ("sim_loop_one_thread", true)] {
        g.bench_function(name, |b| {
            b.iter_batched(
                || ClosedLoop::new(&s, Actuation::Internal, None).expect("the default law"),
                |mut lp| rotorloop::sim::drive_unwritten(&mut lp, BATCH - 1, 100_000, one_thread),
                criterion::BatchSize::LargeInput,
            );
        });
    }
    g.finish();
}

/// The states and references of the first `BATCH` ticks of the paper's run, as the plant
/// and the reference publish them.
fn samples(s: &Scenario) -> (Vec<StateSample>, Vec<ReferenceSample>) {
    let mut lp = ClosedLoop::new(s, s.actuation(), None).expect("the default law");
    let mut lead = LeadWindow::new(s);
    let (mut states, mut refs) = (Vec::new(), Vec::new());
    for k in 0..BATCH {
        states.push(StateSample::of(k, k as f64 * s.dt(), &lp.plant().state()));
        lead.saw_state(k);
        refs.extend(std::iter::from_fn(|| lead.next_due()));
        lp.tick();
    }
    (states, refs)
}

/// The controller's stages per state, their work alone (no clock read, no IPC): what
/// `summary.json`'s `controller_validate`, `controller_pair`, `controller_law` and
/// `controller_publish_prep` measure in a run, less the stamps and the sample's loan.
fn controller_stages(c: &mut Criterion) {
    let s = Scenario::load("paper-sinusoid").expect("builtin scenario");
    let (states, refs) = samples(&s);
    let dt = s.dt();
    let mut g = c.benchmark_group("controller_stages");
    g.throughput(Throughput::Elements(BATCH));
    g.bench_function("validate", |b| {
        let mut answers = TorqueAnswers::for_scenario(&s).expect("the default law");
        b.iter(|| {
            for st in &states {
                black_box(answers.decide(black_box(st)));
            }
        });
    });
    g.bench_function("pair", |b| {
        b.iter_batched_ref(
            || ReferencePairing::new(50, dt, BATCH),
            |pairing| {
                let mut refs = refs.iter().peekable();
                for k in 0..BATCH {
                    while let Some(r) = refs.next_if(|r| r.tick <= k + 4) {
                        pairing.take(*r, || None);
                    }
                    let rd = pairing.pair(k, true, false, |_| Ok(false));
                    black_box(rd.expect("no wait to fail").expect("the tick's own reference"));
                }
            },
            criterion::BatchSize::SmallInput,
        );
    });
    // The references' own checks as they are taken (after the previous publish, off the
    // path from a state to its answer): "pair" less this is the pairing's own work.
    g.bench_function("reference_take", |b| {
        b.iter_batched_ref(
            || ReferencePairing::new(50, dt, BATCH),
            |pairing| {
                for r in &refs {
                    pairing.take(*r, || None);
                }
            },
            criterion::BatchSize::SmallInput,
        );
    });
    let rds: Vec<_> = refs.iter().map(|r| r.reference_state()).collect();
    let pairing = ReferencePairing::new(50, dt, BATCH);
    g.bench_function("law", |b| {
        b.iter_batched_ref(
            || TorqueAnswers::for_scenario(&s).expect("the default law"),
            |answers| {
                for (st, rd) in states.iter().zip(&rds) {
                    black_box(answers.answer(st, 0, Some(rd), &pairing, dt));
                }
            },
            criterion::BatchSize::SmallInput,
        );
    });
    let domain = Domain::new(&format!("bench-stages-{}", std::process::id())).expect("domain");
    let slot: ResumeSlot<ControllerResume> = ResumeSlot::open(&domain, "bench-prep").expect("slot");
    let answers = TorqueAnswers::for_scenario(&s).expect("the default law");
    let torques: Vec<TorqueSample> =
        states.iter().map(|st| TorqueSample { tick: st.tick, ..Default::default() }).collect();
    g.bench_function("publish_prep", |b| {
        let mut sends = DelayedSends::new(Vec::new());
        b.iter(|| {
            for (t, st) in torques.iter().zip(&states) {
                // The answer is in the slot's copy already (written by the law's stage).
                slot.store_with(|r| answers.write_law_state(r));
                black_box(sends.holds_back(black_box(t), st.t_s, 0));
            }
        });
    });
    g.finish();
    rotorloop_common::resume::remove_slots(&domain);
}

/// The controller's resume-slot write per tick: its last answer alone (what the slot kept
/// before the law's state left the wire) against `ControllerResume` (the answer and the
/// law's state, what it keeps now), both into a real slot in /dev/shm.
fn resume_slot(c: &mut Criterion) {
    let s = Scenario::load("paper-sinusoid").expect("builtin scenario");
    let domain = Domain::new(&format!("bench-slot-{}", std::process::id())).expect("domain");
    let answers = TorqueAnswers::for_scenario(&s).expect("the default law");
    let answer = TorqueSample::default();
    let mut g = c.benchmark_group("resume_slot");
    g.throughput(Throughput::Elements(BATCH));
    let before: ResumeSlot<TorqueSample> = ResumeSlot::open(&domain, "bench-answer").expect("slot");
    g.bench_function("store_answer_only", |b| {
        b.iter(|| {
            for _ in 0..BATCH {
                before.store(black_box(&answer));
            }
        });
    });
    let after: ResumeSlot<ControllerResume> =
        ResumeSlot::open(&domain, "bench-resume").expect("slot");
    g.bench_function("store_answer_and_law_state", |b| {
        b.iter(|| {
            for _ in 0..BATCH {
                after.store_with(|r| answers.write_resume_record(r, black_box(&answer)));
            }
        });
    });
    g.finish();
    rotorloop_common::resume::remove_slots(&domain);
}

criterion_group!(benches, ticks, controller_stages, resume_slot);
criterion_main!(benches);
