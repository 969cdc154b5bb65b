//! Incidents: why a tick was late, and what it cost.
//!
//! An incident is a maximal window of abnormal ticks (`ticks`): the plant woke later than
//! the threshold (a quarter tick unless told), a miss, a tick in which something other
//! than the answer to its own state took effect, a fresh answer that took effect later
//! than the run's median delay by more than the threshold, safe mode, a rejected sample,
//! an answer without its reference, a fault the launcher saw, an injected delay. Windows
//! at most [`GAP`] normal ticks apart are one.
//!
//! For each, [`cause`] says which process and stage held the loop up (the launcher's
//! faults, the stamps every sample carries, the kernel's view in `sched.csv`) and [`cost`]
//! what it cost against the loop that had no incident. [`explain`] writes
//! `incidents.csv`, `incidents.md` and `incidents.png` into the run directory and adds
//! the worst incident to `summary.json`; `rotorloop run` calls it after every run, and
//! `rotorloop explain RUN_DIR` again for a finished one.

pub mod cause;
pub mod cost;
pub mod load;
mod report;
pub mod ticks;
pub mod trace;

use std::path::Path;

use serde::Serialize;

use load::RunRecord;

/// Abnormal windows at most this many normal ticks apart are one incident.
pub const GAP: u64 = 2;
/// The most incidents whose cost is computed (those of the launcher's faults, then the
/// longest; within [`COST_TICKS_PER_S`]); the others are listed without it.
pub const MAX_COSTED: usize = 200;

/// The ticks of counterfactual the costing may step for each second of the run: of the
/// [`MAX_COSTED`] candidates, in line, each is costed whose counterfactual's longest walk
/// ([`cost::most_ticks`]) fits in what is left. In a loaded run a counterfactual's
/// deviation is real and falls back at the loop's own pace (seconds: the median walk was
/// 9 700 ticks), and 200 of them were 90 % of the analysis, 7 % of the run's length. A
/// counterfactual's tick costs about 0.8 µs on this 2-vCPU machine, so this holds the
/// costing to about 0.6 % of a run at 1 kHz.
pub const COST_TICKS_PER_S: u64 = 8_000;

/// How incidents are found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Options {
    /// A plant wake or an answer this much later than usual (in ticks) is abnormal.
    pub threshold_ticks: f64,
}

impl Default for Options {
    fn default() -> Self {
        Self { threshold_ticks: 0.25 }
    }
}

/// One incident.
#[derive(Debug, Clone, Serialize)]
pub struct Incident {
    /// Its first tick.
    pub start_tick: u64,
    /// Its last tick.
    pub end_tick: u64,
    /// Its first tick's time (s).
    pub start_s: f64,
    /// Its length (s).
    pub duration_s: f64,
    /// What it was ([`cause::Cause::kind`]).
    pub kind: &'static str,
    /// The process that held the loop up.
    pub cause_role: String,
    /// The stage, or what was done to the process.
    pub cause_stage: String,
    /// The stamps and kernel figures behind the cause.
    pub evidence: String,
    /// Its abnormal ticks' flags, in words.
    pub flags: String,
    /// Ticks in it on which the plant counted a miss.
    pub misses: u64,
    /// Peak deviation from the loop that had no incident (deg); `None`: not computed.
    pub peak_deviation_deg: Option<f64>,
    /// From its start until the deviation is below 10 % of its peak (s); `None`: not
    /// within the run, or not computed.
    pub recovery_s: Option<f64>,
    /// The deviation's curve, for the figure.
    #[serde(skip)]
    pub curve: Vec<f64>,
    /// The launcher's fault that caused it (its index in `summary.json`'s `faults`).
    #[serde(skip)]
    pub fault: Option<usize>,
}

impl Incident {
    /// Orders incidents by cost: peak deviation (an uncosted one below every costed one),
    /// then length.
    pub fn by_cost(a: &Self, b: &Self) -> std::cmp::Ordering {
        let p = |i: &Self| i.peak_deviation_deg.unwrap_or(-1.0);
        p(a).total_cmp(&p(b)).then(a.duration_s.total_cmp(&b.duration_s))
    }
}

/// The most incidents kept in memory (the costliest): `incidents.md` words these, and the
/// figure draws the five costliest of them.
pub const KEPT: usize = 20;

/// The incident that holds one of the launcher's faults: its row of `incidents.csv`
/// (from 0) and its cost.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FaultIncident {
    /// Its row of `incidents.csv`, from 0.
    pub row: usize,
    /// Its peak deviation (deg), if costed.
    pub peak_deviation_deg: Option<f64>,
    /// Its recovery (s), if costed and within the run.
    pub recovery_s: Option<f64>,
}

/// A run's incidents and what was checked on the way. Every incident is a row of
/// `incidents.csv`, written as it is found; this keeps only their count, the costliest
/// [`KEPT`] and the ones that hold the launcher's faults, so its memory is the same for
/// a run with a million incidents as for one with ten.
#[derive(Debug, Clone, Serialize)]
pub struct Explained {
    /// How many incidents the run had.
    pub count: usize,
    /// How many of them have a cost ([`MAX_COSTED`], [`COST_TICKS_PER_S`]).
    pub costed: usize,
    /// The ticks their counterfactuals stepped, in all.
    pub counterfactual_ticks: u64,
    /// The costliest [`KEPT`] incidents, the worst first, each with its row of
    /// `incidents.csv` (from 0).
    pub costliest: Vec<(usize, Incident)>,
    /// The costliest of all; of several equally costly, the last.
    #[serde(skip)]
    worst: Option<Incident>,
    /// For each of the launcher's faults (`summary.json`'s `faults`, in order), the
    /// incident it caused, else one that holds the tick it came at.
    pub faults: Vec<Option<FaultIncident>>,
    /// The threshold of lateness (s).
    pub threshold_s: f64,
    /// The run's median actuation delay (s): the counterfactual's.
    pub median_delay_s: f64,
    /// Answers the law in process reproduced bit for bit, of those the controller computed.
    pub law_reproduced: [u64; 2],
    /// Whether the run was in real time.
    pub realtime: bool,
    /// Whether `sched.csv` was there.
    pub kernel_view: bool,
    /// Whether the kernel's scheduler trace (`--trace-sched`) was there.
    pub traced: bool,
}

impl Explained {
    /// The incident of the largest peak deviation (then the longest).
    pub fn worst(&self) -> Option<&Incident> {
        self.worst.as_ref()
    }

    /// Takes the incident of `row` into the costliest, if it is one of them.
    fn keep(&mut self, row: usize, incident: Incident) {
        if self.worst.as_ref().is_none_or(|w| Incident::by_cost(&incident, w).is_ge()) {
            self.worst = Some(incident.clone());
        }
        // After the equally costly ones found before it, as a stable sort has it.
        let at = self.costliest.partition_point(|(_, i)| Incident::by_cost(i, &incident).is_ge());
        if at < KEPT {
            self.costliest.insert(at, (row, incident));
            self.costliest.truncate(KEPT);
        }
    }

    /// One line for the console and the paper's report.
    pub fn describe_worst(&self) -> String {
        match self.worst() {
            None => "no incident".to_owned(),
            Some(i) => format!(
                "{} incident(s); worst: {} at {:.3} s for {:.1} ms, caused by {} ({}), peak \
                 deviation {}, recovered {}",
                self.count,
                i.kind,
                i.start_s,
                i.duration_s * 1e3,
                i.cause_role,
                i.cause_stage,
                i.peak_deviation_deg.map_or("not computed".into(), |d| format!("{d:.3}°")),
                i.recovery_s.map_or("not within the run".into(), |r| format!("in {r:.3} s")),
            ),
        }
    }
}

/// For each of the launcher's faults, the first incident it caused and the first that
/// holds the tick it came at (`kill_ticks`), as they are found.
struct FaultsHeld {
    kill_ticks: Vec<Option<u64>>,
    caused: Vec<Option<FaultIncident>>,
    holding: Vec<Option<FaultIncident>>,
}

impl FaultsHeld {
    fn new(faults: &[rotorloop_monitor::summary::FaultRow]) -> Self {
        let kill_ticks: Vec<Option<u64>> = faults.iter().map(|f| f.kill_tick).collect();
        Self { caused: vec![None; faults.len()], holding: vec![None; faults.len()], kill_ticks }
    }

    fn see(&mut self, row: usize, i: &Incident) {
        let held = FaultIncident {
            row,
            peak_deviation_deg: i.peak_deviation_deg,
            recovery_s: i.recovery_s,
        };
        let holds = |k: u64| i.start_tick <= k + 1 && k <= i.end_tick + 1;
        for (j, k) in self.kill_ticks.iter().enumerate() {
            if i.fault == Some(j) {
                self.caused[j].get_or_insert(held);
            }
            if k.is_some_and(holds) {
                self.holding[j].get_or_insert(held);
            }
        }
    }

    /// Each fault's incident: the one it caused, else one that holds its tick.
    fn held(self) -> Vec<Option<FaultIncident>> {
        self.caused.into_iter().zip(self.holding).map(|(c, h)| c.or(h)).collect()
    }
}

/// The run's incident windows in the order of their first ticks: the loop's windows of
/// abnormal ticks, and each fault outside the loop as a window of its own (after a loop
/// window with the same first tick). Found as they are asked for, from the run passed to
/// each call: what is held is the faults outside the loop, not the windows.
struct Windows {
    scan: ticks::WindowScan,
    /// The loop's next window, once looked for (`Some(None)`: there is none).
    next_loop: Option<Option<[u64; 2]>>,
    /// The faults outside the loop with their windows, by first tick.
    outside: std::collections::VecDeque<([u64; 2], usize)>,
}

impl Windows {
    /// The windows of `run`, the loop's looked for from tick `from` on (the ticks before
    /// it known to be normal).
    fn new(run: &RunRecord, from: u64) -> Self {
        let mut outside: Vec<([u64; 2], usize)> = (run.faults.iter().enumerate())
            .filter(|(_, f)| !ticks::in_loop(&f.role))
            .map(|(i, f)| (ticks::fault_ticks(run, f), i))
            .collect();
        outside.sort_by_key(|(w, _)| w[0]);
        Self {
            scan: ticks::WindowScan::starting_at(from),
            next_loop: None,
            outside: outside.into(),
        }
    }

    fn next(
        &mut self,
        run: &RunRecord,
        flags: &ticks::TickFlags,
    ) -> Option<([u64; 2], Option<usize>)> {
        self.next_with(|scan| flags.next_window(run, scan, GAP))
    }

    /// The next window, the loop's next found by `next_loop`.
    fn next_with(
        &mut self,
        next_loop: impl FnOnce(&mut ticks::WindowScan) -> Option<[u64; 2]>,
    ) -> Option<([u64; 2], Option<usize>)> {
        let scan = &mut self.scan;
        let next_loop = *self.next_loop.get_or_insert_with(|| next_loop(scan));
        match (next_loop, self.outside.front()) {
            (Some(l), Some((o, _))) if o[0] < l[0] => {
                self.outside.pop_front().map(|(w, i)| (w, Some(i)))
            }
            (Some(l), _) => {
                self.next_loop = None;
                Some((l, None))
            }
            (None, _) => self.outside.pop_front().map(|(w, i)| (w, Some(i))),
        }
    }
}

/// What the first pass over the run's windows finds.
struct FirstPass {
    /// How many windows there are.
    count: usize,
    /// Those to cost, by index ([`Candidates`], [`within_budget`]).
    costed: Vec<(usize, [u64; 2])>,
    /// The first tick of the loop's first window (`None`: the loop had none).
    first_loop_tick: Option<u64>,
}

/// The first pass over the run's windows; each tick it flags is also seen by `stages`
/// (the first of their two passes, which it ends).
fn first_pass(
    run: &RunRecord,
    flags: &ticks::TickFlags,
    stages: &mut cause::StageMedians,
) -> FirstPass {
    let (mut count, mut candidates, mut first_loop_tick) = (0, Candidates::default(), None);
    let mut windows = Windows::new(run, 0);
    let mut flag = |k| {
        let f = flags.get(run, k);
        stages.see(run, k, f);
        f
    };
    while let Some((w, outside)) = windows.next_with(|scan| scan.next(run.last, GAP, &mut flag)) {
        if outside.is_none() {
            first_loop_tick.get_or_insert(w[0]);
        }
        let fault = outside.is_some() || cause::fault_of(run, w).is_some();
        candidates.see(count, w, fault);
        count += 1;
    }
    stages.second_pass();
    let costed = within_budget(&candidates.kept(), run.last, run.dt);
    FirstPass { count, costed, first_loop_tick }
}

/// The [`MAX_COSTED`] windows first in line to be costed of those seen one at a time, as
/// a stable sort would pick them: those that hold one of the launcher's faults, then the
/// longest; of two alike, the earlier.
#[derive(Debug, Default)]
struct Candidates {
    /// A min-heap of those kept: the last in line on top.
    heap: std::collections::BinaryHeap<std::cmp::Reverse<Rank>>,
}

/// A window's place in line: whether it holds a fault, its length, its index (reversed:
/// of two alike, the earlier is the greater), and the window.
type Rank = (bool, u64, std::cmp::Reverse<usize>, [u64; 2]);

impl Candidates {
    /// Sees the window `w`, the `i`-th; `fault`: whether it holds one of the launcher's.
    fn see(&mut self, i: usize, w: [u64; 2], fault: bool) {
        use std::cmp::Reverse;
        self.heap.push(Reverse((fault, w[1] - w[0], Reverse(i), w)));
        if self.heap.len() > MAX_COSTED {
            self.heap.pop();
        }
    }

    /// Those kept, the first in line first: each one's index and window.
    fn kept(self) -> Vec<(usize, [u64; 2])> {
        use std::cmp::Reverse;
        let sorted = self.heap.into_sorted_vec(); // ascending `Reverse`: first in line first
        sorted.into_iter().map(|Reverse((_, _, Reverse(i), w))| (i, w)).collect()
    }
}

/// Of the `candidates` (first in line first), those to cost, by index: in line, each whose
/// counterfactual's longest walk ([`cost::most_ticks`]) fits in what is left of
/// [`COST_TICKS_PER_S`] for each second of a run whose last tick is `last`.
fn within_budget(candidates: &[(usize, [u64; 2])], last: u64, dt: f64) -> Vec<(usize, [u64; 2])> {
    let seconds = (last + 1) as f64 * dt;
    let mut left = (seconds * COST_TICKS_PER_S as f64) as u64;
    let mut costed: Vec<(usize, [u64; 2])> = (candidates.iter().copied())
        .filter(|(_, w)| {
            let walk = cost::most_ticks(*w, last, dt);
            let fits = walk <= left;
            if fits {
                left -= walk;
            }
            fits
        })
        .collect();
    costed.sort_unstable();
    costed
}

/// What [`find`] needs before it explains the first incident.
struct Figures {
    flags: ticks::TickFlags,
    first: FirstPass,
    pass: cost::LawPass,
    /// The stages' medians (ns).
    medians: [f64; 5],
}

/// [`find`]'s passes over the records before the explaining one, each doing what can be
/// done at that point (a day's run is 86.4 M ticks, and these passes are most of the time
/// after its last tick): the first, reading the run, has fed `delays` the states
/// `1..=last`.
fn figures(run: &RunRecord, delays: ticks::Delays, options: Options) -> anyhow::Result<Figures> {
    // 2. The median delay's second pass, which the flags need.
    let flags = ticks::flag_seen(run, options.threshold_ticks, delays);
    // 3. The windows: how many, those to cost (none of them held: a day's run can have
    // millions), and the first pass of the stages' medians.
    let mut stages = cause::StageMedians::default();
    let first = first_pass(run, &flags, &mut stages);
    // 4. The law over every answer, and the second pass of the stages' medians.
    let windows: Vec<[u64; 2]> = first.costed.iter().map(|(_, w)| *w).collect();
    let pass = cost::law_pass(run, &windows, &mut |k| {
        if k < run.last {
            stages.see(run, k, flags.get(run, k));
        }
    })?;
    Ok(Figures { flags, first, pass, medians: stages.medians() })
}

/// Finds, explains and costs the incidents of the run in `dir`, handing each to `row` as
/// it is found, in time order.
pub fn find(
    dir: &Path,
    options: Options,
    row: &mut dyn FnMut(&Incident) -> anyhow::Result<()>,
) -> anyhow::Result<Explained> {
    // 1. Reading the run: the first pass of the median delay, from the states alone.
    let mut delays = ticks::Delays::default();
    let mut run = RunRecord::read_visiting(dir, &mut |k, s| delays.see(k, s))?;
    let Figures { flags, first, pass, medians } = figures(&run, delays, options)?;
    // 5. The windows again, each explained and costed, from the loop's first (the ticks
    // before it are normal).
    let mut befores = pass.before.iter();
    let mut held = FaultsHeld::new(&run.faults);
    let mut found = Explained {
        count: first.count,
        costed: 0, // each with a cost, as found
        counterfactual_ticks: 0,
        costliest: Vec::new(),
        worst: None,
        faults: Vec::new(), // each fault's incident, once all are seen
        threshold_s: flags.threshold_s,
        median_delay_s: flags.median_delay_s,
        law_reproduced: [pass.same, pass.computed],
        realtime: run.realtime(),
        kernel_view: run.kernel_view,
        traced: run.traced,
    };
    let mut costed = first.costed.into_iter().map(|(i, _)| i).peekable();
    let from = first.first_loop_tick.unwrap_or(run.last);
    let (mut windows, mut i) = (Windows::new(&run, from), 0);
    while let Some((w, outside)) = windows.next(&run, &flags) {
        run.sched_for(w);
        run.trace_for(w);
        let fault = outside.or_else(|| cause::fault_of(&run, w));
        let (c, all, misses) = match outside {
            Some(f) => {
                let c = cause::with_kernel(&run, cause::fault_cause(&run, &run.faults[f]), w);
                (c, ticks::FAULT, 0)
            }
            None => {
                let all = flags.all(&run, w);
                let misses =
                    (w[0]..=w[1]).filter(|k| flags.get(&run, *k) & ticks::MISS != 0).count();
                (cause::cause(&run, &flags, &medians, w), all, misses as u64)
            }
        };
        let law = match costed.next_if_eq(&i) {
            Some(_) => befores.next().copied(),
            None => None,
        };
        let cost = law
            .and_then(|law| cost::cost(&run, &flags, w, law, &pass.propagated, outside.is_none()));
        if let Some(c) = &cost {
            found.costed += 1;
            found.counterfactual_ticks += c.ticks;
        }
        let incident = Incident {
            start_tick: w[0],
            end_tick: w[1],
            start_s: run.t_s(w[0]),
            duration_s: (w[1] + 1 - w[0]) as f64 * run.dt,
            kind: c.kind,
            cause_role: c.role,
            cause_stage: c.stage,
            evidence: c.evidence,
            flags: ticks::words(all),
            misses,
            peak_deviation_deg: cost.as_ref().map(|c| c.peak_deg),
            recovery_s: cost.as_ref().and_then(|c| c.recovery_s),
            curve: cost.map(|c| c.curve).unwrap_or_default(),
            fault,
        };
        row(&incident)?;
        held.see(i, &incident);
        found.keep(i, incident);
        i += 1;
    }
    found.faults = held.held();
    Ok(found)
}

/// [`explain`] on a thread of its own at nice 10, as `rotorloop run` calls it after a run:
/// its seconds of arithmetic yield to any loop still running on the machine (a busy
/// machine's other runs, the tests beside it).
pub fn explain_yielding(dir: &Path, options: Options) -> anyhow::Result<Explained> {
    let dir = dir.to_owned();
    std::thread::Builder::new()
        .name("incidents".into())
        .spawn(move || {
            // SAFETY: gettid and setpriority on this very thread.
            unsafe {
                let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
                libc::setpriority(libc::PRIO_PROCESS, tid, 10);
            }
            explain(&dir, options)
        })?
        .join()
        .map_err(|_| anyhow::anyhow!("the incidents' thread panicked"))?
}

/// Finds the incidents of the run in `dir` and writes `incidents.csv`, `incidents.md`,
/// `incidents.png` there, the worst one into `summary.json` (`incidents`) and each fault's
/// cost into its row of `faults`.
pub fn explain(dir: &Path, options: Options) -> anyhow::Result<Explained> {
    let mut rows = report::Rows::create(dir)?;
    let found = find(dir, options, &mut |i| rows.add(i))?;
    rows.finish()?;
    report::write(dir, &found)?;
    Ok(found)
}

/// A small deterministic generator for the incidents' tests: `next(n)` is in `0..n`.
#[cfg(test)]
pub(crate) fn test_random(mut seed: u64) -> impl FnMut(u64) -> u64 {
    move |n| {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        seed % n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn incident(start: u64, peak: Option<f64>, ticks: u64, fault: Option<usize>) -> Incident {
        Incident {
            start_tick: start,
            end_tick: start + ticks - 1,
            start_s: start as f64 * 1e-3,
            duration_s: ticks as f64 * 1e-3,
            kind: "miss",
            cause_role: String::new(),
            cause_stage: String::new(),
            evidence: String::new(),
            flags: String::new(),
            misses: 0,
            peak_deviation_deg: peak,
            recovery_s: None,
            curve: Vec::new(),
            fault,
        }
    }

    /// The candidates kept one at a time are those a stable sort of all of them picks,
    /// faults' first, then by length (what `find` did while it held every window), ties
    /// included, in that order.
    #[test]
    fn the_candidates_kept_one_at_a_time_are_those_a_sort_of_all_picks() {
        let mut next = super::test_random(0x853c_49e6_748f_ea9b_u64);
        for n in [0, 1, MAX_COSTED, MAX_COSTED + 1, 5_000] {
            let windows: Vec<([u64; 2], bool)> = (0..n as u64)
                .map(|i| {
                    let len = next(4) * next(50); // many ties
                    ([10 * i, 10 * i + len], next(40) == 0)
                })
                .collect();
            let mut candidates = Candidates::default();
            windows.iter().enumerate().for_each(|(i, (w, f))| candidates.see(i, *w, *f));
            let mut in_line: Vec<usize> = (0..windows.len()).collect();
            in_line.sort_by_key(|i| {
                let (w, fault) = windows[*i];
                (std::cmp::Reverse(fault), std::cmp::Reverse(w[1] - w[0]))
            });
            let want: Vec<(usize, [u64; 2])> =
                in_line.into_iter().take(MAX_COSTED).map(|i| (i, windows[i].0)).collect();
            assert_eq!(candidates.kept(), want, "{n} windows");
        }
    }

    /// The costed candidates' counterfactuals fit in the run's share, and each candidate
    /// left out would not have fitted in what the others left: none is left out while
    /// there was room for it.
    #[test]
    fn the_costed_fit_in_the_runs_share_and_leave_no_room_for_another() {
        let mut next = super::test_random(0x3c6e_f372_fe94_f82b_u64);
        let dt = 1e-3;
        for round in 0..200 {
            let last = 1 + next(300_000);
            let candidates: Vec<(usize, [u64; 2])> = (0..next(MAX_COSTED as u64 + 1) as usize)
                .map(|i| {
                    let a = next(last + 1);
                    (i, [a, (a + next(2_000)).min(last)])
                })
                .collect();
            let costed = within_budget(&candidates, last, dt);
            let walk = |w: [u64; 2]| cost::most_ticks(w, last, dt);
            let share = ((last + 1) as f64 * dt * COST_TICKS_PER_S as f64) as u64;
            let used: u64 = costed.iter().map(|(_, w)| walk(*w)).sum();
            assert!(used <= share, "round {round}: {used} ticks of {share}");
            for c in candidates.iter().filter(|c| !costed.contains(c)) {
                assert!(
                    walk(c.1) > share - used,
                    "round {round}: {c:?} fitted in {}",
                    share - used
                );
            }
            assert!(costed.is_sorted(), "round {round}: by index");
            assert!(costed.iter().all(|c| candidates.contains(c)), "round {round}");
        }
    }

    /// The windows found a tick at a time, faults outside the loop merged in by first tick,
    /// are those of one scan of every tick with the faults appended and a stable sort (what
    /// `find` did while it held every window).
    #[test]
    fn windows_found_as_asked_are_those_of_a_whole_scan() {
        let mut next = super::test_random(0xda94_2042_e4dd_58b5_u64);
        for round in 0..50 {
            let n = 1 + next(400);
            let flags: Vec<u16> = (0..n).map(|_| u16::from(next(4) == 0)).collect();
            let outside: Vec<[u64; 2]> = (0..next(5))
                .map(|_| {
                    let a = next(n + 1);
                    [a, a + next(20)]
                })
                .collect();
            let mut want: Vec<([u64; 2], Option<usize>)> =
                ticks::windows_of(flags.iter().copied(), GAP)
                    .into_iter()
                    .map(|w| (w, None))
                    .collect();
            want.extend(outside.iter().enumerate().map(|(i, w)| (*w, Some(i))));
            want.sort_by_key(|(w, _)| w[0]);
            let mut sorted: Vec<([u64; 2], usize)> =
                outside.iter().enumerate().map(|(i, w)| (*w, i)).collect();
            sorted.sort_by_key(|(w, _)| w[0]);
            let mut windows = Windows {
                scan: ticks::WindowScan::default(),
                next_loop: None,
                outside: sorted.into(),
            };
            let got: Vec<([u64; 2], Option<usize>)> = std::iter::from_fn(|| {
                windows.next_with(|scan| scan.next(n, GAP, |k| flags[k as usize]))
            })
            .collect();
            assert_eq!(got, want, "round {round}");
        }
    }

    /// The passes that do two things at once find what the passes of one thing each find:
    /// the median delay, the windows, those to cost, the stages' medians, on a run
    /// of misses, late and missing answers, and stamps of every size.
    #[test]
    fn the_shared_passes_find_what_passes_of_their_own_find() {
        use rotorloop_common::scenario::Scenario;
        use rotorloop_common::wire::{StateSample, TorqueSample};
        let scenario = Scenario::load("paper-zero").expect("built-in");
        let mut next = super::test_random(0x6a09_e667_f3bc_c908_u64);
        let (n, mut misses) = (5000, 0);
        let (mut states, mut torques) = (Vec::<StateSample>::new(), Vec::<TorqueSample>::new());
        for k in 0..n {
            let mut s = StateSample::of(k, k as f64 * scenario.dt(), &scenario.plant_init);
            s.deadline_ns = 1_000_000 * (k + 1);
            let late = next(3) * 200_000 + 1;
            s.wake_ns = s.deadline_ns + next(late);
            s.publish_ns = s.wake_ns + 1_000 + next(3_000);
            misses += u64::from(next(50) == 0);
            s.misses = misses;
            // What took effect: the answer to the tick before, at an offset, mostly.
            if let Some(t) = torques.last().filter(|_| next(30) > 0) {
                s.effects = 1;
                s.effect_ticks[0] = t.tick;
                let spread = next(4) * 40_000 + 1;
                s.effect_offsets_s[0] = (10_000 + next(spread)) as f64 * 1e-9;
                s.applied_torque_tick = t.tick;
                s.applied_torque_recv_ns = t.publish_ns + 1_000 + next(5_000);
            }
            // The answer, one a tick.
            let recv = s.publish_ns + 2_000 + next(20_000);
            let publish_ns = recv + 500 + next(2_000);
            torques.push(TorqueSample {
                tick: k,
                state_recv_ns: recv,
                publish_ns,
                ..Default::default()
            });
            states.push(s);
        }
        let run = RunRecord::of(scenario, states, torques);
        let mut delays = ticks::Delays::default();
        (0..=run.last).for_each(|k| run.state(k).iter().for_each(|s| delays.see(k, s)));
        let got = figures(&run, delays, Options::default()).expect("figures");
        let flags = ticks::flag(&run, Options::default().threshold_ticks);
        let mut offsets: Vec<f64> = (0..run.last)
            .filter_map(|k| run.state(k + 1).and_then(|s| ticks::fresh_offset(&s, k)))
            .collect();
        let median = ticks::median(&mut offsets);
        assert!(median > 0.0, "{median}");
        assert_eq!(got.flags.median_delay_s.to_bits(), median.to_bits());
        assert_eq!(flags.median_delay_s.to_bits(), median.to_bits());
        let (count, costed) = {
            let (mut count, mut candidates, mut windows) =
                (0, Candidates::default(), Windows::new(&run, 0));
            while let Some((w, outside)) = windows.next(&run, &flags) {
                candidates.see(count, w, outside.is_some() || cause::fault_of(&run, w).is_some());
                count += 1;
            }
            (count, within_budget(&candidates.kept(), run.last, run.dt))
        };
        assert!(count > 20, "{count} windows: the run tests too little");
        assert!(!costed.is_empty(), "none costed: the run tests too little");
        assert_eq!((got.first.count, &got.first.costed), (count, &costed));
        let mut scan = ticks::WindowScan::default();
        let first_window = flags.next_window(&run, &mut scan, GAP).map(|w| w[0]);
        assert_eq!(got.first.first_loop_tick, first_window);
        let want = cause::tests::stage_medians(&run, &flags);
        assert_eq!(got.medians.map(f64::to_bits), want.map(f64::to_bits), "{want:?}");
        let mut each: [Vec<f64>; 5] = Default::default();
        for k in (0..run.last).filter(|k| flags.get(&run, *k) == 0) {
            for (i, x) in cause::stages(&run, k).iter().enumerate() {
                each[i].extend(x.map(|x| x as f64));
            }
        }
        assert_eq!(want, each.map(|mut v| ticks::median(&mut v)));
        assert!(want.iter().all(|m| m.is_finite()), "{want:?}");
    }

    /// Of incidents seen one at a time, the kept ones are the first [`KEPT`] of a stable
    /// sort of all by cost (ties in time order), and the worst is the one `max_by` picks
    /// of all (of equals, the last), as when every incident was held: ties and uncosted
    /// incidents included.
    #[test]
    fn the_costliest_kept_one_at_a_time_are_those_of_all() {
        let mut next = super::test_random(0x2545_f491_4f6c_dd1d_u64);
        let all: Vec<Incident> = (0..5000)
            .map(|k| {
                let peak = (next(3) > 0).then(|| next(8) as f64 * 0.5);
                incident(10 * k, peak, 1 + next(4), None)
            })
            .collect();
        let mut found = Explained {
            count: all.len(),
            costed: 0,
            counterfactual_ticks: 0,
            costliest: Vec::new(),
            worst: None,
            faults: Vec::new(),
            threshold_s: 0.0,
            median_delay_s: 0.0,
            law_reproduced: [0, 0],
            realtime: false,
            kernel_view: false,
            traced: false,
        };
        for (row, i) in all.iter().enumerate() {
            found.keep(row, i.clone());
        }
        let mut ranked: Vec<usize> = (0..all.len()).collect();
        ranked.sort_by(|a, b| Incident::by_cost(&all[*b], &all[*a]));
        let kept: Vec<usize> = found.costliest.iter().map(|(row, _)| *row).collect();
        assert_eq!(kept, ranked[..KEPT]);
        let worst = all.iter().max_by(|a, b| Incident::by_cost(a, b)).expect("one");
        assert_eq!(found.worst().map(|w| w.start_tick), Some(worst.start_tick));
    }

    /// A fault's incident is the first it caused, else the first that holds its tick,
    /// whichever of the two comes first in time.
    #[test]
    fn a_faults_incident_is_the_one_it_caused_else_one_that_holds_its_tick() {
        let f = |kill_tick| rotorloop_monitor::summary::FaultRow {
            role: "controller".into(),
            kind: "kill".into(),
            detail: String::new(),
            kill_s: 0.0,
            kill_tick,
            restart_s: None,
            ended: None,
            ended_s: None,
            signal: None,
            scheduled: Some(true),
        };
        let mut held = FaultsHeld::new(&[f(Some(100)), f(Some(500)), f(None)]);
        let seen = [
            incident(99, Some(1.0), 5, None),
            incident(400, Some(2.0), 50, Some(1)),
            incident(498, Some(3.0), 10, None),
            incident(600, None, 1, Some(2)),
        ];
        for (row, i) in seen.iter().enumerate() {
            held.see(row, i);
        }
        let rows: Vec<Option<usize>> = held.held().iter().map(|h| h.map(|h| h.row)).collect();
        assert_eq!(rows, [Some(0), Some(1), Some(3)]);
    }
}
