//! The flight records' mover on a thread of its own. A pass copies the finished half of
//! every ring into `OUT/flight`: megabytes written to disk, which under writeback pressure
//! wait seconds in the kernel (seen in the repeat harness: `folio_wait_bit`,
//! `submit_bio_wait`). On the supervision loop that wait delayed the fault schedule, the
//! restarts and the watchdog with it; here only the copy waits.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use rotorloop_common::flight::Mover;

/// How often the thread looks for a newer plant tick.
const POLL: Duration = Duration::from_millis(20);

/// A [`Mover`] that runs on its own thread, told the plant's newest tick by the
/// supervision loop.
pub(crate) struct MoverThread {
    /// The plant's newest tick plus one (0: none yet).
    tick: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
    handle: JoinHandle<Mover>,
}

impl MoverThread {
    /// Starts `mover` on a thread named `flight-mover`.
    pub(crate) fn spawn(mut mover: Mover) -> std::io::Result<Self> {
        let tick = Arc::new(AtomicU64::new(0));
        let stop = Arc::new(AtomicBool::new(false));
        let (t, s) = (tick.clone(), stop.clone());
        let handle = std::thread::Builder::new().name("flight-mover".into()).spawn(move || {
            let mut moved_at = 0;
            loop {
                // The stop is read before the tick: the pass after it sees the last tick.
                let stopping = s.load(Ordering::Acquire);
                let newest = t.load(Ordering::Acquire);
                if newest > moved_at {
                    for e in mover.pass(newest - 1) {
                        eprintln!("warning: flight records: {e}; the loop goes on");
                    }
                    moved_at = newest;
                }
                if stopping {
                    return mover;
                }
                std::thread::sleep(POLL);
            }
        })?;
        Ok(Self { tick, stop, handle })
    }

    /// The plant has published `plant_tick`: what became due is moved soon.
    pub(crate) fn saw(&self, plant_tick: u64) {
        self.tick.fetch_max(plant_tick + 1, Ordering::Release);
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
    use rotorloop_common::flight::{
        FlightRecorder, MIN_RING_TICKS, Stream, segment_path, segments,
    };
    use rotorloop_common::wire::TorqueSample;

    /// The thread moves the halves the loop has finished, and on `finish` the ones the
    /// last tick finished, as the supervision loop's own passes did. The writer waits for a
    /// half's segment before it overwrites that half, as a loop at its rate does not need
    /// to: recorded flat out, the ring comes round before the thread's next look (that
    /// loss is counted, and this test then fails).
    #[test]
    fn the_thread_moves_each_finished_half_and_the_last_ones_on_finish() {
        let dir = tempfile::tempdir().expect("tempdir");
        let (staged, kept) = (dir.path().join("staged"), dir.path().join("kept"));
        std::fs::create_dir_all(&staged).expect("staged");
        let (stream, capacity) = (Stream::ControllerTorque, MIN_RING_TICKS);
        let half = capacity / 2;
        let rec: FlightRecorder<TorqueSample> =
            FlightRecorder::open(Some(&staged), stream, capacity, "controller");
        let mover = MoverThread::spawn(Mover::new(&staged, &kept)).expect("thread");
        let ticks = 4 * capacity;
        for k in 0..ticks {
            if k >= capacity && k % half == 0 {
                let copied = segment_path(&kept, stream, k / half - 2);
                let give_up = std::time::Instant::now() + Duration::from_secs(30);
                while !copied.exists() && std::time::Instant::now() < give_up {
                    std::thread::sleep(Duration::from_millis(2));
                }
            }
            rec.record(&TorqueSample { tick: k, ..Default::default() });
            mover.saw(k);
        }
        let m = mover.finish(Some(ticks - 1)).expect("no panic");
        assert_eq!(m.lost, 0, "records overwritten before they were moved");
        // Halves 0..=6 are due by the last tick (half j once tick (j + 1.5)·half is out).
        assert_eq!(m.segments, 7);
        assert_eq!(segments(&kept, stream).len(), 7);
    }
}
