//! The lockstep fault gate: the plant stops itself (SIGSTOP) right after publishing each
//! tick of `--gate-ticks`, and the launcher, which sees the stop (`waitid`), carries out
//! the faults due at that tick and continues it (SIGCONT). So a fault scheduled at a tick
//! lands there, run after run, though lockstep runs many times faster than real time.
//!
//! Its cost on a tick without a gate is one comparison of two integers, outside the
//! physics: the plant steps exactly as without it, and the state it publishes is the same.
//! [`NoGate`] is the loop before the gate (`--no-gate`), for `rotorloop bench
//! --before-after gate`, which measures that cost.

/// What the tick loop does right after publishing tick `k` (`process::ticks`).
pub(super) trait Pass {
    fn pass(&mut self, k: u64);
}

/// No gate at all: the tick loop as it was before the gate (`--no-gate`).
pub(super) struct NoGate;

impl Pass for NoGate {
    #[inline(always)]
    fn pass(&mut self, _: u64) {}
}

/// The ticks at which the plant holds for the launcher, those to come first.
pub(super) struct Gate {
    /// Ticks still to come, in descending order (the next at the end).
    ahead: Vec<u64>,
    /// The next one (`u64::MAX`: none).
    next: u64,
}

impl Gate {
    /// The gates of `ticks` from tick `first` on; a plant resumed at `first` has passed a
    /// gate there already (it republishes the state it had published), a fresh one not.
    pub(super) fn new(ticks: &[u64], first: u64, resumed: bool) -> Self {
        let mut ahead: Vec<u64> =
            ticks.iter().copied().filter(|k| *k > first || (*k == first && !resumed)).collect();
        ahead.sort_unstable_by(|a, b| b.cmp(a));
        ahead.dedup();
        let next = ahead.pop().unwrap_or(u64::MAX);
        Self { ahead, next }
    }

    #[cold]
    fn hold(&mut self, k: u64) {
        rotorloop_common::signals::stop_self();
        while self.next <= k {
            self.next = self.ahead.pop().unwrap_or(u64::MAX);
        }
    }

    /// The gates still to come (for the tests).
    #[cfg(test)]
    fn upcoming(&self) -> Vec<u64> {
        std::iter::once(self.next).chain(self.ahead.iter().rev().copied()).collect()
    }
}

impl Pass for Gate {
    /// After publishing tick `k`: at a gate, stop until the launcher continues this
    /// process.
    #[inline(always)]
    fn pass(&mut self, k: u64) {
        if k == self.next {
            self.hold(k);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_resumed_plant_does_not_hold_again_at_the_gate_it_passed() {
        assert_eq!(Gate::new(&[4000, 0, 4500], 0, false).upcoming(), [0, 4000, 4500]);
        assert_eq!(Gate::new(&[4000, 4500], 4000, true).upcoming(), [4500]);
        assert_eq!(Gate::new(&[4000, 4500], 3999, true).upcoming(), [4000, 4500]);
        assert_eq!(Gate::new(&[], 0, false).upcoming(), [u64::MAX], "none: never equal");
    }
}
