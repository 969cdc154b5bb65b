//! Speed of the in-process loop: open-loop plant steps per second, and closed-loop ticks
//! per second (plant + reference + controller + metrics, no trace I/O). The target is
//! 1,000,000 closed-loop ticks/s single-threaded in release mode.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::DVec3;
use rotorloop::sim::closed_loop::ClosedLoop;
use rotorloop_common::scenario::{Actuation, Scenario};
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

criterion_group!(benches, ticks);
criterion_main!(benches);
