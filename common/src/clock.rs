//! The monotonic clock every role and the launcher time with, and absolute-deadline sleep
//! (no drift from relative sleeps).

use crate::signals::shutdown_requested;

/// `CLOCK_MONOTONIC` in nanoseconds.
#[inline]
pub fn now_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes into the timespec we own.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Sleeps until the absolute `CLOCK_MONOTONIC` time `deadline_ns` (no drift from
/// relative sleeps). With `spin_last_ns > 0`, sleeps until that much before the deadline
/// and spins the rest.
#[inline]
pub fn sleep_until_ns(deadline_ns: u64, spin_last_ns: u64) {
    let wake = deadline_ns.saturating_sub(spin_last_ns);
    let ts = libc::timespec {
        tv_sec: (wake / 1_000_000_000) as libc::time_t,
        tv_nsec: (wake % 1_000_000_000) as libc::c_long,
    };
    loop {
        // SAFETY: ts is a valid timespec; the remaining-time pointer may be null with
        // TIMER_ABSTIME.
        let rc = unsafe {
            libc::clock_nanosleep(
                libc::CLOCK_MONOTONIC,
                libc::TIMER_ABSTIME,
                &ts,
                std::ptr::null_mut(),
            )
        };
        if rc != libc::EINTR || shutdown_requested() {
            break;
        }
    }
    while now_ns() < deadline_ns {
        std::hint::spin_loop();
    }
}

/// The time of `clock` in seconds.
pub fn clock_s(clock: libc::clockid_t) -> f64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: valid pointer to a timespec.
    unsafe { libc::clock_gettime(clock, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// The absolute time grid of a real-time run: tick `k` is due at `start_ns + (k − first)`
/// periods (rounded to the ns, never accumulated, so the rate does not drift).
#[derive(Debug, Clone, Copy)]
pub struct TickGrid {
    start_ns: u64,
    first: u64,
    period_ns: f64,
}

impl TickGrid {
    /// Tick `first` at `start_ns`, then one tick every `1 / rate_hz` seconds.
    pub fn new(start_ns: u64, first: u64, rate_hz: f64) -> Self {
        Self { start_ns, first, period_ns: 1e9 / rate_hz }
    }

    /// When tick `k` is due (monotonic ns).
    pub fn at(&self, k: u64) -> u64 {
        self.start_ns + ((k - self.first) as f64 * self.period_ns).round() as u64
    }

    /// `--plant-stall pause`: tick `k` woken at `woke_ns`, more than a quarter tick after
    /// its time, is due now, and every later tick as much later (the world's clock stood
    /// still while the simulator did not run). Whether it moved the grid.
    pub fn pause_if_late(&mut self, k: u64, woke_ns: u64) -> bool {
        let late = woke_ns > self.at(k) + (self.period_ns / 4.0) as u64;
        if late {
            *self = Self { start_ns: woke_ns, first: k, period_ns: self.period_ns };
        }
        late
    }
}
