//! The `monitor` process: subscribes to state, reference and torque, joins them by tick
//! into the same `trace.csv` rows as `rotorloop sim`, and records the per-hop latency
//! histograms.
//!
//! It is passive: it has no event listener (publishers never wait for it or wake it), it
//! polls its large ring buffers every `--poll-us`, and if it falls behind the oldest
//! samples are overwritten: it counts the ticks lost and says so in the report.
//!
//! Every sample is validated before it is used ([`StateSample::validate`] and its
//! siblings). A rejected sample is a fault event in the report (`wire_faults`, with
//! topic, tick and reason, and `wire_rejected` counts together with the plant's and
//! the controller's own); a row whose state or reference was rejected is not written.

use std::fs::File;
use std::io::{BufWriter, IsTerminal, Write};
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Args;
use glam::DVec3;
use iceoryx2::prelude::ZeroCopySend;
use rotorloop_common::Actuation;
use rotorloop_common::ipc::{MAX_BUFFER, Topic, now_ns, shutdown_requested};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::wire::{
    FLAG_LAST, FLAG_REALTIME, ReferenceSample, StateSample, TorqueSample,
};
use rotorloop_monitor::figures::tracking_figures;
use rotorloop_monitor::latency::{Hop, HopStats, Latency};
use rotorloop_monitor::{Metrics, Recorder, TraceWriter};
use serde::Serialize;

use super::{Mode, PlantEnd, RoleArgs, SeqCounter};
use crate::sim::write_json;

/// `monitor` arguments.
#[derive(Debug, Clone, Args)]
pub struct MonitorArgs {
    #[command(flatten)]
    pub role: RoleArgs,
    /// Output directory for trace, histograms, logs, plots and summary.
    #[arg(long)]
    pub out: PathBuf,
    /// Print a live status line on stderr.
    #[arg(long)]
    pub status: bool,
    /// Poll period (µs).
    #[arg(long, allow_negative_numbers = true, default_value_t = 2000, value_parser = clap::value_parser!(u64).range(50..=100_000))]
    pub poll_us: u64,
}

const RING: usize = 16_384;
const MAX_GAPS: usize = 8;
/// After the plant's last state, this long without any new sample settles the rows still
/// open: their missing samples are not coming.
const END_QUIET_NS: u64 = 5_000_000_000;

/// What a restarted monitor needs to continue the same report.
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("rotorloop::MonitorResume_v3")]
#[repr(C)]
struct MonitorResume {
    next_row: u64,
    rows: u64,
    rows_lost: u64,
    restarts: u64,
    first_err: f64,
    drift_max: f64,
    metrics: [f64; rotorloop_monitor::metrics::METRICS_STATE_LEN],
    counts: [u64; 6],
    rejected: [u64; 3],
    gaps: [[u64; 2]; MAX_GAPS],
    n_gaps: u64,
}

#[derive(Debug, Clone, Copy, Default)]
struct Slot {
    state: Option<StateSample>,
    reference: Option<ReferenceSample>,
    torque: Option<TorqueSample>,
    /// The tick of a torque sample that arrived here and was rejected.
    torque_rejected: Option<u64>,
}

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

/// A sample the monitor rejected.
#[derive(Debug, Clone, Serialize)]
pub struct WireFaultEvent {
    /// `state`, `reference` or `torque`.
    pub topic: &'static str,
    /// The sample's tick.
    pub tick: u64,
    /// `non-finite`, `absurd` or `non-orthonormal`.
    pub kind: &'static str,
    /// The reason, naming the field.
    pub detail: String,
}

/// Most wire fault events kept in the report.
const MAX_FAULT_EVENTS: usize = 64;

/// `summary.json` of a multi-process run.
#[derive(Debug, Clone, Serialize)]
pub struct RunSummary {
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
    /// Rows the monitor could not assemble (samples lost or never published).
    pub rows_lost: u64,
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
    pub subscribers: std::collections::BTreeMap<String, SubscriberCounts>,
    /// Per hop (ns).
    pub hops: std::collections::BTreeMap<String, HopStats>,
    /// Attitude error at the first and last row (deg).
    pub err_deg_initial: f64,
    /// See `err_deg_initial`.
    pub err_deg_final: f64,
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
    pub wire_rejected: std::collections::BTreeMap<String, u64>,
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
}

/// Runs the monitor until it has the last row, or a termination signal.
pub fn run(args: &MonitorArgs) -> anyhow::Result<()> {
    let role = &args.role;
    let scenario = role.scenario()?;
    role.setup("monitor");
    let domain = role.open_domain()?;
    let node = domain.node("monitor").context("monitor")?;
    // Subscribe to the state last: the plant starts when it sees its state subscribers,
    // so everything else must already be connected by then.
    let refs = domain
        .inbox::<ReferenceSample>(&node, Topic::Reference, MAX_BUFFER, false)
        .context("monitor")?;
    let torques =
        domain.inbox::<TorqueSample>(&node, Topic::Torque, MAX_BUFFER, false).context("monitor")?;
    let states =
        domain.inbox::<StateSample>(&node, Topic::State, MAX_BUFFER, false).context("monitor")?;

    let resume_slot = ResumeSlot::<MonitorResume>::open(&domain, "monitor").context("monitor")?;
    let plant_end = PlantEnd::open(&domain).context("monitor")?;
    let ticks = scenario.ticks();
    let out = &args.out;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let summary_path = out.join("summary.json");
    let _ = std::fs::remove_file(&summary_path);
    let trace_path = out.join("trace.csv");
    let timing_path = out.join("timing.csv");
    // A restart continues the report in the same directory.
    let resumed = resume_slot.load().filter(|r| r.next_row <= ticks && trace_path.exists());
    let open = |path: &std::path::Path| {
        std::fs::OpenOptions::new()
            .create(true)
            .append(resumed.is_some())
            .write(true)
            .truncate(resumed.is_none())
            .open(path)
            .with_context(|| format!("cannot open {}", path.display()))
    };
    let buffered = |f: File| BufWriter::with_capacity(1 << 20, f);
    let mut trace = match resumed {
        Some(_) => TraceWriter::append(buffered(open(&trace_path)?)),
        None => TraceWriter::new(buffered(open(&trace_path)?))?,
    };
    let mut timing = buffered(open(&timing_path)?);
    if resumed.is_none() {
        writeln!(timing, "tick,state_publish_ns,applied_torque_tick,flags")?;
    }

    let actuation = scenario.actuation();
    let params = scenario.plant_params(actuation);
    let init = rotorloop_plant::Body::new(params, scenario.plant_init).state();
    let mut metrics = match &resumed {
        Some(r) => Metrics::restore(params, &r.metrics),
        None => Metrics::new(params, &init).with_disturbance(scenario.disturbance),
    };
    let torque_limit = rotorloop_common::wire::TorqueSample::absurd_limit(
        scenario.limits_for(actuation).rotor_torque,
    );
    let mut rejected = resumed.map_or([0u64; 3], |r| r.rejected);
    let mut wire_faults: Vec<WireFaultEvent> = Vec::new();
    let mut note_fault = |topic: &'static str, tick: u64, f: rotorloop_common::wire::WireFault| {
        if wire_faults.len() < MAX_FAULT_EVENTS {
            wire_faults.push(WireFaultEvent { topic, tick, kind: f.kind(), detail: f.to_string() });
        }
    };
    let mut rec = Recorder::new(ticks + 1);
    let mut latency =
        Latency::new(out, now_ns(), resumed.is_some()).context("monitor: interval logs")?;

    let mut slots = vec![Slot::default(); RING];
    let (mut s_seq, mut r_seq, mut t_seq) =
        (SeqCounter::default(), SeqCounter::default(), SeqCounter::default());
    let mut next = 0u64;
    let mut rows = 0u64;
    let mut rows_lost = 0u64;
    let (mut first_err, mut last_err, mut drift_max) = (f64::NAN, f64::NAN, 0.0f64);
    let mut gaps: Vec<[u64; 2]> = Vec::new();
    let mut restarts = 0u64;
    let mut gap_pending = false;
    let mut rows_at_flush = 0u64;
    if let Some(r) = resumed {
        next = r.next_row;
        rows = r.rows;
        rows_lost = r.rows_lost;
        first_err = r.first_err;
        drift_max = r.drift_max;
        restarts = r.restarts + 1;
        gaps = r.gaps[..(r.n_gaps as usize).min(MAX_GAPS)].to_vec();
        let c = r.counts;
        let last = next.saturating_sub(1);
        s_seq = SeqCounter::resume(c[0], c[1], last);
        r_seq = SeqCounter::resume(c[2], c[3], last);
        t_seq = SeqCounter::resume(c[4], c[5], last);
        gap_pending = true;
        eprintln!("monitor: restarted; continuing the report from tick {next}");
    }
    let (mut inputs_seen, mut last_input_ns) = (0u64, now_ns());
    let mut first_wake: Option<u64> = None;
    let mut last_state: Option<StateSample> = None;
    let mut last_torque: Option<TorqueSample> = None;
    let mut last_status = now_ns();
    let status = args.status && std::io::stderr().is_terminal();

    loop {
        while let Some(s) = states.take()? {
            s_seq.see(s.tick);
            // Counters and flags are integers: usable even from a rejected sample.
            if last_state.is_none_or(|l| s.tick >= l.tick) {
                last_state = Some(s);
            }
            if let Err(f) = s.validate() {
                rejected[0] += 1;
                note_fault("state", s.tick, f);
                continue;
            }
            first_wake.get_or_insert(s.wake_ns);
            slots[s.tick as usize % RING].state = Some(s);
        }
        while let Some(r) = refs.take()? {
            r_seq.see(r.tick);
            if let Err(f) = r.validate() {
                rejected[1] += 1;
                note_fault("reference", r.tick, f);
                continue;
            }
            slots[r.tick as usize % RING].reference = Some(r);
        }
        while let Some(t) = torques.take()? {
            t_seq.see(t.tick);
            if let Err(f) = t.validate(torque_limit) {
                rejected[2] += 1;
                note_fault("torque", t.tick, f);
                slots[t.tick as usize % RING].torque_rejected = Some(t.tick);
                continue;
            }
            slots[t.tick as usize % RING].torque = Some(t);
            last_torque = Some(t);
        }
        if gap_pending {
            // The first state a restarted monitor sees tells how much it missed.
            let first = slots
                .iter()
                .filter_map(|sl| sl.state)
                .map(|st| st.tick)
                .filter(|t| *t >= next)
                .min();
            if let Some(first) = first {
                if first > next {
                    gaps.push([next, first - 1]);
                    rows_lost += first - next;
                    next = first;
                }
                gap_pending = false;
            }
        }
        let newest = s_seq.last().unwrap_or(0);
        let newest_torque = t_seq.last();
        let ended = last_state.is_some_and(|s| s.flags & FLAG_LAST != 0);
        let counts = s_seq.received + r_seq.received + t_seq.received;
        if counts != inputs_seen {
            (inputs_seen, last_input_ns) = (counts, now_ns());
        }
        // The plant has ended (seen here, or in its resume slot by a monitor restarted
        // after the end) and nothing has arrived for a while: what is missing now never
        // comes (a role killed at the very end, say), so settle the rest.
        let drained = now_ns() - last_input_ns > END_QUIET_NS && (ended || plant_end.ended());
        let stopping = shutdown_requested() || drained;
        // Emit every row that is complete, in tick order.
        while next <= ticks {
            let slot = slots[next as usize % RING];
            let s = slot.state.filter(|s| s.tick == next);
            let r = slot.reference.filter(|r| r.tick == next);
            let t = slot.torque.filter(|t| t.tick == next);
            let following = if next < ticks {
                slots[(next + 1) as usize % RING].state.filter(|s| s.tick == next + 1)
            } else {
                None
            };
            // A rejected torque settles its row too: no other sample of that tick comes.
            let t_rejected = slot.torque_rejected == Some(next);
            // The controller answers the newest state and skips older ones (a loaded
            // machine): a torque of a later tick means none comes for this one.
            let torque_settled = t.is_some()
                || t_rejected
                || newest >= next + 2
                || newest_torque.is_some_and(|l| l > next)
                || stopping;
            let next_settled =
                following.is_some() || next == ticks || newest > next + 1 || stopping;
            let (Some(s), Some(r)) = (s, r) else {
                // Lost for good: newer states exist and the ring moved on, or the run ended.
                if newest >= next + (RING as u64) / 2 || ((ended || stopping) && newest > next) {
                    rows_lost += 1;
                    next += 1;
                    continue;
                }
                break;
            };
            if !(torque_settled && next_settled)
                || (next == ticks && t.is_none() && !t_rejected && !stopping && !ended)
            {
                break;
            }
            let x = s.body_state();
            let rd = r.reference_state();
            let nan = DVec3::splat(f64::NAN);
            let (u, tau) = match t {
                Some(t) if t.computed() => (
                    if actuation == Actuation::Internal {
                        DVec3::from_array(t.rotor_torque_nm)
                    } else {
                        DVec3::ZERO
                    },
                    DVec3::from_array(t.body_torque_nm),
                ),
                _ => (nan, nan),
            };
            let row = metrics.observe(
                next,
                s.t_s,
                &x,
                &rd,
                u,
                tau,
                DVec3::from_array(s.applied_rotor_torque_nm),
            );
            trace.write(&row).with_context(|| format!("cannot write {}", trace_path.display()))?;
            writeln!(
                timing,
                "{next},{},{},{}",
                s.publish_ns, s.applied_torque_tick as i64, s.flags
            )?;
            rec.record(&row, next == ticks);
            if rows == 0 {
                first_err = row.err_deg;
            }
            last_err = row.err_deg;
            drift_max = drift_max.max(row.h_drift_rel);
            rows += 1;

            let at = s.publish_ns;
            if let Some(t) = t {
                latency.record(
                    Hop::StateTransport,
                    t.state_recv_ns.saturating_sub(s.publish_ns),
                    at,
                )?;
                latency.record(
                    Hop::ControllerCompute,
                    t.publish_ns.saturating_sub(t.state_recv_ns),
                    at,
                )?;
                if let Some(f) = following.filter(|f| f.applied_torque_tick == next) {
                    latency.record(
                        Hop::TorqueTransport,
                        f.applied_torque_recv_ns.saturating_sub(t.publish_ns),
                        at,
                    )?;
                    latency.record(
                        Hop::SenseToActuate,
                        f.applied_torque_recv_ns.saturating_sub(s.publish_ns),
                        at,
                    )?;
                }
            }
            if s.flags & FLAG_REALTIME != 0 {
                latency.record(Hop::TickLateness, s.wake_ns.saturating_sub(s.deadline_ns), at)?;
            }
            latency.record(Hop::ReferenceLead, s.publish_ns.saturating_sub(r.publish_ns), at)?;
            next += 1;
        }
        if drained && next <= ticks {
            // The run is over and these rows never came together: lost. A monitor
            // restarted after the end saw none of them: that is its gap.
            if gap_pending {
                gaps.push([next, ticks]);
                gap_pending = false;
            }
            rows_lost += ticks + 1 - next;
            next = ticks + 1;
        }
        if rows > rows_at_flush {
            // Durable first, then recorded: a monitor killed now loses nothing that its
            // resume slot claims was written.
            trace.flush().with_context(|| format!("cannot write {}", trace_path.display()))?;
            timing.flush()?;
            rows_at_flush = rows;
            let mut g = [[0u64; 2]; MAX_GAPS];
            for (d, src) in g.iter_mut().zip(&gaps) {
                *d = *src;
            }
            resume_slot.store(&MonitorResume {
                next_row: next,
                rows,
                rows_lost,
                restarts,
                first_err,
                drift_max,
                metrics: metrics.save(),
                counts: [
                    s_seq.received,
                    s_seq.lost,
                    r_seq.received,
                    r_seq.lost,
                    t_seq.received,
                    t_seq.lost,
                ],
                rejected,
                gaps: g,
                n_gaps: gaps.len().min(MAX_GAPS) as u64,
            });
        }
        if status && now_ns() - last_status > 500_000_000 {
            last_status = now_ns();
            let p99 = latency.histogram(Hop::SenseToActuate).value_at_quantile(0.99) as f64 / 1e3;
            let misses = last_state.map_or(0, |s| s.misses);
            let t = last_state.map_or(0.0, |s| s.t_s);
            let mut e = std::io::stderr().lock();
            let _ = write!(
                e,
                "\r  t = {t:8.3} s   error {last_err:.3e}°   sense-to-actuate p99 {p99:9.1} µs   misses {misses}   "
            );
            let _ = e.flush();
        }
        if next > ticks || stopping {
            break;
        }
        std::thread::sleep(Duration::from_micros(args.poll_us));
    }
    if status {
        eprint!("\r{:100}\r", "");
    }
    trace.finish().with_context(|| format!("cannot write {}", trace_path.display()))?;
    timing.flush()?;
    if next > ticks {
        resume_slot.clear(); // finished: a later monitor in this domain starts a new report
    }
    let mut files = vec!["trace.csv".to_owned(), "timing.csv".to_owned()];
    files.extend(latency.finish().context("monitor: histograms")?);
    files.extend(Hop::ALL.iter().map(|h| format!("{}.hlog", h.name())));
    files.extend(latency.plots(&scenario.file.name)?);
    files.extend(tracking_figures(out, &scenario.file.name, &rec, None)?);

    let last = last_state;
    let achieved = match (first_wake, last) {
        (Some(w0), Some(l)) if l.tick > 0 && l.wake_ns > w0 => {
            l.tick as f64 / ((l.wake_ns - w0) as f64 / 1e9)
        }
        _ => 0.0,
    };
    let mut subscribers = std::collections::BTreeMap::new();
    subscribers.insert("monitor.state".to_owned(), s_seq.into());
    subscribers.insert("monitor.reference".to_owned(), r_seq.into());
    // Torque ticks the controller skipped are not losses: count against what it published.
    let monitor_torque_lost = last_torque.map_or(0, |t| t.published.saturating_sub(t_seq.received));
    subscribers.insert(
        "monitor.torque".to_owned(),
        SubscriberCounts { received: t_seq.received, lost: monitor_torque_lost },
    );
    if let (Some(l), Some(t)) = (last, last_torque) {
        // The plant's counters are as of its last state sample, before the last torque.
        let published_before = t.published - u64::from(t.tick == l.tick);
        subscribers.insert(
            "plant.torque".to_owned(),
            SubscriberCounts {
                received: l.torques_received,
                lost: published_before.saturating_sub(l.torques_received),
            },
        );
    }
    if let Some(t) = last_torque {
        subscribers.insert(
            "controller.state".to_owned(),
            SubscriberCounts { received: t.states_received, lost: t.states_lost },
        );
    }
    let mut wire_rejected = std::collections::BTreeMap::new();
    for (name, n) in ["monitor.state", "monitor.reference", "monitor.torque"].iter().zip(rejected) {
        wire_rejected.insert((*name).to_owned(), n);
    }
    wire_rejected.insert("plant.torque".to_owned(), last.map_or(0, |s| s.torques_rejected));
    wire_rejected
        .insert("controller.state".to_owned(), last_torque.map_or(0, |t| t.states_rejected));
    wire_rejected.insert(
        "controller.reference".to_owned(),
        last_torque.map_or(0, |t| t.references_rejected),
    );
    let saturated_ticks = last.map_or(0, |s| s.saturated_ticks);
    let summary = RunSummary {
        name: scenario.file.name.clone(),
        scenario: scenario.file.clone(),
        mode: match role.mode {
            Mode::Lockstep => "lockstep".into(),
            Mode::Realtime => "realtime".into(),
        },
        wait: role.wait.to_string(),
        ticks,
        trace_rows: rows,
        rows_lost,
        monitor_kept_up: rows_lost == 0
            && s_seq.lost == 0
            && r_seq.lost == 0
            && monitor_torque_lost == 0
            && rows == ticks + 1,
        states_skipped_by_controller: last_torque.map_or(0, |t| t.states_skipped),
        misses: last.map_or(0, |s| s.misses),
        reference_misses: last_torque.map_or(0, |t| t.reference_misses),
        rate_hz: scenario.file.run.rate_hz,
        achieved_rate_hz: achieved,
        subscribers,
        hops: Hop::ALL.iter().map(|h| (h.name().to_owned(), latency.stats(*h))).collect(),
        err_deg_initial: first_err,
        err_deg_final: last_err,
        momentum_drift_rel_max: drift_max,
        completed: next > ticks,
        monitor_gaps: gaps.clone(),
        monitor_restarts: restarts,
        safe_mode_ticks: last.map_or(0, |s| s.safe_mode_ticks),
        wire_rejected,
        wire_faults,
        saturated_ticks,
        saturated_fraction: saturated_ticks as f64 / ticks as f64,
        faults: Vec::new(),
        resources: None,
        files,
    };
    println!("{}", console_summary(&summary));
    write_json(&summary_path, &summary)?;
    Ok(())
}

/// A cyclictest-like summary: one line per hop with count/min/avg/p99/max in µs.
pub fn console_summary(s: &RunSummary) -> String {
    let mut t = format!(
        "{} ({}, {} wait): {} ticks, {} rows, {} lost, {} misses, achieved {:.3} Hz of {} Hz, error {:.4}° → {:.3e}°\n",
        s.name,
        s.mode,
        s.wait,
        s.ticks,
        s.trace_rows,
        s.rows_lost,
        s.misses,
        s.achieved_rate_hz,
        s.rate_hz,
        s.err_deg_initial,
        s.err_deg_final
    );
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
