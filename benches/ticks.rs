//! Speed of the in-process loop: open-loop plant steps per second, and closed-loop ticks
//! per second (plant + reference + controller + metrics, no trace I/O). The target is
//! 1,000,000 closed-loop ticks/s single-threaded in release mode.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::DVec3;
use rotorloop::sim::closed_loop::ClosedLoop;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::scenario::{Actuation, Scenario};
use rotorloop_common::wire::TorqueSample;
use rotorloop_controller::policy::{ControllerResume, TorqueAnswers};
use rotorloop_plant::{Body, BodyInput};

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
    g.finish();
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
                after.store(&answers.resume_record(black_box(&answer)));
            }
        });
    });
    g.finish();
    rotorloop_common::resume::remove_slots(&domain);
}

criterion_group!(benches, ticks, resume_slot);
criterion_main!(benches);
