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
/// The most incidents whose cost is computed (the longest ones); the others are listed
/// without it.
pub const MAX_COSTED: usize = 200;

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
    fn new(faults: &[load::FaultRow]) -> Self {
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

/// Finds, explains and costs the incidents of the run in `dir`, handing each to `row` as
/// it is found, in time order.
pub fn find(
    dir: &Path,
    options: Options,
    row: &mut dyn FnMut(&Incident) -> anyhow::Result<()>,
) -> anyhow::Result<Explained> {
    let mut run = RunRecord::read(dir)?;
    let flags = ticks::flag(&run, options.threshold_ticks);
    // The loop's windows, then each fault outside the loop as an incident of its own.
    let mut windows: Vec<([u64; 2], Option<usize>)> =
        flags.windows(&run, GAP).into_iter().map(|w| (w, None)).collect();
    for (i, f) in run.faults.iter().enumerate().filter(|(_, f)| !ticks::in_loop(&f.role)) {
        windows.push((ticks::fault_ticks(&run, f), Some(i)));
    }
    windows.sort_by_key(|(w, _)| w[0]);
    run.keep_trace(&windows.iter().map(|(w, _)| *w).collect::<Vec<_>>());
    let medians = cause::stage_medians(&run, &flags);
    // The longest windows are costed.
    let mut by_length: Vec<usize> = (0..windows.len()).collect();
    by_length.sort_by_key(|i| std::cmp::Reverse(windows[*i].0[1] - windows[*i].0[0]));
    let mut costed = vec![false; windows.len()];
    for i in by_length.into_iter().take(MAX_COSTED) {
        costed[i] = true;
    }
    let starts: Vec<u64> =
        (windows.iter().zip(&costed)).filter(|(_, c)| **c).map(|(w, _)| w.0[0]).collect();
    let pass = cost::law_pass(&run, &starts)?;
    let mut befores = pass.before.iter();
    let mut held = FaultsHeld::new(&run.faults);
    let mut found = Explained {
        count: windows.len(),
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
    for (i, (w, outside)) in windows.iter().enumerate() {
        run.sched_for(*w);
        let fault = outside.or_else(|| cause::fault_of(&run, *w));
        let (c, all, misses) = match outside {
            Some(f) => {
                let c = cause::with_kernel(&run, cause::fault_cause(&run, &run.faults[*f]), *w);
                (c, ticks::FAULT, 0)
            }
            None => {
                let all = flags.all(&run, *w);
                let misses =
                    (w[0]..=w[1]).filter(|k| flags.get(&run, *k) & ticks::MISS != 0).count();
                (cause::cause(&run, &flags, &medians, *w), all, misses as u64)
            }
        };
        let law = if costed[i] { befores.next().copied() } else { None };
        let cost = law
            .and_then(|law| cost::cost(&run, &flags, *w, law, &pass.propagated, outside.is_none()));
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
        let f = |kill_tick| load::FaultRow {
            role: "controller".into(),
            kind: "kill".into(),
            detail: String::new(),
            kill_s: 0.0,
            kill_tick,
            restart_s: None,
            ended_s: None,
            signal: None,
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
