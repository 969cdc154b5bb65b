//! The flight records' mover on a thread of its own. A pass copies the finished half of
//! every ring into `OUT/flight`: megabytes written to disk, which under writeback pressure
//! wait seconds in the kernel (seen in the repeat harness: `folio_wait_bit`,
//! `submit_bio_wait`). On the supervision loop that wait delayed the fault schedule, the
//! restarts and the watchdog with it; here only the copy waits. The same thread journals
//! the newest ticks of every stream into `OUT/flight` every
//! [`rotorloop_common::flight::JOURNAL_PERIOD`] and makes them durable (a crash of the
//! machine loses at most the last second: `common::flight::journal`), in the background
//! (`SCHED_IDLE`) while it keeps up: `Mover::in_background`.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use rotorloop_common::flight::{CATCH_UP, Mover, free_through};
use rotorloop_common::rt::Background;

/// How often the thread looks for a newer plant tick.
const POLL: Duration = Duration::from_millis(20);

/// A [`Mover`] that runs on its own thread, told the plant's newest tick by the
/// supervision loop.
pub(crate) struct MoverThread {
    /// The plant's newest tick plus one (0: none yet).
    tick: Arc<AtomicU64>,
    /// The last tick the plant may publish before the mover has copied more
    /// (`flight::free_through`; `u64::MAX` until a ring's size is known).
    free: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
    /// The thread's policy: in the background while it keeps up (`Mover::in_background`).
    background: Arc<Background>,
    handle: JoinHandle<Mover>,
}

impl MoverThread {
    /// Starts `mover` on a thread named `flight-mover`; with `stall`, its first pass
    /// waits that long (the tests' stand-in for a copy held up by writeback). In
    /// `background` (real time) it journals as `SCHED_IDLE` while it keeps up
    /// (`Mover::in_background`). Not in lockstep, whose loop keeps every CPU busy as long as
    /// it runs and has no deadline to miss: there a background journal only ever ran once it
    /// had fallen [`CATCH_UP`] behind, and beside a build the newest ticks were then over a
    /// second from the disk (1.08 s, docs/flight-recorders.md).
    pub(crate) fn spawn(
        mover: Mover,
        stall: Option<Duration>,
        background: bool,
    ) -> std::io::Result<Self> {
        let tick = Arc::new(AtomicU64::new(0));
        let stop = Arc::new(AtomicBool::new(false));
        let free = mover.half.map_or(u64::MAX, |h| free_through(mover.copied(), h));
        let free = Arc::new(AtomicU64::new(free));
        let (t, s, f) = (tick.clone(), stop.clone(), free.clone());
        let background_of = Arc::new(Background::default());
        let mut mover = mover.following(tick.clone());
        if background {
            mover = mover.in_background(background_of.clone());
        }
        let b = background_of.clone();
        let handle = std::thread::Builder::new().name("flight-mover".into()).spawn(move || {
            b.here();
            let mut moved_at = 0;
            loop {
                // The stop is read before the tick: the pass after it sees the last tick.
                let stopping = s.load(Ordering::Acquire);
                let newest = t.load(Ordering::Acquire);
                if newest > 0 && mover.journal_due() {
                    // The newest ticks onto the disk, durably (a machine crash loses at
                    // most about this period; a pass journals too, between its segments).
                    for e in mover.journal(newest - 1) {
                        eprintln!("warning: flight records: {e}; the loop goes on");
                    }
                }
                if newest > moved_at {
                    if let Some(d) = stall.filter(|_| moved_at == 0) {
                        std::thread::sleep(d);
                    }
                    for e in mover.pass(newest - 1) {
                        eprintln!("warning: flight records: {e}; the loop goes on");
                    }
                    if let Some(h) = mover.half {
                        f.store(free_through(mover.copied(), h), Ordering::Release);
                    }
                    moved_at = newest;
                }
                if stopping {
                    return mover;
                }
                std::thread::sleep(POLL);
            }
        })?;
        Ok(Self { tick, free, stop, background: background_of, handle })
    }

    /// Whether a lockstep plant whose newest published tick is `plant_tick` waits for
    /// this mover before it publishes the next one.
    pub(crate) fn holds(&self, plant_tick: u64) -> bool {
        plant_tick + 1 > self.free.load(Ordering::Acquire)
    }

    /// The plant has published `plant_tick`: what became due is moved soon. A thread in
    /// the background that has fallen behind (the newest ticks [`CATCH_UP`] from the disk)
    /// is made ordinary until it has caught up.
    pub(crate) fn saw(&self, plant_tick: u64) {
        self.tick.fetch_max(plant_tick + 1, Ordering::Release);
        self.background.catch_up(CATCH_UP);
    }

    /// Moves what is due after `plant_tick`, stops the thread and returns the mover (its
    /// counts); `None` if the thread panicked.
    pub(crate) fn finish(self, plant_tick: Option<u64>) -> Option<Mover> {
        if let Some(k) = plant_tick {
            self.saw(k);
        }
        self.stop.store(true, Ordering::Release);
        self.handle.join().ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rotorloop_common::flight::{FlightRecorder, MIN_RING_TICKS, Stream, segments};
    use rotorloop_common::params::RotorBodyState;
    use rotorloop_common::wire::{ReferenceSample, StateSample, TorqueSample};

    /// The thread moves the halves the loop has finished, and on `finish` the ones the
    /// last tick finished. The writers (the plant's state, the reference 16 ticks ahead,
    /// the controller's answers) go flat out, far faster than the thread's 20 ms polls,
    /// and the plant waits for the mover as a lockstep plant does: nothing is lost (without
    /// that wait the rings come round between two polls, and this test fails). Until a half
    /// is copied the thread says it holds the plant (the watchdog's exemption).
    #[test]
    fn the_thread_moves_each_finished_half_while_the_plant_waits_for_it() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (staged, kept) = (dir.path().join("staged"), dir.path().join("kept"));
        std::fs::create_dir_all(&staged).expect("staged");
        let (capacity, lead) = (MIN_RING_TICKS, 16);
        let half = capacity / 2;
        let states: FlightRecorder<StateSample> =
            FlightRecorder::open(Some(&staged), Stream::PlantState, capacity, "t");
        let references: FlightRecorder<ReferenceSample> =
            FlightRecorder::open(Some(&staged), Stream::Reference, capacity, "t");
        let torques: FlightRecorder<TorqueSample> =
            FlightRecorder::open(Some(&staged), Stream::ControllerTorque, capacity, "t");
        let x = RotorBodyState {
            r: glam::DMat3::IDENTITY,
            omega: glam::DVec3::ZERO,
            omega_r: glam::DVec3::ZERO,
            theta: glam::DVec3::ZERO,
        };
        let mover = Mover::new(&staged, &kept).with_half(half);
        let mover = MoverThread::spawn(mover, None, true).expect("thread");
        assert!(mover.holds(free_through(0, half)), "the first tick past the room waits");
        assert!(!mover.holds(free_through(0, half) - 1));
        let ticks = 4 * capacity;
        for k in 0..ticks {
            assert!(!states.wait_for_mover(k, Duration::from_secs(30)), "the mover came");
            states.record(&StateSample::of(k, 0.0, &x));
            mover.saw(k);
            references.record(&ReferenceSample::zeroed(k + lead));
            torques.record(&TorqueSample { tick: k, ..Default::default() });
        }
        let m = mover.finish(Some(ticks - 1)).expect("no panic");
        assert_eq!(m.lost, 0, "records overwritten before they were moved");
        // Halves 0..=6 are due by the last tick (half j once tick (j + 1.5)·half is out).
        assert_eq!(m.segments, 3 * 7);
        for s in [Stream::PlantState, Stream::Reference, Stream::ControllerTorque] {
            assert_eq!(segments(&kept, s).len(), 7, "{s:?}");
        }
    }
}
