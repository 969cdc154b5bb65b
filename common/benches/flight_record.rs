//! What one flight record costs the role that writes it, on the disk and on tmpfs: the
//! time of `FlightRecorder::record` per tick (p50, p99, p99.9, max) and the page faults
//! of 60 000 records, with one writeback of the whole machine halfway (what the kernel's
//! writeback does to a dirty page of the mapping: cleans it and write-protects it, so the
//! next record takes a fault). A measurement, not a test: `cargo bench -p
//! rotorloop-common --bench flight_record`.

use std::path::Path;

use rotorloop_common::flight::{FlightRecorder, Stream};
use rotorloop_common::params::RotorBodyState;
use rotorloop_common::wire::StateSample;

/// Records per directory.
const TICKS: u64 = 60_000;

fn page_faults() -> i64 {
    // SAFETY: rusage is plain data; getrusage fills it.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: a valid pointer to the struct above.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    u.ru_minflt + u.ru_majflt
}

/// The cost of each of [`TICKS`] records into a recorder in `dir`, printed.
fn measure(dir: &Path) {
    let r = FlightRecorder::<StateSample>::open(Some(dir), Stream::PlantState, TICKS, "cost");
    assert!(r.capacity() > 0, "cannot record into {}", dir.display());
    let x = RotorBodyState {
        r: glam::DMat3::IDENTITY,
        omega: glam::DVec3::ZERO,
        omega_r: glam::DVec3::ZERO,
        theta: glam::DVec3::ZERO,
    };
    let mut s = StateSample::of(0, 0.0, &x);
    let f0 = page_faults();
    let mut ns = Vec::with_capacity(TICKS as usize);
    for k in 0..TICKS {
        if k == TICKS / 2 {
            // SAFETY: sync takes no arguments; it writes back every dirty page.
            unsafe { libc::sync() };
        }
        s.tick = k;
        let t = rotorloop_common::clock::now_ns();
        r.record(&s);
        ns.push(rotorloop_common::clock::now_ns() - t);
    }
    ns.sort_unstable();
    let q = |p: f64| ns[((ns.len() - 1) as f64 * p) as usize];
    println!(
        "{}: p50 {} ns, p99 {} ns, p99.9 {} ns, max {} ns, page faults {}",
        dir.display(),
        q(0.5),
        q(0.99),
        q(0.999),
        q(1.0),
        page_faults() - f0
    );
}

fn main() {
    for base in [std::env::temp_dir(), std::path::PathBuf::from("/dev/shm")] {
        let dir = base.join(format!("rotorloop-flight-cost-{}", std::process::id()));
        measure(&dir);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
