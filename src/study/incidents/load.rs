//! What the incidents of a run are made from, read from its directory: the scenario as
//! run and the launcher's faults (`summary.json`), the roles' flight records (`flight/`:
//! every state, torque and reference sample with their stamps) and the launcher's
//! scheduler samples (`sched.csv`, where there are some).

use std::path::Path;

use rotorloop_common::flight::{FlightLog, Stream};
use rotorloop_common::role::UsageError;
use rotorloop_common::scenario::Scenario;
use rotorloop_common::wire::{ReferenceSample, StateSample, TorqueSample};
use serde::Deserialize;

/// A fault the launcher saw (a row of `summary.json`'s `faults`).
#[derive(Debug, Clone, Deserialize)]
pub struct FaultRow {
    /// The role.
    pub role: String,
    /// `kill`, `stop`, `killed`, `crash`, `exited`, `hang`, `link-lost`.
    pub kind: String,
    /// In words.
    #[serde(default)]
    pub detail: String,
    /// When (s after the first state's publish).
    pub kill_s: f64,
    /// Restarted or continued (s).
    pub restart_s: Option<f64>,
    /// A stop's end (s).
    #[serde(default)]
    pub ended_s: Option<f64>,
    /// The signal.
    #[serde(default)]
    pub signal: Option<String>,
}

/// A fault of the `--fault` schedule (`summary.json`'s `fault_schedule`): what the launcher
/// was asked to do, the delays the controller applies itself among them.
#[derive(Debug, Clone, Deserialize)]
pub struct Scheduled {
    /// The role.
    pub role: String,
    /// `kill`, `stop` or `delay`.
    pub kind: String,
    /// Its start (s after tick 0).
    pub at_s: f64,
    /// Its end, if any (s).
    pub until_s: Option<f64>,
    /// A delay's seconds.
    pub value_s: Option<f64>,
}

/// One row of `sched.csv` (`crate::run::sched`).
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
    /// The scheduler samples (empty without `sched.csv`).
    pub sched: Vec<SchedRow>,
    /// The kernel's scheduler trace (empty without `--trace-sched`).
    pub trace: Vec<super::trace::Traced>,
    /// The first state's publish (ns): the origin of the faults' times.
    pub t0_ns: u64,
    /// Each tick's grid time (its publish in lockstep; a tick without a state: the one
    /// before it), ns.
    grid_ns: Vec<u64>,
}

fn bad(dir: &Path, what: impl std::fmt::Display) -> UsageError {
    UsageError(format!("{}: {what}", dir.display()))
}

impl RunRecord {
    /// Reads the run in `dir`; an error names the file that is missing or foreign.
    pub fn read(dir: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(dir.join("summary.json"))
            .map_err(|e| bad(dir, format!("summary.json: {e} (is this a run directory?)")))?;
        let summary: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| bad(dir, format!("summary.json: {e}")))?;
        let file = serde_json::from_value(summary["scenario"].clone())
            .map_err(|e| bad(dir, format!("summary.json has no scenario as run: {e}")))?;
        let scenario = Scenario::from_file(file).map_err(UsageError::from)?;
        let list = |key: &str| summary.get(key).cloned().unwrap_or(serde_json::json!([]));
        let faults: Vec<FaultRow> = serde_json::from_value(list("faults"))
            .map_err(|e| bad(dir, format!("summary.json faults: {e}")))?;
        let schedule: Vec<Scheduled> = serde_json::from_value(list("fault_schedule"))
            .map_err(|e| bad(dir, format!("summary.json fault_schedule: {e}")))?;
        let flight = dir.join("flight");
        let plant_state = Stream::PlantState.path(&flight);
        if !plant_state.exists() {
            return Err(bad(dir, format!("no flight record {}", plant_state.display())).into());
        }
        let states = FlightLog::<StateSample>::read(&flight, Stream::PlantState)?;
        let torques = FlightLog::<TorqueSample>::read(&flight, Stream::ControllerTorque)
            .unwrap_or(FlightLog { records: Vec::new(), opens: 0, beyond: 0 });
        let references = FlightLog::<ReferenceSample>::read(&flight, Stream::Reference)
            .unwrap_or(FlightLog { records: Vec::new(), opens: 0, beyond: 0 });
        let last = (states.records.len() as u64).saturating_sub(1).min(scenario.ticks());
        let t0_ns = states.records.iter().flatten().map(|s| s.publish_ns).min().unwrap_or(0);
        let sched = read_sched(&dir.join("sched.csv"));
        let mut grid_ns = Vec::with_capacity(last as usize + 1);
        for k in 0..=last {
            let before = grid_ns.last().copied().unwrap_or(0);
            let t = states.get(k).map_or(before, |s| match s.deadline_ns {
                0 => s.publish_ns,
                d => d,
            });
            grid_ns.push(t.max(before));
        }
        Ok(Self {
            grid_ns,
            dt: scenario.dt(),
            scenario,
            last,
            states,
            torques,
            references,
            faults,
            schedule,
            sched,
            trace: super::trace::read(&dir.join("sched-trace.txt")),
            t0_ns,
        })
    }

    /// A lockstep run of these records alone (no faults, schedule or kernel figures),
    /// each tick's grid time its state's publish: for the incidents' unit tests.
    #[cfg(test)]
    pub(crate) fn of(
        scenario: Scenario,
        states: Vec<StateSample>,
        torques: Vec<TorqueSample>,
    ) -> Self {
        fn log<T>(v: Vec<T>) -> FlightLog<T> {
            FlightLog { records: v.into_iter().map(Some).collect(), opens: 1, beyond: 0 }
        }
        let grid_ns: Vec<u64> = states.iter().map(|s| s.publish_ns).collect();
        Self {
            dt: scenario.dt(),
            scenario,
            last: (states.len() as u64).saturating_sub(1),
            t0_ns: grid_ns.first().copied().unwrap_or(0),
            grid_ns,
            states: log(states),
            torques: log(torques),
            references: FlightLog { records: Vec::new(), opens: 0, beyond: 0 },
            faults: Vec::new(),
            schedule: Vec::new(),
            sched: Vec::new(),
            trace: Vec::new(),
        }
    }

    /// Whether the run was in real time (its states carry grid times).
    pub fn realtime(&self) -> bool {
        self.states.records.iter().flatten().any(|s| s.deadline_ns > 0)
    }

    /// The state of tick `k`.
    pub fn state(&self, k: u64) -> Option<&StateSample> {
        self.states.get(k)
    }

    /// The controller's answer to state `k`.
    pub fn torque(&self, k: u64) -> Option<&TorqueSample> {
        self.torques.get(k)
    }

    /// The newest tick whose grid time (its publish in lockstep) is at or before `ns`.
    pub fn tick_at_ns(&self, ns: u64) -> u64 {
        self.grid_ns.partition_point(|t| *t <= ns).saturating_sub(1) as u64
    }

    /// The grid time of tick `k` (its publish in lockstep; ns).
    pub fn grid_ns(&self, k: u64) -> u64 {
        self.grid_ns.get(k as usize).or(self.grid_ns.last()).copied().unwrap_or(0)
    }

    /// The time of tick `k` (s after tick 0).
    pub fn t_s(&self, k: u64) -> f64 {
        k as f64 * self.dt
    }
}

/// `sched.csv`'s rows (none where it is missing; a row that does not parse is skipped).
pub fn read_sched(path: &Path) -> Vec<SchedRow> {
    let Ok(text) = std::fs::read_to_string(path) else { return Vec::new() };
    text.lines()
        .skip(1)
        .filter_map(|l| {
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
        .collect()
}
