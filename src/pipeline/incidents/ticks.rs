//! Which ticks of a run were abnormal, and why: each tick's flags from the state that
//! ends it (what took effect in it), the controller's answer to its state, and the
//! launcher's faults.

use rotorloop_common::wire::{FLAG_SAFE_MODE, StateSample, TorqueSample};

use rotorloop_monitor::summary::FaultRow;

use super::load::RunRecord;

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

/// The run's typical figures, and each tick's flags computed from its records when asked
/// for ([`TickFlags::get`]): nothing is kept per tick, so a day's run takes the memory of
/// a minute's.
#[derive(Debug, Clone)]
pub struct TickFlags {
    /// The median offset at which a tick's fresh answer took effect (s).
    pub median_delay_s: f64,
    /// The threshold of lateness (s).
    pub threshold_s: f64,
    /// The launcher's fault windows and the injected delays ([`windows`]).
    windows: Vec<(u64, u64, u16)>,
    /// Ticks `0..last` have flags.
    last: u64,
}

/// Exact medians (the element at index `n / 2` of the sorted values, as [`median`] gives)
/// of `N` series of values that can be produced again, in bounded memory: a first pass
/// counts them in a histogram of their nanoseconds, which names the narrow bin that
/// holds each median; a second keeps only the values in that bin, and the median is
/// picked among them. Feed every value with [`Medians::add`] in each of the two passes
/// ([`Medians::second_pass`] between them).
#[derive(Debug)]
pub struct Medians<const N: usize> {
    hist: [hdrhistogram::Histogram<u64>; N],
    /// Per series, after the first pass: the bin `[lo, hi]` (ns keys) holding the median,
    /// the values below it, and the values in it by their bits (ordered as the floats).
    bins: Option<[MedianBin; N]>,
}

/// The bin `[lo, hi]` (ns keys) that holds a median, the values below it, and the values
/// in it by their bits (ordered as the floats), with their counts.
type MedianBin = (u64, u64, u64, std::collections::BTreeMap<i64, u64>);

/// A value's histogram key: its nanoseconds, rounded (negative ones are 0; the rounding
/// keeps the order).
fn key(v: f64) -> u64 {
    (v.max(0.0) * 1e9).round().min(1e18) as u64
}

/// A float's bits as a signed integer ordered as the floats are (finite values).
fn ordered(v: f64) -> i64 {
    let b = v.to_bits() as i64;
    if b < 0 { b ^ i64::MAX } else { b }
}

impl<const N: usize> Default for Medians<N> {
    fn default() -> Self {
        let h = || {
            hdrhistogram::Histogram::new_with_bounds(1, 1_000_000_000_000_000_000, 3)
                .expect("constant bounds are valid")
        };
        Self { hist: std::array::from_fn(|_| h()), bins: None }
    }
}

impl<const N: usize> Medians<N> {
    /// Adds value `v` (s) of series `i` (non-finite values are left out).
    pub fn add(&mut self, i: usize, v: f64) {
        if !v.is_finite() {
            return;
        }
        let k = key(v);
        match &mut self.bins {
            None => self.hist[i].saturating_record(k.max(1)),
            Some(bins) => {
                let (lo, hi, below, values) = &mut bins[i];
                if k.max(1) < *lo {
                    *below += 1;
                } else if k.max(1) <= *hi {
                    *values.entry(ordered(v)).or_default() += 1;
                }
            }
        }
    }

    /// Ends the first pass.
    pub fn second_pass(&mut self) {
        self.bins = Some(std::array::from_fn(|i| {
            // The bin of the value at index n / 2 of the sorted values.
            let h = &self.hist[i];
            let (n, mut seen) = (h.len(), 0);
            let at = h
                .iter_recorded()
                .find(|v| {
                    seen += v.count_at_value();
                    seen > n / 2
                })
                .map_or(0, |v| v.value_iterated_to());
            (h.lowest_equivalent(at), h.highest_equivalent(at), 0, Default::default())
        }));
    }

    /// The medians (NaN for a series without values), after the second pass.
    pub fn medians(&self) -> [f64; N] {
        std::array::from_fn(|i| {
            let n = self.hist[i].len();
            let Some((_, _, below, values)) = self.bins.as_ref().map(|b| &b[i]) else {
                return f64::NAN;
            };
            if n == 0 {
                return f64::NAN;
            }
            let mut rank = (n / 2).saturating_sub(*below);
            for (bits, count) in values {
                if rank < *count {
                    let b = if *bits < 0 { *bits ^ i64::MAX } else { *bits };
                    return f64::from_bits(b as u64);
                }
                rank -= count;
            }
            f64::NAN
        })
    }
}

/// The fresh answer's offset in tick `k`, as state `k + 1` recorded it.
pub fn fresh_offset(next: &StateSample, k: u64) -> Option<f64> {
    (next.effects == 1 && next.effect_ticks[0] == k).then_some(next.effect_offsets_s[0])
}

/// The previous answer the controller computed before tick `k` (its counters are
/// cumulative).
pub fn previous_answer(run: &RunRecord, k: u64) -> Option<TorqueSample> {
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

/// The figures by which the ticks of `run` are flagged, lateness measured against
/// `threshold_ticks` of a tick.
pub fn flag(run: &RunRecord, threshold_ticks: f64) -> TickFlags {
    let mut delays = Delays::default();
    (1..=run.last).for_each(|k| run.state(k).iter().for_each(|s| delays.see(k, s)));
    flag_seen(run, threshold_ticks, delays)
}

/// [`flag`] once the states `1..=last` have been seen by `delays` (on a pass over the
/// states made for something else: [`super::load::RunRecord::read_visiting`]).
pub fn flag_seen(run: &RunRecord, threshold_ticks: f64, mut delays: Delays) -> TickFlags {
    let threshold_s = threshold_ticks * run.dt;
    let offsets = &mut delays.0;
    offsets.second_pass();
    for k in 0..run.last {
        if let Some(o) = run.state(k + 1).and_then(|n| fresh_offset(&n, k)) {
            offsets.add(0, o);
        }
    }
    let [median_delay_s] = offsets.medians();
    TickFlags { median_delay_s, threshold_s, windows: windows(run), last: run.last }
}

/// The first pass of the median delay of [`flag`]: each fresh answer's offset, from the
/// state that ends its tick.
#[derive(Debug, Default)]
pub struct Delays(Medians<1>);

impl Delays {
    /// Sees state `k` (`k ≥ 1`: the state that ends tick `k − 1`).
    pub fn see(&mut self, k: u64, s: &StateSample) {
        if let Some(o) = k.checked_sub(1).and_then(|j| fresh_offset(s, j)) {
            self.0.add(0, o);
        }
    }
}

impl TickFlags {
    /// The flags of tick `k` (`0..last`; 0 beyond).
    pub fn get(&self, run: &RunRecord, k: u64) -> u16 {
        if k >= self.last {
            return 0;
        }
        let mut f =
            self.windows.iter().filter(|(a, b, _)| (*a..=*b).contains(&k)).fold(0, |f, w| f | w.2);
        let (Some(s), Some(n)) = (run.state(k), run.state(k + 1)) else { return f };
        let threshold_ns = (self.threshold_s * 1e9) as u64;
        if s.deadline_ns > 0 && s.wake_ns > s.deadline_ns + threshold_ns {
            f |= LATE;
        }
        if paused_ns(run, k) > threshold_ns {
            f |= LATE;
        }
        match fresh_offset(&n, k) {
            Some(o) if o > self.median_delay_s + self.threshold_s => f |= SLOW,
            Some(_) => {}
            None => f |= NOT_FRESH,
        }
        if n.misses > s.misses {
            f |= MISS;
        }
        if n.flags & FLAG_SAFE_MODE != 0 {
            f |= SAFE;
        }
        if n.torques_rejected > s.torques_rejected {
            f |= REJECTED;
        }
        if let (Some(t), Some(p)) = (run.torque(k), previous_answer(run, k)) {
            if t.states_rejected > p.states_rejected
                || t.references_rejected > p.references_rejected
            {
                f |= REJECTED;
            }
            // In lockstep the controller waits for a late reference: only in real time
            // does it answer without it.
            if t.reference_misses > p.reference_misses && s.deadline_ns > 0 {
                f |= REFERENCE_LATE;
            }
        }
        f
    }

    /// The flags of ticks `from..=to`, or-ed together.
    pub fn all(&self, run: &RunRecord, [from, to]: [u64; 2]) -> u16 {
        (from..=to).fold(0, |a, k| a | self.get(run, k))
    }

    /// The run's next maximal window of abnormal ticks `[start, end]` after those `scan`
    /// gave, two windows with at most `gap` normal ticks between them being one; `None`
    /// once the ticks are done. The run is passed to each call, not held, so the caller
    /// may change what it keeps between windows.
    pub fn next_window(
        &self,
        run: &RunRecord,
        scan: &mut WindowScan,
        gap: u64,
    ) -> Option<[u64; 2]> {
        scan.next(self.last, gap, |k| self.get(run, k))
    }
}

/// Where a search for windows of abnormal ticks stands: the next tick to look at and the
/// window still open. What it holds does not grow with the run.
#[derive(Debug, Default, Clone)]
pub struct WindowScan {
    k: u64,
    open: Option<[u64; 2]>,
}

impl WindowScan {
    /// A search from tick `k` on, where the ticks before it are known to be normal.
    pub fn starting_at(k: u64) -> Self {
        Self { k, open: None }
    }

    /// The next maximal window among ticks `..end` whose flags are `flag(k)`, two windows
    /// with at most `gap` normal ticks between them being one.
    pub fn next(
        &mut self,
        end: u64,
        gap: u64,
        mut flag: impl FnMut(u64) -> u16,
    ) -> Option<[u64; 2]> {
        while self.k < end {
            let k = self.k;
            self.k += 1;
            if flag(k) == 0 {
                continue;
            }
            match &mut self.open {
                Some(w) if k <= w[1] + gap + 1 => w[1] = k,
                open => {
                    if let Some(done) = open.replace([k, k]) {
                        return Some(done);
                    }
                }
            }
        }
        self.open.take()
    }
}

/// Whether a fault of `role` is one of the loop's: the monitor is outside it (its faults
/// are incidents of their own, which abnormal ticks of the loop do not join).
pub fn in_loop(role: &str) -> bool {
    role != rotorloop_common::graph::Role::Monitor.name()
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
/// normal ticks between them being one (the tests' whole scan).
#[cfg(test)]
pub fn windows_of(flags: impl IntoIterator<Item = u16>, gap: u64) -> Vec<[u64; 2]> {
    let flags: Vec<u16> = flags.into_iter().collect();
    let mut scan = WindowScan::default();
    std::iter::from_fn(|| scan.next(flags.len() as u64, gap, |k| flags[k as usize])).collect()
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
        assert_eq!(windows_of(f, 1), vec![[1, 4], [8, 8]]);
        assert_eq!(windows_of(f, 0), vec![[1, 2], [4, 4], [8, 8]]);
        assert_eq!(windows_of([0, 0], 2), Vec::<[u64; 2]>::new());
    }

    /// The two-pass median is the sorted middle element, exactly, whatever the values:
    /// equal ones (lockstep), spread ones, negative and non-finite ones.
    #[test]
    fn two_pass_medians_are_exact() {
        let series: [Vec<f64>; 6] = [
            vec![2.5e-4; 1001],
            (0..5001).map(|i| ((i * 7919) % 5001) as f64 * 1.37e-7 + 1e-5).collect(),
            vec![-1.0, 3e-3, 1e-9, 5.0, f64::NAN, 2e-3, 2e-3 + 1e-15],
            Vec::new(),
            vec![2e-3, 1e-6],
            vec![7e-6, 1e-6, 5e-3, 4e-3],
        ];
        let mut m = Medians::<6>::default();
        for pass in 0..2 {
            for (i, v) in series.iter().enumerate() {
                v.iter().for_each(|x| m.add(i, *x));
            }
            if pass == 0 {
                m.second_pass();
            }
        }
        let got = m.medians();
        for (i, v) in series.iter().enumerate() {
            let mut v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
            let want = median(&mut v);
            assert!(
                want.to_bits() == got[i].to_bits() || (want.is_nan() && got[i].is_nan()),
                "{i}: {want} vs {}",
                got[i]
            );
        }
    }

    #[test]
    fn flags_are_named_in_bit_order() {
        assert_eq!(words(LATE | DELAY), "late wake, injected delay");
        assert_eq!(WORDS.len(), 9);
        assert_eq!(1 << (WORDS.len() - 1), DELAY);
    }
}
