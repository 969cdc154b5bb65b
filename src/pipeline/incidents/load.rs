//! What the incidents of a run are made from, read from its directory: the scenario as
//! run and the launcher's faults (`summary.json`), the roles' flight records (`flight/`:
//! every state, torque and reference sample with their stamps) and the launcher's
//! scheduler samples (`sched.csv`, where there are some).

use std::path::Path;

use rotorloop_common::flight::{FlightLog, SPARE_SLOTS, Stream};
use rotorloop_common::role::UsageError;
use rotorloop_common::scenario::Scenario;
use rotorloop_common::wire::{ReferenceSample, StateSample, TorqueSample};
use rotorloop_monitor::summary::{FaultRow, Scheduled, Summary};

/// One row of `sched.csv` (`crate::pipeline::sched_csv`).
#[derive(Debug, Clone, PartialEq)]
pub struct SchedRow {
    /// When (monotonic ns).
    pub t_ns: u64,
    /// The role.
    pub role: String,
    /// Its pid.
    pub pid: u32,
    /// `/proc/PID/stat`'s state letter.
    pub state: char,
    /// The CPU it last ran on.
    pub cpu: u32,
    /// Time on a CPU so far (ns).
    pub on_cpu_ns: u64,
    /// Time runnable but waiting for a CPU so far (ns).
    pub wait_ns: u64,
    /// The machine's steal time so far (ns).
    pub steal_ns: u64,
}

/// A finished run, as its incidents need it.
#[derive(Debug)]
pub struct RunRecord {
    /// The scenario as run.
    pub scenario: Scenario,
    /// Its tick (s).
    pub dt: f64,
    /// The last tick with a state.
    pub last: u64,
    /// Every state the plant published.
    pub states: FlightLog<StateSample>,
    /// Every torque the controller published, by the state tick it answers.
    pub torques: FlightLog<TorqueSample>,
    /// Every reference sample.
    pub references: FlightLog<ReferenceSample>,
    /// The faults the launcher saw.
    pub faults: Vec<FaultRow>,
    /// The `--fault` schedule.
    pub schedule: Vec<Scheduled>,
    /// The scheduler samples near the incident being explained (empty without
    /// `sched.csv`, and until [`RunRecord::sched_for`] names it: the file has a row per
    /// role per millisecond of the run, which is not held whole).
    pub sched: Vec<SchedRow>,
    /// Whether `sched.csv` has any row.
    pub kernel_view: bool,
    /// The kernel's scheduler trace near the incident being explained, in time order
    /// (empty without `--trace-sched`, and until [`RunRecord::trace_for`] names it).
    pub trace: Vec<super::trace::Traced>,
    /// Whether the run has a scheduler trace with any event (`--trace-sched`).
    pub traced: bool,
    /// `sched-trace.txt`, read by [`RunRecord::trace_for`].
    trace_path: std::path::PathBuf,
    /// The events of `sched-trace.txt` not read yet ([`RunRecord::trace_for`]).
    trace_left: Left<super::trace::Traced>,
    /// The first state's publish (ns): the origin of the faults' times.
    pub t0_ns: u64,
    /// Whether any state carries a grid time (a real-time run).
    realtime: bool,
    /// `sched.csv`, read by [`RunRecord::sched_for`].
    sched_path: std::path::PathBuf,
    /// The grid time of every [`GRID_STRIDE`]-th tick (the largest of the states' up to
    /// it: ticks without a state take the one before), ns; the ticks between are read
    /// from the records when asked for.
    grid_marks: Vec<u64>,
    /// The rows of `sched.csv` not read yet ([`RunRecord::sched_for`]).
    sched_left: Left<SchedRow>,
    /// The last [`RunRecord::next_answer`] found: `(k, j)`, no answer in `k + 1 .. j`
    /// and one for `j`. The ticks of an incident ask in order, so a window in which the
    /// controller was silent reads its records once, not once per tick.
    next_found: std::cell::Cell<Option<(u64, u64)>>,
    /// Each fault's ticks ([`super::ticks::fault_ticks`]), found once: each takes up to
    /// three scans of a grid stride of states, and every window of the loop asks for all.
    fault_spans: std::cell::OnceCell<Vec<[u64; 2]>>,
}

/// Ticks between two of [`RunRecord`]'s grid marks (a day at 1 kHz: 84 000 marks).
const GRID_STRIDE: u64 = 1024;

/// Blocks each stream's reader keeps for the incidents, within [`KEPT_BYTES`]: a
/// counterfactual goes up to a minute past its incident ([`super::cost`]: 15 packed
/// chunks of 4096 ticks at 1 kHz), and the next incident's starts back near its own. With
/// the readers' default (three chunks of states) each incident unpacked again every chunk
/// the one before it had walked: 90 % of the analysis of a loaded run was unpacking.
const KEPT_BLOCKS: usize = 24;
/// Bytes each stream's reader keeps for the incidents: 22 chunks of plant states.
const KEPT_BYTES: usize = 48 << 20;

/// A state's grid time: its deadline in real time, its publish in lockstep.
fn grid_of(s: &StateSample) -> u64 {
    match s.deadline_ns {
        0 => s.publish_ns,
        d => d,
    }
}

fn bad(dir: &Path, what: impl std::fmt::Display) -> UsageError {
    UsageError(format!("{}: {what}", dir.display()))
}

impl RunRecord {
    /// Reads the run in `dir`; an error names the file that is missing or foreign.
    pub fn read(dir: &Path) -> anyhow::Result<Self> {
        Self::read_visiting(dir, &mut |_, _| {})
    }

    /// [`RunRecord::read`], handing each state `0..=last` that is there to `visit` (with
    /// its tick) on the one pass over the states it makes: what the incidents' first
    /// figures need of the states alone, without another pass over a day of records.
    pub fn read_visiting(
        dir: &Path,
        visit: &mut dyn FnMut(u64, &StateSample),
    ) -> anyhow::Result<Self> {
        let summary = Summary::read(dir).map_err(|e| UsageError(e.to_string()))?;
        let scenario = summary.scenario().map_err(|e| bad(dir, e))?;
        let flight = dir.join("flight");
        let limit = scenario.ticks().saturating_add(SPARE_SLOTS);
        // Whatever of the states is sound (a missing or torn ring, segment or journal frame
        // is skipped: its ticks are missing); refused only where nothing of it is.
        let states = FlightLog::<StateSample>::read(&flight, Stream::PlantState, limit)
            .map_err(|e| bad(dir, format!("no plant state record can be read: {e}")))?
            .keeping(KEPT_BLOCKS, KEPT_BYTES);
        // The controller's answers from its own record; a controller of the user's own
        // (`--controller-cmd`) keeps none, and its answers are then the plant's record of
        // the torques it received (the same samples, less any lost on the way).
        let torques = FlightLog::<TorqueSample>::read(&flight, Stream::ControllerTorque, limit)
            .ok()
            .filter(|t| t.last().is_some())
            .or_else(|| FlightLog::read(&flight, Stream::PlantTorque, limit).ok())
            .unwrap_or_else(FlightLog::empty)
            .keeping(KEPT_BLOCKS, KEPT_BYTES);
        let references = FlightLog::<ReferenceSample>::read(&flight, Stream::Reference, limit)
            .unwrap_or_else(|_| FlightLog::empty())
            .keeping(KEPT_BLOCKS, KEPT_BYTES);
        let last = states.last().unwrap_or(0).min(scenario.ticks());
        // One pass over the states: the origin, the mode, and the grid marks.
        let (mut t0_ns, mut realtime, mut grid) = (u64::MAX, false, 0u64);
        let mut grid_marks = Vec::new();
        for k in 0..=last {
            if let Some(s) = states.get(k) {
                t0_ns = t0_ns.min(s.publish_ns);
                realtime |= s.deadline_ns > 0;
                grid = grid.max(grid_of(&s));
                visit(k, &s);
            }
            if k % GRID_STRIDE == 0 {
                grid_marks.push(grid);
            }
        }
        let t0_ns = if t0_ns == u64::MAX { 0 } else { t0_ns };
        let sched_path = crate::pipeline::sched_csv::path(dir);
        let kernel_view = sched_rows(&sched_path).next().is_some();
        let trace_path = dir.join("sched-trace.txt");
        Ok(Self {
            grid_marks,
            realtime,
            dt: scenario.dt(),
            scenario,
            last,
            states,
            torques,
            references,
            faults: summary.faults,
            schedule: summary.fault_schedule,
            sched: Vec::new(),
            kernel_view,
            sched_path,
            trace: Vec::new(),
            traced: super::trace::events(&trace_path).next().is_some(),
            trace_path,
            trace_left: Left::default(),
            t0_ns,
            next_found: Default::default(),
            fault_spans: Default::default(),
            sched_left: Left::default(),
        })
    }

    /// A lockstep run of these records alone (no faults, schedule or kernel figures),
    /// each tick's grid time its state's publish, each torque at its own tick: for the
    /// incidents' unit tests.
    #[cfg(test)]
    pub(crate) fn of(
        scenario: Scenario,
        states: Vec<StateSample>,
        torques: Vec<TorqueSample>,
    ) -> Self {
        let mut grid = 0;
        let grid_marks = (states.iter().enumerate())
            .filter_map(|(k, s)| {
                grid = grid.max(s.publish_ns);
                (k as u64 % GRID_STRIDE == 0).then_some(grid)
            })
            .collect();
        Self {
            dt: scenario.dt(),
            scenario,
            last: (states.len() as u64).saturating_sub(1),
            t0_ns: states.first().map_or(0, |s| s.publish_ns),
            next_found: Default::default(),
            fault_spans: Default::default(),
            sched_left: Left::default(),
            realtime: false,
            grid_marks,
            states: FlightLog::of(states),
            torques: FlightLog::of_ticks(torques),
            references: FlightLog::empty(),
            faults: Vec::new(),
            schedule: Vec::new(),
            sched: Vec::new(),
            kernel_view: false,
            sched_path: Default::default(),
            trace: Vec::new(),
            traced: false,
            trace_path: Default::default(),
            trace_left: Left::default(),
        }
    }

    /// Whether the run was in real time (its states carry grid times).
    pub fn realtime(&self) -> bool {
        self.realtime
    }

    /// The state of tick `k`.
    pub fn state(&self, k: u64) -> Option<StateSample> {
        self.states.get(k)
    }

    /// The controller's answer to state `k`.
    pub fn torque(&self, k: u64) -> Option<TorqueSample> {
        self.torques.get(k)
    }

    /// The controller's first answer after state `k`, within 10 000 ticks.
    pub fn next_answer(&self, k: u64) -> Option<TorqueSample> {
        if let Some((_, j)) = self.next_found.get().filter(|(from, j)| *from <= k && k < *j) {
            return self.torque(j);
        }
        let (j, t) = (k + 1..(k + 10_000).min(self.last + 1))
            .find_map(|j| self.torque(j).map(|t| (j, t)))?;
        self.next_found.set(Some((k, j)));
        Some(t)
    }

    /// The grid times of the ticks from mark `m` on (up to the next mark and the last
    /// tick), each the largest of the states' so far, with their ticks.
    fn grid_from_mark(&self, m: usize) -> impl Iterator<Item = (u64, u64)> + '_ {
        let first = m as u64 * GRID_STRIDE;
        let end = (first + GRID_STRIDE).min(self.last + 1);
        let mut grid = self.grid_marks.get(m).copied().unwrap_or(0);
        (first..end.max(first + 1)).map(move |k| {
            if let Some(s) = self.states.get(k) {
                grid = grid.max(grid_of(&s));
            }
            (k, grid)
        })
    }

    /// The newest tick whose grid time (its publish in lockstep) is at or before `ns`.
    pub fn tick_at_ns(&self, ns: u64) -> u64 {
        let m = self.grid_marks.partition_point(|t| *t <= ns);
        let Some(m) = m.checked_sub(1) else { return 0 };
        self.grid_from_mark(m).take_while(|(_, t)| *t <= ns).last().map_or(0, |(k, _)| k)
    }

    /// The grid time of tick `k` (its publish in lockstep; ns).
    pub fn grid_ns(&self, k: u64) -> u64 {
        let k = k.min(self.last);
        let m = (k / GRID_STRIDE) as usize;
        self.grid_from_mark(m).take_while(|(j, _)| *j <= k).last().map_or(0, |(_, t)| t)
    }

    /// The ticks of each of the launcher's faults, in the order of [`Self::faults`].
    pub fn fault_spans(&self) -> &[[u64; 2]] {
        self.fault_spans.get_or_init(|| {
            self.faults.iter().map(|f| super::ticks::fault_ticks(self, f)).collect()
        })
    }

    /// The time of tick `k` (s after tick 0).
    pub fn t_s(&self, k: u64) -> f64 {
        k as f64 * self.dt
    }
}

/// `sched.csv`'s rows, a line at a time (none where it is missing; a row that does not
/// parse is skipped), from `sched.csv.zst` too (to where a frame cut short ends).
pub fn sched_rows(path: &Path) -> impl Iterator<Item = SchedRow> + use<> {
    use std::io::BufRead;
    let zst = path.extension().is_some_and(|e| e == "zst");
    let lines = std::fs::File::open(path).ok().and_then(|f| {
        let read: Box<dyn std::io::Read> = match zst {
            true => Box::new(zstd::stream::read::Decoder::new(f).ok()?),
            false => Box::new(f),
        };
        Some(std::io::BufReader::new(read).lines())
    });
    lines.into_iter().flatten().skip(1).map_while(Result::ok).filter_map(|l| {
        let f: Vec<&str> = l.split(',').collect();
        Some(SchedRow {
            t_ns: f.first()?.parse().ok()?,
            role: (*f.get(1)?).to_owned(),
            pid: f.get(2)?.parse().ok()?,
            state: f.get(3)?.chars().next()?,
            cpu: f.get(4)?.parse().ok()?,
            on_cpu_ns: f.get(5)?.parse().ok()?,
            wait_ns: f.get(6)?.parse().ok()?,
            steal_ns: f.get(7)?.parse().ok()?,
        })
    })
}

/// The rows of a file read forward (`sched.csv` by [`RunRecord::sched_for`],
/// `sched-trace.txt` by [`RunRecord::trace_for`]) after those read so far, opened at the
/// first call.
struct Left<T>(Option<std::iter::Peekable<Box<dyn Iterator<Item = T>>>>);

impl<T> Default for Left<T> {
    fn default() -> Self {
        Self(None)
    }
}

impl<T> std::fmt::Debug for Left<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(if self.0.is_some() { "Left(open)" } else { "Left" })
    }
}

/// How far out of time order `sched-trace.txt` is read ahead (ns): an event of one CPU
/// committed late comes after later ones of another, by far less than this.
const TRACE_REORDER_NS: u64 = 1_000_000_000;

impl RunRecord {
    /// The span of grid time (ns) whose kernel figures the incident `w` may need: a second
    /// either side of it.
    pub(super) fn near_ns(&self, w: [u64; 2]) -> [u64; 2] {
        let slack = 1_000_000_000 + (self.dt * 1e9) as u64;
        [self.grid_ns(w[0]).saturating_sub(slack), self.grid_ns(w[1] + 1) + slack]
    }

    /// Keeps the scheduler samples of `sched.csv` within a second of the incident `w`
    /// ([`RunRecord::sched`]), read forward from where the last call stopped: the
    /// incidents ask in the order of their first ticks, so the file is read once, a line
    /// at a time, and what is held is the rows near one incident (a row per role per
    /// millisecond: a soak's 80 549 incidents held most of its 105 MB `sched.csv`).
    pub fn sched_for(&mut self, w: [u64; 2]) {
        let [from, to] = self.near_ns(w);
        let gone = self.sched.partition_point(|r| r.t_ns < from);
        self.sched.drain(..gone);
        let path = &self.sched_path;
        let left = self.sched_left.0.get_or_insert_with(|| {
            let rows: Box<dyn Iterator<Item = SchedRow>> = Box::new(sched_rows(path));
            rows.peekable()
        });
        let mut sorted = true;
        while let Some(r) = left.next_if(|r| r.t_ns <= to) {
            if r.t_ns >= from {
                sorted &= self.sched.last().is_none_or(|l| l.t_ns <= r.t_ns);
                self.sched.push(r);
            }
        }
        // In time order (the file is; a stable sort keeps it so), for the bisection.
        if !sorted {
            self.sched.sort_by_key(|r| r.t_ns);
        }
    }

    /// Keeps the events of `sched-trace.txt` (`--trace-sched`) within a second of the
    /// incident `w` ([`RunRecord::trace`], in time order), read forward from where the last
    /// call stopped, as [`RunRecord::sched_for`] reads `sched.csv`: the file is read once,
    /// and what is held is the events near one incident (and up to a second read ahead),
    /// not those near every incident of the run.
    pub fn trace_for(&mut self, w: [u64; 2]) {
        if !self.traced {
            return;
        }
        let [from, to] = self.near_ns(w);
        self.trace.retain(|e| e.t_ns >= from);
        let path = &self.trace_path;
        let left = self.trace_left.0.get_or_insert_with(|| {
            let events: Box<dyn Iterator<Item = super::trace::Traced>> =
                Box::new(super::trace::events(path));
            events.peekable()
        });
        while let Some(e) = left.next_if(|e| e.t_ns <= to.saturating_add(TRACE_REORDER_NS)) {
            if e.t_ns >= from {
                self.trace.push(e);
            }
        }
        self.trace.sort_by_key(|e| e.t_ns);
    }
}

/// Closed spans `[from, to]`, merged where they overlap: the ticks a costed incident's
/// counterfactual can reach ([`super::cost::law_pass`]). Spans
/// added in the order of their starts merge as they come, so what is held is the merged
/// spans alone.
#[derive(Debug, Default)]
pub struct Spans {
    merged: Vec<[u64; 2]>,
}

impl Spans {
    /// Adds the span `s`.
    pub fn add(&mut self, s: [u64; 2]) {
        if self.merged.last().is_some_and(|m| s[0] < m[0]) {
            // Out of order (not as the incidents add them): merged again from scratch.
            let mut all = std::mem::take(&mut self.merged);
            all.push(s);
            all.sort_unstable();
            all.into_iter().for_each(|s| self.extend(s));
        } else {
            self.extend(s);
        }
    }

    /// Adds `s`, which starts at or after every span held.
    fn extend(&mut self, s: [u64; 2]) {
        match self.merged.last_mut() {
            Some(m) if s[0] <= m[1] => m[1] = m[1].max(s[1]),
            _ => self.merged.push(s),
        }
    }

    /// Whether a span holds `t`.
    pub fn contains(&self, t: u64) -> bool {
        let i = self.merged.partition_point(|s| s[0] <= t);
        i.checked_sub(1).is_some_and(|i| t <= self.merged[i][1])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Spans added one at a time, in order of their starts or not, merge as a sort and
    /// merge of all of them does; in order, what is held is the merged spans alone.
    #[test]
    fn spans_merge_as_they_come_as_a_sort_of_all_does() {
        let mut next = super::super::test_random(0x6a09_e667_f3bc_c908_u64);
        for round in 0..100 {
            let mut spans: Vec<[u64; 2]> = (0..next(60))
                .map(|_| {
                    let a = next(1000);
                    [a, a + next(40)]
                })
                .collect();
            if round % 2 == 0 {
                spans.sort_unstable();
            }
            let mut near = Spans::default();
            spans.iter().for_each(|s| near.add(*s));
            let mut all = spans.clone();
            all.sort_unstable();
            let mut want: Vec<[u64; 2]> = Vec::new();
            for s in all {
                match want.last_mut() {
                    Some(m) if s[0] <= m[1] => m[1] = m[1].max(s[1]),
                    _ => want.push(s),
                }
            }
            assert_eq!(near.merged, want, "round {round}: {spans:?}");
            for t in 0..1050 {
                let held = want.iter().any(|w| w[0] <= t && t <= w[1]);
                assert_eq!(near.contains(t), held, "round {round}, {t}");
            }
        }
    }

    /// A run of `ticks` states of `paper-zero`, tick `k` published at `(k + 1)` ms.
    fn run_of(ticks: u64) -> RunRecord {
        let scenario = Scenario::load("paper-zero").expect("built-in");
        let states = (0..ticks)
            .map(|k| {
                let mut s = StateSample::of(k, k as f64 * scenario.dt(), &scenario.plant_init);
                s.publish_ns = 1_000_000 * (k + 1);
                s
            })
            .collect();
        RunRecord::of(scenario, states, Vec::new())
    }

    /// Read forward incident by incident, `sched.csv` gives each incident every row within
    /// a second of it, in time order, and holds no row from before that second: what is
    /// held is bounded by one incident's neighbourhood, not by the run's incidents.
    #[test]
    fn the_kernel_rows_are_read_forward_incident_by_incident() {
        let ticks = 20_000u64;
        let mut run = run_of(ticks);
        let dir = tempfile::tempdir().expect("tempdir");
        let mut csv = String::from("t_ns,role,pid,state,cpu,on_cpu_ns,wait_ns,steal_ns\n");
        let mut all = Vec::new();
        for ms in 0..ticks + 100 {
            for (i, role) in ["plant", "controller"].iter().enumerate() {
                let t = ms * 1_000_000 + i as u64;
                csv += &format!("{t},{role},{},R,0,{ms},0,0\n", 10 + i);
                all.push((t, *role));
            }
        }
        run.sched_path = dir.path().join("sched.csv");
        std::fs::write(&run.sched_path, csv).expect("write");
        let windows =
            [[5, 5], [900, 1200], [1300, 1301], [4000, 9000], [9100, 9100], [19_990, 19_999]];
        let mut held_most = 0;
        for w in windows {
            run.sched_for(w);
            let [from, to] = run.near_ns(w);
            let want: Vec<(u64, &str)> =
                all.iter().filter(|(t, _)| (from..=to).contains(t)).copied().collect();
            let held: Vec<(u64, &str)> =
                run.sched.iter().map(|r| (r.t_ns, r.role.as_str())).collect();
            assert!(held.is_sorted(), "{w:?}: out of time order");
            assert!(
                held.first().is_some_and(|(t, _)| *t >= from),
                "{w:?}: a row before its second"
            );
            assert_eq!(&held[..want.len()], &want[..], "{w:?}: the rows near it");
            held_most = held_most.max(held.len());
        }
        // The longest incident (5001 ticks) and a second and a tick either side: 7003 ms
        // of two roles' rows, both ends included.
        assert!(held_most <= 2 * 7_004, "held {held_most} rows at once");
    }

    /// Read forward incident by incident, `sched-trace.txt` gives each incident every
    /// event within a second of it, in time order, though the file has pairs out of order
    /// (per-CPU buffers); what is held is one incident's neighbourhood and the second read
    /// ahead, not the events near every incident.
    #[test]
    fn the_trace_events_are_read_forward_incident_by_incident() {
        let ticks = 20_000u64;
        let mut run = run_of(ticks);
        let dir = tempfile::tempdir().expect("tempdir");
        let mut text = String::from("# tracer: nop\n");
        let mut all = Vec::new();
        for ms in 0..ticks + 100 {
            // Every other pair of events out of order, as a late commit on another CPU.
            let t = if ms % 4 == 1 {
                ms + 1
            } else if ms % 4 == 2 {
                ms - 1
            } else {
                ms
            } * 1_000_000;
            text += &format!(
                "  yes-9 [001] d..2. {}.{:09}: sched_switch: prev_comm=a prev_pid=1 \
                 prev_prio=120 prev_state=R ==> next_comm=b next_pid=2 next_prio=120\n",
                t / 1_000_000_000,
                t % 1_000_000_000
            );
            all.push(t);
        }
        all.sort_unstable();
        run.trace_path = dir.path().join("sched-trace.txt");
        std::fs::write(&run.trace_path, text).expect("write");
        run.traced = true;
        let windows = [[5, 5], [900, 1200], [1300, 1301], [4000, 9000], [19_990, 19_999]];
        let mut held_most = 0;
        for w in windows {
            run.trace_for(w);
            let [from, to] = run.near_ns(w);
            let want: Vec<u64> = all.iter().filter(|t| (from..=to).contains(*t)).copied().collect();
            let held: Vec<u64> = run.trace.iter().map(|e| e.t_ns).collect();
            assert!(held.is_sorted(), "{w:?}: out of time order");
            assert!(held.first().is_some_and(|t| *t >= from), "{w:?}: an event before its second");
            assert_eq!(&held[..want.len()], &want[..], "{w:?}: the events near it");
            held_most = held_most.max(held.len());
        }
        // The longest incident (5001 ticks), a second either side and a second read ahead.
        assert!(held_most <= 8_004, "held {held_most} events at once");
    }

    /// `sched.csv.zst` (`run --no-csv`) gives the rows `sched.csv` would, and one cut short
    /// by a launcher killed mid-run gives those before the cut: never a row that is not
    /// the file's, never an error.
    #[test]
    fn compressed_kernel_rows_read_as_the_plain_ones_and_as_far_as_a_cut_frame_goes() {
        let dir = tempfile::tempdir().expect("tempdir");
        let mut csv = String::from("t_ns,role,pid,state,cpu,on_cpu_ns,wait_ns,steal_ns\n");
        for ms in 0..50_000u64 {
            let wait = (ms * 7919) % 1_000_003;
            csv += &format!("{},plant,10,R,{},{ms},{wait},0\n", ms * 1_000_000, ms % 2);
        }
        std::fs::write(dir.path().join("sched.csv"), &csv).expect("plain");
        let zst = zstd::encode_all(csv.as_bytes(), 3).expect("zstd");
        std::fs::write(dir.path().join("sched.csv.zst"), &zst).expect("compressed");
        let row = |r: SchedRow| (r.t_ns, r.cpu, r.on_cpu_ns, r.wait_ns);
        let plain: Vec<_> = sched_rows(&dir.path().join("sched.csv")).map(row).collect();
        let packed: Vec<_> = sched_rows(&dir.path().join("sched.csv.zst")).map(row).collect();
        assert_eq!(plain.len(), 50_000);
        assert_eq!(packed, plain);
        // Where both are there the plain one is read; the compressed one alone otherwise.
        assert_eq!(crate::pipeline::sched_csv::path(dir.path()), dir.path().join("sched.csv"));
        std::fs::remove_file(dir.path().join("sched.csv")).expect("rm");
        assert_eq!(crate::pipeline::sched_csv::path(dir.path()), dir.path().join("sched.csv.zst"));
        std::fs::write(dir.path().join("sched.csv.zst"), &zst[..zst.len() * 2 / 3]).expect("cut");
        let cut: Vec<_> = sched_rows(&dir.path().join("sched.csv.zst")).map(row).collect();
        assert!(!cut.is_empty() && cut.len() < plain.len(), "{} rows", cut.len());
        assert_eq!(cut[..], plain[..cut.len()]);
    }
}
