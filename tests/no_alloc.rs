//! The hot path does not allocate: one closed-loop tick (plant step, reference step,
//! control law, metrics), and the simulator's loop with its reference ahead, are counted
//! by a global allocator wrapper.
//!
//! Only the test's own thread is counted: libtest's main thread allocates while it waits
//! for the test (CI once saw 4 such allocations land inside the ticks' window).

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use rotorloop::sim::closed_loop::ClosedLoop;
use rotorloop_common::scenario::{Actuation, Scenario};

struct Counting;

thread_local! {
    /// Whether this thread's allocations are counted (a const initialiser: reading it
    /// never allocates).
    static COUNTED: Cell<bool> = const { Cell::new(false) };
    /// This thread's counted allocations (the tests run on threads of one binary: each
    /// counts its own).
    static MINE: Cell<u64> = const { Cell::new(0) };
}

fn count() {
    if COUNTED.with(Cell::get) {
        MINE.with(|m| m.set(m.get() + 1));
    }
}

/// This thread's counted allocations so far.
fn mine() -> u64 {
    MINE.with(Cell::get)
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
    let before = mine();
    let v = std::hint::black_box(vec![1u8; 16]);
    drop(v);
    assert!(mine() > before, "allocation counter is not wired");
    let before = mine();
    std::thread::spawn(|| {
        for n in 0..1000 {
            drop(std::hint::black_box(vec![1u8; 16 + n]));
        }
    })
    .join()
    .expect("thread");
    let seen = mine() - before;
    assert!(seen < 1000, "another thread's 1000 allocations were counted ({seen} seen)");

    for lp in &mut loops {
        let before = mine();
        let mut sum = 0.0;
        for _ in 0..10_000 {
            sum += lp.tick().err_deg;
        }
        let after = mine();
        std::hint::black_box(sum);
        assert_eq!(after - before, 0, "{} allocations in 10 000 ticks", after - before);
    }

    // The simulator's loop with the reference ahead on its own thread: what it allocates
    // on the loop's thread (the blocks, the channels, the thread) does not grow with the
    // ticks.
    let drive = |ticks: u64| {
        let mut lp = ClosedLoop::new(&s, Actuation::Internal, None).expect("the default law");
        let before = mine();
        let mut sum = 0.0;
        lp.drive_ahead(ticks, |_, row| {
            sum += row.err_deg;
            Ok::<(), ()>(())
        })
        .expect("no error");
        std::hint::black_box(sum);
        mine() - before
    };
    // The first drive also makes what the channels keep per thread once (their waiting
    // context): not counted.
    drive(2_000);
    let (short, long) = (drive(2_000), drive(20_000));
    assert!(short > 0, "the blocks and the thread are counted");
    assert!(long <= short, "20 001 ticks allocated {long} times, 2 001 ticks {short}");
}

/// The C API's tick allocates nothing of its own once the port is open: receiving the
/// newest state and its reference allocates nothing, and loan + publish allocate exactly
/// what a loan and send of one sample through iceoryx2 allocates (the built-in
/// controller's path: once per sample here, inside iceoryx2). A thousand ticks against a plant and a
/// reference played by this test in its own domain.
#[test]
fn the_c_apis_tick_allocates_only_what_iceoryx2s_send_does() {
    use rotorloop_c::*;
    use rotorloop_common::graph::Topic;
    use rotorloop_common::ipc::domain::Domain;
    use rotorloop_common::wire::{ReferenceSample, StateSample, TorqueSample};

    let name = format!("na{}", std::process::id());
    let domain = Domain::new(&name).expect("domain");
    let s = Scenario::load("paper-sinusoid").expect("builtin");
    let cname = std::ffi::CString::new(name.clone()).expect("name");
    let mut c: *mut RotorloopController = std::ptr::null_mut();
    // SAFETY: valid strings and a writable pointer.
    let opened = unsafe { rotorloop_controller_open(cname.as_ptr(), c"event".as_ptr(), &mut c) };
    assert_eq!(opened, RotorloopStatus::Ok);
    let plant = domain.node("plant").expect("plant node");
    let states = domain.outbox::<StateSample>(&plant, Topic::State).expect("states");
    let torques = domain.inbox::<TorqueSample>(&plant, Topic::Torque, 8, false).expect("torques");
    let refnode = domain.node("reference").expect("reference node");
    let refs = domain.outbox::<ReferenceSample>(&refnode, Topic::Reference).expect("refs");
    let probe = domain.node("monitor").expect("monitor node");
    let loans = domain.outbox::<TorqueSample>(&probe, Topic::Torque).expect("a second publisher");
    states.update_connections();
    refs.update_connections();
    let x = s.plant_init;
    let (mut reading, mut sending, mut iceoryx2_loans, mut answered) = (0, 0, 0, 0);
    for k in 0..1100u64 {
        // SAFETY: every field a number: zero bytes are a value.
        let mut r: ReferenceSample = unsafe { std::mem::zeroed() };
        r.tick = k;
        r.r_d_row_major = StateSample::of(0, 0.0, &x).r_row_major;
        refs.send(r, |_| ()).expect("reference");
        states.send(StateSample::of(k, k as f64 * 1e-3, &x), |_| ()).expect("state");
        COUNTED.with(|f| f.set(k >= 100));
        let before = mine();
        // SAFETY: an open handle and writable outputs, as the header says.
        unsafe {
            let mut state = std::mem::MaybeUninit::<StateSample>::uninit();
            let mut recv = 0u64;
            let got =
                rotorloop_controller_receive_state(c, 1_000_000_000, state.as_mut_ptr(), &mut recv);
            assert_eq!(got, RotorloopStatus::Ok);
            let tick = state.assume_init().tick;
            let mut rd = std::mem::MaybeUninit::<ReferenceSample>::uninit();
            let got = rotorloop_controller_reference(c, tick, 0, rd.as_mut_ptr());
            assert_eq!(got, RotorloopStatus::Ok);
            reading += mine() - before;
            let before = mine();
            let mut t: *mut TorqueSample = std::ptr::null_mut();
            assert_eq!(rotorloop_controller_loan(c, &mut t), RotorloopStatus::Ok);
            (*t).tick = tick;
            assert_eq!(rotorloop_controller_publish(c), RotorloopStatus::Ok);
            sending += mine() - before;
        }
        // iceoryx2's own loan and send of one sample (the built-in controller's path), for
        // comparison.
        let before = mine();
        loans.send(TorqueSample::default(), |_| ()).expect("send");
        iceoryx2_loans += mine() - before;
        COUNTED.with(|f| f.set(false));
        torques.drain(|_| answered += 1).expect("torques");
    }
    // SAFETY: the open handle, closed once.
    unsafe { rotorloop_controller_close(c, 0) };
    drop((states, torques, refs, loans, plant, refnode, probe));
    let _ = domain.cleanup();
    assert!(answered >= 1000, "{answered} torques came back");
    assert_eq!(reading, 0, "receiving 1000 states and references allocated {reading} times");
    assert_eq!(
        sending, iceoryx2_loans,
        "1000 loans and publishes allocated {sending} times, 1000 of iceoryx2's {iceoryx2_loans}"
    );
}
