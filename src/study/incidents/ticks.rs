//! Which ticks of a run were abnormal, and why: each tick's flags from the state that
//! ends it (what took effect in it), the controller's answer to its state, and the
//! launcher's faults.

use rotorloop_common::wire::{FLAG_SAFE_MODE, StateSample, TorqueSample};

use super::load::{FaultRow, RunRecord};

/// The plant woke for this tick later than the threshold after its grid time.
pub const LATE: u16 = 1;
/// No fresh torque in time: the plant counted a miss.
pub const MISS: u16 = 1 << 1;
/// What took effect in the tick was not the answer to its own state alone.
pub const NOT_FRESH: u16 = 1 << 2;
/// The fresh answer took effect later than the run's median delay by more than the
/// threshold.
pub const SLOW: u16 = 1 << 3;
/// Safe mode.
pub const SAFE: u16 = 1 << 4;
/// A sample was rejected by validation (a torque by the plant, a state or a reference by
/// the controller).
pub const REJECTED: u16 = 1 << 5;
/// The controller answered without its reference sample.
pub const REFERENCE_LATE: u16 = 1 << 6;
/// A fault the launcher saw (kill, stop, hang, crash) was going on.
pub const FAULT: u16 = 1 << 7;
/// The controller's injected delay (`--fault controller:delay`) was on.
pub const DELAY: u16 = 1 << 8;

/// What the flags of the loop itself are (not the launcher's windows).
pub const LOOP: u16 = LATE | MISS | NOT_FRESH | SLOW | SAFE | REJECTED | REFERENCE_LATE;

/// The words of each flag, in bit order.
pub const WORDS: [&str; 9] = [
    "late wake",
    "miss",
    "not fresh",
    "slow torque",
    "safe mode",
    "rejected",
    "reference late",
    "fault",
    "injected delay",
];

/// Each tick's flags and the run's typical figures.
#[derive(Debug, Clone)]
pub struct TickFlags {
    /// Flags of tick `k` (`0..last`).
    pub flags: Vec<u16>,
    /// The median offset at which a tick's fresh answer took effect (s).
    pub median_delay_s: f64,
    /// The threshold of lateness (s).
    pub threshold_s: f64,
}

/// The fresh answer's offset in tick `k`, as state `k + 1` recorded it.
pub fn fresh_offset(next: &StateSample, k: u64) -> Option<f64> {
    (next.effects == 1 && next.effect_ticks[0] == k).then_some(next.effect_offsets_s[0])
}

/// The previous answer the controller computed before tick `k` (its counters are
/// cumulative).
pub fn previous_answer(run: &RunRecord, k: u64) -> Option<&TorqueSample> {
    (k.saturating_sub(64)..k).rev().find_map(|j| run.torque(j))
}

/// How much later than one period after tick `k − 1`'s grid time tick `k`'s is (ns): the
/// world's clock standing still while the plant was late (`--plant-stall pause`), or a
/// restarted plant's new grid.
pub fn paused_ns(run: &RunRecord, k: u64) -> u64 {
    let (Some(s), Some(p)) = (run.state(k), k.checked_sub(1).and_then(|j| run.state(j))) else {
        return 0;
    };
    if s.deadline_ns == 0 || p.deadline_ns == 0 {
        return 0;
    }
    s.deadline_ns.saturating_sub(p.deadline_ns + (run.dt * 1e9).round() as u64)
}

/// The median of `v` (NaN for none).
pub fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Flags every tick of `run`, lateness measured against `threshold_ticks` of a tick.
pub fn flag(run: &RunRecord, threshold_ticks: f64) -> TickFlags {
    let threshold_s = threshold_ticks * run.dt;
    let threshold_ns = (threshold_s * 1e9) as u64;
    let mut offsets: Vec<f64> =
        (0..run.last).filter_map(|k| fresh_offset(run.state(k + 1)?, k)).collect();
    let median_delay_s = median(&mut offsets);
    let mut flags = vec![0u16; run.last as usize];
    for (k, f) in flags.iter_mut().enumerate() {
        let k = k as u64;
        let (Some(s), Some(n)) = (run.state(k), run.state(k + 1)) else { continue };
        if s.deadline_ns > 0 && s.wake_ns > s.deadline_ns + threshold_ns {
            *f |= LATE;
        }
        if paused_ns(run, k) > threshold_ns {
            *f |= LATE;
        }
        match fresh_offset(n, k) {
            Some(o) if o > median_delay_s + threshold_s => *f |= SLOW,
            Some(_) => {}
            None => *f |= NOT_FRESH,
        }
        if n.misses > s.misses {
            *f |= MISS;
        }
        if n.flags & FLAG_SAFE_MODE != 0 {
            *f |= SAFE;
        }
        if n.torques_rejected > s.torques_rejected {
            *f |= REJECTED;
        }
        if let (Some(t), Some(p)) = (run.torque(k), previous_answer(run, k)) {
            if t.states_rejected > p.states_rejected
                || t.references_rejected > p.references_rejected
            {
                *f |= REJECTED;
            }
            // In lockstep the controller waits for a late reference: only in real time
            // does it answer without it.
            if t.reference_misses > p.reference_misses && s.deadline_ns > 0 {
                *f |= REFERENCE_LATE;
            }
        }
    }
    for (from, to, bit) in windows(run) {
        for f in flags.iter_mut().take(to as usize + 1).skip(from as usize) {
            *f |= bit;
        }
    }
    TickFlags { flags, median_delay_s, threshold_s }
}

/// Whether a fault of `role` is one of the loop's: the monitor is outside it (its faults
/// are incidents of their own, which abnormal ticks of the loop do not join).
pub fn in_loop(role: &str) -> bool {
    role != "monitor"
}

/// The ticks `[from, to]` of the launcher's fault `f`: from its start to its end (a role
/// killed and not started again: to the end of the run).
pub fn fault_ticks(run: &RunRecord, f: &FaultRow) -> [u64; 2] {
    let at = |s: f64| run.tick_at_ns(run.t0_ns + (s.max(0.0) * 1e9) as u64);
    let to = f.ended_s.or(f.restart_s).map_or(run.last, at).max(at(f.kill_s));
    [at(f.kill_s), to.min(run.last.saturating_sub(1))]
}

/// The loop's faults and the injected delays as tick windows `(from, to, flag)`.
pub fn windows(run: &RunRecord) -> Vec<(u64, u64, u16)> {
    let mut out = Vec::new();
    for f in run.faults.iter().filter(|f| in_loop(&f.role) && f.kind != "delay") {
        let [from, to] = fault_ticks(run, f);
        out.push((from, to, FAULT));
    }
    for d in run.schedule.iter().filter(|d| d.kind == "delay") {
        let from = (d.at_s / run.dt).round() as u64;
        let to = d.until_s.map_or(run.last, |u| (u / run.dt).round() as u64);
        out.push((from, to.max(from), DELAY));
    }
    out
}

/// Maximal windows of abnormal ticks `[start, end]`, two windows with at most `gap`
/// normal ticks between them being one.
pub fn windows_of(flags: &[u16], gap: u64) -> Vec<[u64; 2]> {
    let mut out: Vec<[u64; 2]> = Vec::new();
    for (k, f) in flags.iter().enumerate() {
        if *f == 0 {
            continue;
        }
        let k = k as u64;
        match out.last_mut() {
            Some(w) if k <= w[1] + gap + 1 => w[1] = k,
            _ => out.push([k, k]),
        }
    }
    out
}

/// The words of `flags`, joined.
pub fn words(flags: u16) -> String {
    WORDS
        .iter()
        .enumerate()
        .filter(|(i, _)| flags & (1 << i) != 0)
        .map(|(_, w)| *w)
        .collect::<Vec<_>>()
        .join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows_join_over_small_gaps_only() {
        let f = [0, 1, 1, 0, 2, 0, 0, 0, 4, 0];
        assert_eq!(windows_of(&f, 1), vec![[1, 4], [8, 8]]);
        assert_eq!(windows_of(&f, 0), vec![[1, 2], [4, 4], [8, 8]]);
        assert_eq!(windows_of(&[0, 0], 2), Vec::<[u64; 2]>::new());
    }

    #[test]
    fn flags_are_named_in_bit_order() {
        assert_eq!(words(LATE | DELAY), "late wake, injected delay");
        assert_eq!(WORDS.len(), 9);
        assert_eq!(1 << (WORDS.len() - 1), DELAY);
    }
}
