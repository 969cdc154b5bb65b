//! What the monitor process writes while a run goes on: each joined row becomes a
//! `trace.csv` row (the same columns and code as `rotorloop sim`) and a `timing.csv` row,
//! feeds the figures' recorder, and records its per-hop latencies from the timestamps the
//! samples carry. A restarted monitor appends to the same files.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::Context;
use glam::DVec3;
use rotorloop_common::wire::{FLAG_REALTIME, StateSample};
use rotorloop_common::{Actuation, Scenario};

use crate::figures::tracking_figures;
use crate::latency::{Hop, Latency};
use crate::policy::{JoinedRow, MonitorResume, RowJoiner};
use crate::{Metrics, Recorder, TraceWriter};

type Buffered = BufWriter<File>;

/// The files of one run's report, open for appending rows.
#[derive(Debug)]
pub struct Recording {
    out: PathBuf,
    trace: TraceWriter<Buffered>,
    timing: Buffered,
    metrics: Metrics,
    recorder: Recorder,
    /// Per-hop histograms and interval logs.
    pub latency: Latency,
    actuation: Actuation,
    ticks: u64,
    rows_at_flush: u64,
    /// Attitude error of the first row of the run (deg).
    pub first_err: f64,
    /// Attitude error of the last row written (deg).
    pub last_err: f64,
    /// Largest relative spatial-momentum drift.
    pub drift_max: f64,
    /// When the live status line was last drawn (`None`: never).
    status_at_ns: Option<u64>,
}

impl Recording {
    /// Opens the report in `out` for `scenario`, starting at `now_ns`: new files, or, when
    /// `slot` (the monitor's resume slot) holds an unfinished report whose trace is there,
    /// the predecessor's, appended to (a restart); then it also returns that slot content.
    pub fn open(
        out: &Path,
        scenario: &Scenario,
        slot: Option<MonitorResume>,
        now_ns: u64,
    ) -> anyhow::Result<(Self, Option<MonitorResume>)> {
        std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
        let _ = std::fs::remove_file(out.join("summary.json"));
        let resumed =
            slot.filter(|r| r.next_row <= scenario.ticks() && out.join("trace.csv").exists());
        let resumed = resumed.as_ref();
        let open = |name: &str| {
            let path = out.join(name);
            let f = std::fs::OpenOptions::new()
                .create(true)
                .append(resumed.is_some())
                .write(true)
                .truncate(resumed.is_none())
                .open(&path)
                .with_context(|| format!("cannot open {}", path.display()))?;
            anyhow::Ok(BufWriter::with_capacity(1 << 20, f))
        };
        let trace = match resumed {
            Some(_) => TraceWriter::append(open("trace.csv")?),
            None => TraceWriter::new(open("trace.csv")?)?,
        };
        let mut timing = open("timing.csv")?;
        if resumed.is_none() {
            writeln!(timing, "tick,state_publish_ns,applied_torque_tick,flags")?;
        }
        let actuation = scenario.actuation();
        let params = scenario.plant_params(actuation);
        // The initial state exactly as the plant's integrator holds it.
        let init = rotorloop_plant::Body::new(params, scenario.plant_init).state();
        let metrics = match resumed {
            Some(r) => Metrics::restore(params, &r.metrics),
            None => Metrics::new(params, &init).with_disturbance(scenario.disturbance),
        };
        let latency =
            Latency::new(out, now_ns, resumed.is_some()).context("monitor: interval logs")?;
        let rec = Self {
            out: out.to_owned(),
            trace,
            timing,
            metrics,
            recorder: Recorder::new(scenario.ticks() + 1),
            latency,
            actuation,
            ticks: scenario.ticks(),
            rows_at_flush: resumed.map_or(0, |r| r.rows),
            first_err: resumed.map_or(f64::NAN, |r| r.first_err),
            last_err: f64::NAN,
            drift_max: resumed.map_or(0.0, |r| r.drift_max),
            status_at_ns: None,
        };
        Ok((rec, resumed.copied()))
    }

    /// Writes one joined row and records its latencies.
    pub fn write(&mut self, j: &JoinedRow) -> anyhow::Result<()> {
        let (s, k) = (&j.state, j.tick);
        let nan = DVec3::splat(f64::NAN);
        let (u, tau) = match j.torque {
            Some(t) if t.computed() => (
                if self.actuation == Actuation::Internal {
                    DVec3::from_array(t.rotor_torque_nm)
                } else {
                    DVec3::ZERO
                },
                DVec3::from_array(t.body_torque_nm),
            ),
            _ => (nan, nan),
        };
        let applied = DVec3::from_array(s.applied_rotor_torque_nm);
        let row = self.metrics.observe(
            k,
            s.t_s,
            &s.body_state(),
            &j.reference.reference_state(),
            u,
            tau,
            applied,
        );
        let trace_path = || self.out.join("trace.csv").display().to_string();
        self.trace.write(&row).with_context(|| format!("cannot write {}", trace_path()))?;
        writeln!(self.timing, "{k},{},{},{}", s.publish_ns, s.applied_torque_tick as i64, s.flags)?;
        self.recorder.record(&row, k == self.ticks);
        if j.first {
            self.first_err = row.err_deg;
        }
        self.last_err = row.err_deg;
        self.drift_max = self.drift_max.max(row.h_drift_rel);
        self.record_latencies(j)
    }

    fn record_latencies(&mut self, j: &JoinedRow) -> anyhow::Result<()> {
        let (s, at, l) = (&j.state, j.state.publish_ns, &mut self.latency);
        if let Some(t) = j.torque {
            l.record(Hop::StateTransport, t.state_recv_ns.saturating_sub(s.publish_ns), at)?;
            l.record(Hop::ControllerCompute, t.publish_ns.saturating_sub(t.state_recv_ns), at)?;
            if let Some(f) = j.following.filter(|f| f.applied_torque_tick == j.tick) {
                l.record(
                    Hop::TorqueTransport,
                    f.applied_torque_recv_ns.saturating_sub(t.publish_ns),
                    at,
                )?;
                l.record(
                    Hop::SenseToActuate,
                    f.applied_torque_recv_ns.saturating_sub(s.publish_ns),
                    at,
                )?;
            }
        }
        if s.flags & FLAG_REALTIME != 0 {
            l.record(Hop::TickLateness, s.wake_ns.saturating_sub(s.deadline_ns), at)?;
        }
        l.record(Hop::ReferenceLead, s.publish_ns.saturating_sub(j.reference.publish_ns), at)?;
        Ok(())
    }

    /// If rows were written since the last call: makes them durable, then returns what the
    /// resume slot should now say (durable first, then recorded: a monitor killed now
    /// loses nothing that its resume slot claims was written).
    pub fn flush(&mut self, joiner: &RowJoiner) -> anyhow::Result<Option<MonitorResume>> {
        if joiner.rows() <= self.rows_at_flush {
            return Ok(None);
        }
        self.trace
            .flush()
            .with_context(|| format!("cannot write {}", self.out.join("trace.csv").display()))?;
        self.timing.flush()?;
        self.rows_at_flush = joiner.rows();
        Ok(Some(joiner.save(self.first_err, self.drift_max, self.metrics.save())))
    }

    /// Rewrites the live status line on stderr, at most twice a second: run time, attitude
    /// error, sense-to-actuate p99, misses (of the newest state `last`).
    pub fn status_line(&mut self, last: Option<StateSample>, now_ns: u64) {
        if self.status_at_ns.is_some_and(|t| now_ns - t < 500_000_000) {
            return;
        }
        self.status_at_ns = Some(now_ns);
        let p99 = self.latency.histogram(Hop::SenseToActuate).value_at_quantile(0.99) as f64 / 1e3;
        let (t, misses, err) =
            last.map_or((0.0, 0, self.last_err), |s| (s.t_s, s.misses, self.last_err));
        let mut e = std::io::stderr().lock();
        let _ = write!(
            e,
            "\r  t = {t:8.3} s   error {err:.3e}°   sense-to-actuate p99 {p99:9.1} µs   misses {misses}   "
        );
        let _ = e.flush();
    }

    /// Closes the files and writes the histograms, interval logs and figures; returns the
    /// files written.
    pub fn finish(&mut self, title: &str) -> anyhow::Result<Vec<String>> {
        if self.status_at_ns.is_some() {
            eprint!("\r{:100}\r", ""); // clear the status line
        }
        let trace_path = self.out.join("trace.csv");
        self.trace.flush().with_context(|| format!("cannot write {}", trace_path.display()))?;
        self.timing.flush()?;
        let mut files = vec!["trace.csv".to_owned(), "timing.csv".to_owned()];
        files.extend(self.latency.finish().context("monitor: histograms")?);
        files.extend(Hop::ALL.iter().map(|h| format!("{}.hlog", h.name())));
        files.extend(self.latency.plots(title)?);
        files.extend(tracking_figures(&self.out, title, &self.recorder, None)?);
        Ok(files)
    }
}
