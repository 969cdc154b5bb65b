//! The hot path does not allocate: one closed-loop tick (plant step, reference step,
//! control law, metrics) is counted by a global allocator wrapper.
//!
//! Only the test's own thread is counted: libtest's main thread allocates while it waits
//! for the test (CI once saw 4 such allocations land inside the ticks' window).

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicU64, Ordering};

use rotorloop::sim::closed_loop::ClosedLoop;
use rotorloop_common::scenario::{Actuation, Scenario};

struct Counting;

static ALLOCATIONS: AtomicU64 = AtomicU64::new(0);

thread_local! {
    /// Whether this thread's allocations are counted (a const initialiser: reading it
    /// never allocates).
    static COUNTED: Cell<bool> = const { Cell::new(false) };
}

fn count() {
    if COUNTED.with(Cell::get) {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
    }
}

// SAFETY: forwards to the system allocator unchanged; only counts calls.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count();
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count();
        // SAFETY: same contract as the caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Ten thousand ticks of each actuation and of the open loop allocate nothing.
#[test]
fn a_tick_does_not_allocate() {
    let s = Scenario::load("paper-sinusoid").expect("builtin");
    let mut loops = [
        ClosedLoop::new(&s, Actuation::Internal, None).expect("the default law"),
        ClosedLoop::new(&s, Actuation::External, None).expect("the default law"),
        ClosedLoop::new(&s, Actuation::Internal, Some(glam::DVec3::new(0.1, 0.2, 0.3)))
            .expect("the default law"),
    ];
    COUNTED.with(|c| c.set(true));
    // The counter works: an allocation on this thread is seen, one on another is not.
    let before = ALLOCATIONS.load(Ordering::Relaxed);
    let v = std::hint::black_box(vec![1u8; 16]);
    drop(v);
    assert!(ALLOCATIONS.load(Ordering::Relaxed) > before, "allocation counter is not wired");
    let before = ALLOCATIONS.load(Ordering::Relaxed);
    std::thread::spawn(|| {
        for n in 0..1000 {
            drop(std::hint::black_box(vec![1u8; 16 + n]));
        }
    })
    .join()
    .expect("thread");
    let seen = ALLOCATIONS.load(Ordering::Relaxed) - before;
    assert!(seen < 1000, "another thread's 1000 allocations were counted ({seen} seen)");

    for lp in &mut loops {
        let before = ALLOCATIONS.load(Ordering::Relaxed);
        let mut sum = 0.0;
        for _ in 0..10_000 {
            sum += lp.tick().err_deg;
        }
        let after = ALLOCATIONS.load(Ordering::Relaxed);
        std::hint::black_box(sum);
        assert_eq!(after - before, 0, "{} allocations in 10 000 ticks", after - before);
    }
}
