//! `summary.json` of a multi-process run ([`RunSummary`]), assembled from what the
//! [`RowJoiner`] saw (its counts and the counters that the plant's and the controller's
//! own samples carry) and what the [`Recording`] measured, and its console form.

use std::collections::BTreeMap;
use std::path::Path;

use rotorloop_common::output::write_json;
use rotorloop_common::role::args::{Mode, RoleArgs};
use rotorloop_common::role::count::SeqCounter;
use rotorloop_common::scenario::Scenario;
use serde::Serialize;

use crate::latency::{Hop, HopStats};
use crate::policy::{MAX_FAULT_EVENTS, RowJoiner, WireFaultEvent};
use crate::recording::{Recording, with_fallback};
use crate::stages::StageStats;

/// Received and lost samples of one subscriber.
#[derive(Debug, Clone, Copy, Serialize, Default)]
pub struct SubscriberCounts {
    /// Samples taken.
    pub received: u64,
    /// Samples known lost (gaps in the tick sequence).
    pub lost: u64,
}

impl From<SeqCounter> for SubscriberCounts {
    fn from(s: SeqCounter) -> Self {
        Self { received: s.received, lost: s.lost }
    }
}

/// `summary.json` of a multi-process run.
#[derive(Debug, Clone, Serialize)]
pub struct RunSummary {
    /// `summary.json`'s layout version (`rotorloop_common::summary_json`: its every key).
    pub layout_version: u32,
    /// Scenario name.
    pub name: String,
    /// The scenario as run.
    pub scenario: rotorloop_common::scenario::ScenarioFile,
    /// `lockstep` or `realtime`.
    pub mode: String,
    /// Wait strategy.
    pub wait: String,
    /// Plant steps in the run.
    pub ticks: u64,
    /// Rows written to `trace.csv` (ticks + 1 when complete).
    pub trace_rows: u64,
    /// Rows missing from `trace.csv`: with flight records, ticks no role recorded (a
    /// sample never published); without, also what the live monitor missed.
    pub rows_lost: u64,
    /// Rows the live monitor itself missed (its gaps, samples it fell behind on): what
    /// a report from the live view alone would have lost.
    pub live_rows_lost: u64,
    /// The flight records the report was assembled from (absent: run without them).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub flight: Option<FlightSummary>,
    /// Whether the monitor saw every tick.
    pub monitor_kept_up: bool,
    /// Ticks on which the plant had no fresh torque in time (real time).
    pub misses: u64,
    /// Ticks answered without a reference sample at hand (controller).
    pub reference_misses: u64,
    /// State samples the controller took but did not answer (a newer one was there).
    pub states_skipped_by_controller: u64,
    /// Requested rate (Hz).
    pub rate_hz: f64,
    /// Achieved tick rate (Hz): ticks over the plant's wall time from tick 0 to the last.
    pub achieved_rate_hz: f64,
    /// Per subscriber: samples received and lost.
    pub subscribers: BTreeMap<String, SubscriberCounts>,
    /// Per hop (ns).
    pub hops: BTreeMap<String, HopStats>,
    /// The stage breakdown of sense-to-actuate (ns; `crate::stages`), in tick order.
    pub stages: Vec<StageStats>,
    /// A run over several hosts: the hosts, and the hops not computed (two clocks).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cross_host: Option<crate::hosts::CrossHost>,
    /// Attitude error at the first and last row (deg).
    pub err_deg_initial: f64,
    /// See `err_deg_initial`.
    pub err_deg_final: f64,
    /// Root mean square of the attitude error over the rows recorded (deg): how well the
    /// loop tracked over the whole run, not only where it ended. Rows the monitor missed
    /// while it was down (`monitor_gaps`) are not in it.
    pub err_deg_rms: f64,
    /// Largest relative spatial-momentum drift.
    pub momentum_drift_rel_max: f64,
    /// Whether the run reached its last tick (false after a signal).
    pub completed: bool,
    /// Ticks the monitor missed while it was down, `[first, last]` (restarted monitor).
    pub monitor_gaps: Vec<[u64; 2]>,
    /// How often the monitor was restarted during the run.
    pub monitor_restarts: u64,
    /// Ticks the plant spent in safe mode.
    pub safe_mode_ticks: u64,
    /// Samples rejected by validation, per receiver (`plant.torque`, `controller.state`,
    /// `controller.reference`, `monitor.state`, `monitor.reference`, `monitor.torque`).
    pub wire_rejected: BTreeMap<String, u64>,
    /// The first rejected samples the monitor saw (this monitor life), with the reason.
    pub wire_faults: Vec<WireFaultEvent>,
    /// Ticks whose rotor torque the actuator limits changed.
    pub saturated_ticks: u64,
    /// `saturated_ticks / ticks`.
    pub saturated_fraction: f64,
    /// Faults injected by the launcher (filled in by `rotorloop run --fault`).
    pub faults: Vec<serde_json::Value>,
    /// Resident memory of each process (filled in by `rotorloop run`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resources: Option<serde_json::Value>,
    /// Files written.
    pub files: Vec<String>,
    /// The first tick missing from `trace.csv`, when the output could not be written
    /// (a full disk): the rows from it on were not written, though the figures above
    /// count them.
    pub trace_incomplete_from_tick: Option<u64>,
    /// What could not be written where it belonged, and why (empty: everything was).
    pub storage_errors: Vec<String>,
    /// Where the report was written, when not in the output directory (a fallback).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub report_dir: Option<String>,
}

/// The monitor's receivers in `wire_rejected`, in the order of [`RowJoiner::rejected`].
const MONITOR_RECEIVERS: [&str; 3] = ["monitor.state", "monitor.reference", "monitor.torque"];

/// Adds to `s` (a report from the flight records) the rejected samples only the live
/// monitor `live` saw: those of no role's record, such as another publisher's on the
/// topic (a torque for a tick the loop had not reached, say). Per topic the larger count
/// of the two (the records' when the live monitor missed some), and the live fault
/// events the records do not have, first (the records' then, at most
/// [`MAX_FAULT_EVENTS`] in all).
pub(crate) fn add_live_rejections(s: &mut RunSummary, live: &RowJoiner) {
    for (name, n) in MONITOR_RECEIVERS.iter().zip(live.rejected) {
        let count = s.wire_rejected.entry((*name).to_owned()).or_default();
        *count = (*count).max(n);
    }
    let key = |e: &WireFaultEvent| (e.topic, e.tick, e.kind);
    let recorded = std::mem::take(&mut s.wire_faults);
    let unrecorded = live.wire_faults.iter().filter(|e| !recorded.iter().any(|f| key(f) == key(e)));
    let mut events: Vec<WireFaultEvent> = unrecorded.cloned().collect();
    events.extend(recorded);
    events.truncate(MAX_FAULT_EVENTS);
    s.wire_faults = events;
}

/// The summary of a run of `role`'s mode and wait strategy, `files` written.
pub fn summary(
    scenario: &Scenario,
    role: &RoleArgs,
    j: &RowJoiner,
    rec: &Recording,
    files: Vec<String>,
) -> RunSummary {
    let ticks = scenario.ticks();
    let (last, last_torque) = (j.last_state(), j.last_torque());
    let achieved = match (j.first_wake(), last) {
        (Some(w0), Some(l)) if l.tick > 0 && l.wake_ns > w0 => {
            l.tick as f64 / ((l.wake_ns - w0) as f64 / 1e9)
        }
        _ => 0.0,
    };
    let mut subscribers = monitor_counts(j);
    let counts = |received, lost| SubscriberCounts { received, lost };
    if let (Some(l), Some(t)) = (last, last_torque) {
        // The plant's counters are as of its last state sample, before the last torque.
        let published_before = t.published - u64::from(t.tick == l.tick);
        let lost = published_before.saturating_sub(l.torques_received);
        subscribers.insert("plant.torque".to_owned(), counts(l.torques_received, lost));
    }
    if let Some(t) = last_torque {
        subscribers.insert("controller.state".to_owned(), counts(t.states_received, t.states_lost));
    }
    let mut wire_rejected: BTreeMap<String, u64> =
        MONITOR_RECEIVERS.iter().zip(j.rejected).map(|(n, c)| ((*n).to_owned(), c)).collect();
    wire_rejected.insert("plant.torque".to_owned(), last.map_or(0, |s| s.torques_rejected));
    wire_rejected
        .insert("controller.state".to_owned(), last_torque.map_or(0, |t| t.states_rejected));
    wire_rejected.insert(
        "controller.reference".to_owned(),
        last_torque.map_or(0, |t| t.references_rejected),
    );
    let saturated_ticks = last.map_or(0, |s| s.saturated_ticks);
    let rows = j.rows();
    RunSummary {
        layout_version: rotorloop_common::summary_json::SUMMARY_JSON_VERSION,
        name: scenario.file.name.clone(),
        scenario: scenario.file.clone(),
        mode: if role.mode == Mode::Lockstep { "lockstep" } else { "realtime" }.to_owned(),
        wait: role.wait.to_string(),
        ticks,
        trace_rows: rows,
        rows_lost: j.rows_lost(),
        live_rows_lost: j.rows_lost(),
        flight: None,
        monitor_kept_up: kept_up(j, ticks),
        states_skipped_by_controller: last_torque.map_or(0, |t| t.states_skipped),
        misses: last.map_or(0, |s| s.misses),
        reference_misses: last_torque.map_or(0, |t| t.reference_misses),
        rate_hz: scenario.file.run.rate_hz,
        achieved_rate_hz: achieved,
        subscribers,
        hops: Hop::ALL.iter().map(|h| (h.name().to_owned(), rec.latency.stats(*h))).collect(),
        stages: rec.stages.stats(),
        cross_host: rec.hosts.cross_host(),
        err_deg_initial: rec.first_err,
        err_deg_final: rec.last_err,
        err_deg_rms: rec.err_rms(),
        momentum_drift_rel_max: rec.drift_max,
        completed: j.done(),
        monitor_gaps: j.gaps().to_vec(),
        monitor_restarts: j.restarts(),
        safe_mode_ticks: last.map_or(0, |s| s.safe_mode_ticks),
        wire_rejected,
        wire_faults: j.wire_faults.clone(),
        saturated_ticks,
        saturated_fraction: saturated_ticks as f64 / ticks as f64,
        faults: Vec::new(),
        resources: None,
        files,
        trace_incomplete_from_tick: rec.loss.as_ref().map(|l| l.from_tick),
        storage_errors: rec.storage_errors.clone(),
        report_dir: None,
    }
}

/// What the monitor's subscribers received and lost (`monitor.state`, …).
pub fn monitor_counts(j: &RowJoiner) -> BTreeMap<String, SubscriberCounts> {
    let [s_seq, r_seq, t_seq] = j.seq;
    let mut subscribers = BTreeMap::new();
    subscribers.insert("monitor.state".to_owned(), s_seq.into());
    subscribers.insert("monitor.reference".to_owned(), r_seq.into());
    // Torque ticks the controller skipped are not losses: count against what it published.
    let lost = j.last_torque().map_or(0, |t| t.published.saturating_sub(t_seq.received));
    let torque = SubscriberCounts { received: t_seq.received, lost };
    subscribers.insert("monitor.torque".to_owned(), torque);
    subscribers
}

/// Whether the live monitor saw every tick of `0..=ticks`.
pub fn kept_up(j: &RowJoiner, ticks: u64) -> bool {
    let c = monitor_counts(j);
    j.rows_lost() == 0 && c.values().all(|c| c.lost == 0) && j.rows() == ticks + 1
}

/// A cyclictest-like summary: one line per hop with count/min/avg/p99/max in µs.
pub fn console_summary(s: &RunSummary) -> String {
    let RunSummary { name, mode, wait, ticks, trace_rows, rows_lost, misses, rate_hz, .. } = s;
    let (hz, e0, e1, rms) = (s.achieved_rate_hz, s.err_deg_initial, s.err_deg_final, s.err_deg_rms);
    let mut t = format!(
        "{name} ({mode}, {wait} wait): {ticks} ticks, {trace_rows} rows, {rows_lost} lost, {misses} misses, achieved {hz:.3} Hz of {rate_hz} Hz, error {e0:.4}° → {e1:.3e}° (rms {rms:.3}°)\n"
    );
    for e in &s.storage_errors {
        t.push_str(&format!("storage: {e}\n"));
    }
    let rejected: u64 = s.wire_rejected.values().sum();
    if rejected > 0 || s.saturated_ticks > 0 || s.safe_mode_ticks > 0 {
        t.push_str(&format!(
            "rejected samples {:?}; saturated {:.2} % of ticks; {} ticks in safe mode\n",
            s.wire_rejected,
            100.0 * s.saturated_fraction,
            s.safe_mode_ticks
        ));
    }
    for hop in Hop::ALL {
        let h = s.hops.get(hop.name()).copied().unwrap_or_default();
        let us = |v: u64| v as f64 / 1e3;
        t.push_str(&format!(
            "T:{:<20} C:{:>9} Min:{:>9.1} Avg:{:>9.1} P99:{:>9.1} Max:{:>10.1} (µs)\n",
            hop.name(),
            h.count,
            us(h.min),
            h.mean / 1e3,
            us(h.p99),
            us(h.max)
        ));
    }
    t
}

/// Writes `summary.json` into `out`, or into `fallback` where `out` cannot take it, or
/// (nowhere to write) onto stderr, so that it is never lost.
pub fn write_summary(out: &Path, fallback: &Path, summary: &RunSummary) -> anyhow::Result<()> {
    let write = |d: &Path| write_json(&d.join("summary.json"), summary);
    match with_fallback(out, fallback, write) {
        Ok(((), d)) if d != out => eprintln!("monitor: summary.json written to {}", d.display()),
        Ok(_) => {}
        Err(e) => {
            eprintln!("monitor: summary.json not written ({e:#}); here it is:");
            eprintln!("{}", serde_json::to_string_pretty(summary)?);
        }
    }
    Ok(())
}

/// What the flight records held, per stream (in `summary.json`).
#[derive(Debug, Clone, Serialize, Default)]
pub struct FlightSummary {
    /// The directory of the records.
    pub dir: String,
    /// Whether the report was assembled from them (else: the monitor's live view, and
    /// `error` says why).
    pub assembled: bool,
    /// Why the records could not be used.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Per stream: ticks recorded, ticks of the run missing, how often it was opened.
    pub streams: Vec<StreamSummary>,
    /// Torques taken from the plant's record because the controller's had none.
    pub torques_from_plant: u64,
    /// What the record lost to a machine crash or to damage (absent where nothing).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lost: Option<LostSummary>,
}

/// What a run's record lost (`summary.json` `flight.lost`): to a crash of the machine (the
/// rings on tmpfs gone: the ticks after the last durable journal frame) or to damage (a
/// file skipped or read in part, named in the stream's `problems`).
#[derive(Debug, Clone, Serialize)]
pub struct LostSummary {
    /// `machine crash`, `record damaged`, or `machine crash, record damaged`.
    pub reason: &'static str,
    /// The newest tick of the plant's states on disk (`None`: none).
    pub last_tick_recorded: Option<u64>,
    /// Ticks up to it with no state recorded, `[first, last]` (the first 16 ranges).
    pub ticks: Vec<[u64; 2]>,
    /// How many such ranges there are in all.
    pub ranges: u64,
    /// The run's ticks after it, `[first, last]`: lost with the crash where the run had
    /// reached them, else never run (`None`: the record reaches the run's last tick).
    pub after_last: Option<[u64; 2]>,
}

/// One stream's record.
#[derive(Debug, Clone, Serialize)]
pub struct StreamSummary {
    /// `plant-state`, `plant-torque`, `controller-torque`, `reference`.
    pub stream: &'static str,
    /// Ticks recorded.
    pub records: u64,
    /// Ticks `0..=last` with no record, `[first, last]` (the first 16 ranges).
    pub missing: Vec<[u64; 2]>,
    /// How often the file was opened for writing (1 + the writer's restarts).
    pub opens: u64,
    /// Samples whose tick lay beyond the file (not recorded).
    pub beyond: u64,
    /// What in its files could not be read (a torn or foreign segment, samples for ticks
    /// beyond the run), in words; the stream was read as far as it is sound.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub problems: Vec<String>,
}
