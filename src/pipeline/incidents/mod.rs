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

/// A run's incidents and what was checked on the way.
#[derive(Debug, Clone, Serialize)]
pub struct Explained {
    /// Every incident, in time order.
    pub incidents: Vec<Incident>,
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
        self.incidents.iter().max_by(|a, b| Incident::by_cost(a, b))
    }

    /// One line for the console and the paper's report.
    pub fn describe_worst(&self) -> String {
        match self.worst() {
            None => "no incident".to_owned(),
            Some(i) => format!(
                "{} incident(s); worst: {} at {:.3} s for {:.1} ms, caused by {} ({}), peak \
                 deviation {}, recovered {}",
                self.incidents.len(),
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

/// Finds, explains and costs the incidents of the run in `dir`.
pub fn find(dir: &Path, options: Options) -> anyhow::Result<Explained> {
    let mut run = RunRecord::read(dir)?;
    let flags = ticks::flag(&run, options.threshold_ticks);
    // The loop's windows, then each fault outside the loop as an incident of its own.
    let mut windows: Vec<([u64; 2], Option<usize>)> =
        flags.windows(&run, GAP).into_iter().map(|w| (w, None)).collect();
    for (i, f) in run.faults.iter().enumerate().filter(|(_, f)| !ticks::in_loop(&f.role)) {
        windows.push((ticks::fault_ticks(&run, f), Some(i)));
    }
    windows.sort_by_key(|(w, _)| w[0]);
    run.keep_sched(&windows.iter().map(|(w, _)| *w).collect::<Vec<_>>());
    let medians = cause::stage_medians(&run, &flags);
    // The longest windows are costed.
    let mut by_length: Vec<usize> = (0..windows.len()).collect();
    by_length.sort_by_key(|i| std::cmp::Reverse(windows[*i].0[1] - windows[*i].0[0]));
    let mut costed = vec![false; windows.len()];
    for i in by_length.into_iter().take(MAX_COSTED) {
        costed[i] = true;
    }
    let starts: Vec<u64> = windows.iter().map(|(w, _)| w[0]).collect();
    let pass = cost::law_pass(&run, &starts)?;
    let mut incidents = Vec::with_capacity(windows.len());
    for (i, (w, outside)) in windows.iter().enumerate() {
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
        let cost = costed[i]
            .then(|| {
                cost::cost(&run, &flags, *w, pass.before[i], &pass.propagated, outside.is_none())
            })
            .flatten();
        incidents.push(Incident {
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
        });
    }
    Ok(Explained {
        incidents,
        threshold_s: flags.threshold_s,
        median_delay_s: flags.median_delay_s,
        law_reproduced: [pass.same, pass.computed],
        realtime: run.realtime(),
        kernel_view: run.kernel_view,
        traced: run.traced,
    })
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
    let found = find(dir, options)?;
    report::write(dir, &found)?;
    Ok(found)
}
