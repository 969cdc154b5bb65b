//! What the monitor process writes while a run goes on: each joined row becomes a
//! `trace.csv` row (the same columns and code as `rotorloop sim`) and a `timing.csv` row,
//! feeds the figures' recorder, and records its per-hop latencies from the timestamps the
//! samples carry. A restarted monitor appends to the same files.
//!
//! **An observer never stops the loop.** When the output cannot be written (a full disk,
//! an I/O error, the directory removed), the recording stops appending rows and records
//! from which tick the trace is incomplete and why ([`StorageLoss`]); the metrics,
//! histograms and figures' data go on in memory. At the end the histograms, figures and
//! `summary.json` are written where possible: into the output directory (tried twice),
//! else into a fallback directory it names, else the summary goes to stderr.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Context;
use glam::DVec3;
use rotorloop_common::scenario::{Actuation, Scenario};
use rotorloop_common::wire::{FLAG_REALTIME, StateSample};
use serde::Serialize;

use crate::figures::Recorder;
use crate::figures::tracking_figures;
use crate::filer::{Filer, Written};
use crate::latency::{Hop, Latency};
use crate::metrics::{Metrics, TraceRow};
use crate::policy::{JoinedRow, MonitorResume, RowJoiner};
use crate::stages::Stages;
use crate::trace::TraceWriter;

/// Formatted rows kept before they are handed to the files' thread even between polls.
const PENDING_MAX: usize = 1 << 20;

/// The trace stopped being written.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct StorageLoss {
    /// The first tick whose row is missing from `trace.csv` (rows from it on were not
    /// written).
    pub from_tick: u64,
    /// Why: the I/O error and the file.
    pub reason: String,
}

/// The files of one run's report, open for appending rows.
#[derive(Debug)]
pub struct Recording {
    out: PathBuf,
    /// The thread that writes `trace.csv` and `timing.csv`; `None` once they could not
    /// be written.
    files: Option<Filer>,
    /// The rows taken since the last poll, formatted: `trace.csv`'s and `timing.csv`'s.
    pending: [Vec<u8>; 2],
    /// The newest resume slot content whose rows are in the files (`None`: none yet).
    durable: Option<MonitorResume>,
    /// The next row to take: the progress mark the slot carries.
    taken_row: u64,
    /// The files' lengths when opened (bytes).
    lengths_at_open: [u64; 2],
    metrics: Metrics,
    recorder: Recorder,
    /// Per-hop histograms and interval logs.
    pub latency: Latency,
    /// The stage breakdown of sense-to-actuate.
    pub stages: Stages,
    /// The roles' hosts: which hops share a clock.
    pub hosts: crate::hosts::Hosts,
    actuation: Actuation,
    ticks: u64,
    dt: f64,
    rows_at_flush: u64,
    /// The tick of the first row taken since the last flush.
    first_unflushed: Option<u64>,
    /// Attitude error of the first row of the run (deg).
    pub first_err: f64,
    /// Attitude error of the last row (deg).
    pub last_err: f64,
    /// Sum of the squared attitude errors of the rows taken (deg²), and their number.
    err_sq: (f64, u64),
    /// Largest relative spatial-momentum drift.
    pub drift_max: f64,
    /// Where the trace stopped, if it did.
    pub loss: Option<StorageLoss>,
    /// Every output that could not be written where it belonged, and where it went.
    pub storage_errors: Vec<String>,
    /// When the live status line was last drawn (`None`: never).
    status_at_ns: Option<u64>,
    /// The first status line: when (ns) and at what run time (s), for the pace.
    status_since: Option<(u64, f64)>,
}

/// Opens `trace.csv` and `timing.csv` in `out` (new, with their headers; or `resumed`'s,
/// cut back to the lengths its slot says were written) and starts their writing thread.
fn open_files(
    out: &Path,
    resumed: Option<&MonitorResume>,
    stall: Option<std::time::Duration>,
) -> anyhow::Result<(Filer, [u64; 2])> {
    let open = |name: &str, claimed: Option<u64>, header: &str| {
        let path = out.join(name);
        let dir = rotorloop_common::outdir::OutDir::open(out)?;
        // A restart appends to its predecessor's file; a new report replaces the name (never
        // writing through a link).
        let f = match resumed {
            Some(_) => dir.append(name),
            None => dir.create(name),
        };
        let mut f = f.with_context(|| format!("cannot open {}", path.display()))?;
        let len = f.metadata().with_context(|| format!("cannot read {}", path.display()))?.len();
        let len = match claimed {
            // Rows the predecessor wrote after its slot's last word: taken again now.
            Some(c) if c < len => {
                f.set_len(c).with_context(|| format!("cannot cut {} back", path.display()))?;
                c
            }
            Some(_) => len,
            None => {
                writeln!(f, "{header}").with_context(|| format!("cannot write {name}"))?;
                header.len() as u64 + 1
            }
        };
        anyhow::Ok((f, len))
    };
    let (trace, t) = open("trace.csv", resumed.map(|r| r.trace_bytes), crate::trace::HEADER)?;
    let (timing, m) =
        open("timing.csv", resumed.map(|r| r.timing_bytes), &crate::timing::header())?;
    let filer = Filer::start(trace, timing, [t, m], stall)
        .context("cannot start the monitor's file thread")?;
    Ok((filer, [t, m]))
}

/// The live status line: the run's time out of its length and the share done, the wall
/// time left where it can be estimated yet (`left_s`), the attitude error, the
/// sense-to-actuate p99 (µs) and the misses so far.
pub fn status_text(
    t: f64,
    end_s: f64,
    err_deg: f64,
    p99_us: f64,
    misses: u64,
    left_s: Option<f64>,
) -> String {
    let share = 100.0 * t / end_s;
    let left = left_s.map_or_else(String::new, |l| format!(", {l:.1} s left"));
    format!(
        "  t = {t:8.3} of {end_s:.3} s ({share:3.0} %{left})   error {err_deg:.3e}°   \
         sense-to-actuate p99 {p99_us:9.1} µs   misses {misses}   "
    )
}

impl Recording {
    /// Opens the report in `out` for `scenario`, starting at `now_ns`: new files, or, when
    /// `slot` (the monitor's resume slot) holds an unfinished report whose trace is there,
    /// the predecessor's, appended to (a restart); then it also returns that slot content.
    /// Files that cannot be opened are a [`StorageLoss`] from the first row, not an error.
    /// `stall`: the tests' hold-up of a first monitor's first write ([`Filer::start`]).
    /// Without `csv` it writes no `trace.csv` or `timing.csv` (a long run's output: they
    /// are derived from the flight records on demand, [`crate::derive`]), and removes those
    /// of an earlier run in `out`.
    pub fn open(
        out: &Path,
        scenario: &Scenario,
        slot: Option<MonitorResume>,
        (now_ns, stall): (u64, Option<std::time::Duration>),
        csv: bool,
    ) -> (Self, Option<MonitorResume>) {
        if let Ok(dir) = rotorloop_common::outdir::OutDir::make(out) {
            // An earlier run's summary, and without `csv` its trace and timing.
            let stale = ["summary.json", "trace.csv", "timing.csv"];
            for f in &stale[..if csv { 1 } else { 3 }] {
                let _ = dir.remove(f);
            }
        }
        let resumed = slot
            .filter(|r| r.next_row <= scenario.ticks() && (!csv || out.join("trace.csv").exists()));
        let first_row = resumed.map_or(0, |r| r.next_row);
        let stall = stall.filter(|_| resumed.is_none());
        let opened = if csv { Some(open_files(out, resumed.as_ref(), stall)) } else { None };
        let (files, lengths_at_open, loss) = match opened {
            None => (None, [0, 0], None),
            Some(Ok((f, lengths))) => (Some(f), lengths, None),
            Some(Err(e)) => {
                let loss = StorageLoss { from_tick: first_row, reason: format!("{e:#}") };
                (None, [0, 0], Some(loss))
            }
        };
        let (metrics, actuation) = new_metrics(scenario);
        let metrics = match &resumed {
            Some(r) => Metrics::restore(scenario.plant_params(actuation), &r.metrics),
            None => metrics,
        };
        let latency = Latency::new(out, now_ns, resumed.is_some()).unwrap_or_else(|_| {
            unreachable!("Latency::new keeps its histograms when its logs cannot be opened")
        });
        let mut rec = Self {
            out: out.to_owned(),
            files,
            pending: [Vec::with_capacity(PENDING_MAX), Vec::with_capacity(PENDING_MAX)],
            durable: resumed,
            taken_row: first_row,
            lengths_at_open,
            metrics,
            recorder: Recorder::new(scenario.ticks() + 1),
            latency,
            stages: Stages::default(),
            hosts: Default::default(),
            actuation,
            ticks: scenario.ticks(),
            dt: scenario.dt(),
            rows_at_flush: resumed.map_or(0, |r| r.rows),
            first_unflushed: None,
            first_err: resumed.map_or(f64::NAN, |r| r.first_err),
            last_err: f64::NAN,
            err_sq: resumed.map_or((0.0, 0), |r| (r.err_sq_sum, r.err_rows)),
            drift_max: resumed.map_or(0.0, |r| r.drift_max),
            loss: None,
            storage_errors: Vec::new(),
            status_at_ns: None,
            status_since: None,
        };
        if let Some(l) = loss {
            rec.lose(l.from_tick, l.reason);
        }
        (rec, resumed)
    }

    /// The trace cannot be written from `tick` on: stop appending, say so once.
    fn lose(&mut self, tick: u64, reason: String) {
        self.files = None;
        if self.loss.is_none() {
            eprintln!(
                "monitor: cannot write the trace from tick {tick}: {reason}; the loop goes on, \
                 histograms and metrics are kept in memory"
            );
            self.loss = Some(StorageLoss { from_tick: tick, reason });
        }
    }

    /// Takes one joined row: metrics, the trace row (while the trace can be written), the
    /// figures' data and its latencies.
    pub fn write(&mut self, j: &JoinedRow) {
        let (s, k) = (&j.state, j.tick);
        let row = trace_row(&mut self.metrics, self.actuation, self.dt, j);
        self.first_unflushed.get_or_insert(k);
        if self.files.is_some() {
            // Formatted here, written by the files' thread (`crate::filer`); a write into
            // memory does not fail.
            let [trace, timing] = &mut self.pending;
            let _ = TraceWriter::append(&mut *trace).write(&row);
            let _ = crate::timing::TimingRow::of(s).write(&mut *timing);
            // Many rows between two polls (a report assembled from the flight records
            // takes them all at once): handed over by the MiB, without a slot content.
            if trace.len() >= PENDING_MAX {
                let first = self.first_unflushed.take().unwrap_or(k);
                let written = self.files.as_mut().map(|f| f.hand_over(trace, timing, first, None));
                self.take(written.unwrap_or_default());
            }
        }
        self.recorder.record(&row, k == self.ticks);
        if j.first {
            self.first_err = row.err_deg;
        }
        self.last_err = row.err_deg;
        if row.err_deg.is_finite() {
            self.err_sq.0 += row.err_deg * row.err_deg;
            self.err_sq.1 += 1;
        }
        self.drift_max = self.drift_max.max(row.h_drift_rel);
        self.record_latencies(j);
        self.stages.record_row(j, self.hosts.controller_apart());
    }

    fn record_latencies(&mut self, j: &JoinedRow) {
        let (s, at, l) = (&j.state, j.state.publish_ns, &mut self.latency);
        // Only hops whose two stamps come from one host's clock (crate::hosts).
        let hosts = &self.hosts;
        let mut record = |hop, ns| {
            if hosts.computable(hop) {
                l.record(hop, ns, at);
            }
        };
        if let Some(t) = j.torque {
            record(Hop::StateTransport, t.state_recv_ns.saturating_sub(s.publish_ns));
            record(Hop::ControllerCompute, t.publish_ns.saturating_sub(t.state_recv_ns));
            if let Some(f) = j.following.filter(|f| f.applied_torque_tick == j.tick) {
                let recv = f.applied_torque_recv_ns;
                record(Hop::TorqueTransport, recv.saturating_sub(t.publish_ns));
                record(Hop::SenseToActuate, recv.saturating_sub(s.publish_ns));
            }
        }
        if s.flags & FLAG_REALTIME != 0 {
            record(Hop::TickLateness, s.wake_ns.saturating_sub(s.deadline_ns));
        }
        record(Hop::ReferenceLead, s.publish_ns.saturating_sub(j.reference.publish_ns));
    }

    /// A new report's first resume slot content, before any row: a monitor killed before
    /// its first rows reach the files restarts from row 0 (with the headers only), and
    /// the slot carries the progress mark from the first poll on, however long the first
    /// write takes. A restart keeps its predecessor's.
    pub fn begin(&mut self, joiner: &RowJoiner) {
        if self.durable.is_none() {
            let [trace_bytes, timing_bytes] = self.lengths_at_open;
            let r = joiner.save(self.first_err, self.err_sq, self.drift_max, self.metrics.save());
            self.durable = Some(MonitorResume { trace_bytes, timing_bytes, ..r });
        }
    }

    /// Hands the rows taken since the last call to the files' thread, and returns what
    /// the resume slot should now say, if that changed: the newest content whose rows are
    /// in the files (a monitor killed now loses nothing its slot claims was written, and
    /// writes no row twice), with the progress mark `taken_row` at the rows taken.
    pub fn flush(&mut self, joiner: &RowJoiner) -> Option<MonitorResume> {
        let taken = joiner.rows() > self.rows_at_flush;
        let mut snapshot = None;
        if taken {
            self.rows_at_flush = joiner.rows();
            let first = self.first_unflushed.take().unwrap_or_default();
            let now = joiner.save(self.first_err, self.err_sq, self.drift_max, self.metrics.save());
            snapshot = Some(now);
            let [trace, timing] = &mut self.pending;
            let written = match &mut self.files {
                Some(f) => f.hand_over(trace, timing, first, Some(now)),
                // Not written any more: the slot goes on with the rows taken (and the
                // files' lengths at the loss).
                None => {
                    let d = self.durable.map(|d| (d.trace_bytes, d.timing_bytes));
                    let (trace_bytes, timing_bytes) = d.unwrap_or_default();
                    self.durable = Some(MonitorResume { trace_bytes, timing_bytes, ..now });
                    Vec::new()
                }
            };
            self.take(written);
        } else if let Some(f) = &mut self.files {
            let written = f.finished();
            if written.is_empty() {
                return None;
            }
            self.take(written);
        } else {
            return None;
        }
        if let Some(s) = snapshot {
            self.taken_row = s.next_row;
        }
        let taken_row = self.taken_row;
        self.durable.map(|d| MonitorResume { taken_row, ..d })
    }

    /// Takes the thread's answers: the newest slot content written, or the loss.
    fn take(&mut self, written: Vec<Written>) {
        for w in written {
            match w {
                Written::Ok { resume: Some(r), .. } => self.durable = Some(r),
                Written::Ok { resume: None, .. } => {}
                Written::Failed { from_tick, reason } => self.lose(from_tick, reason),
            }
        }
    }

    /// Root mean square of the attitude error over the rows taken (deg); NaN before any.
    pub fn err_rms(&self) -> f64 {
        match self.err_sq {
            (_, 0) => f64::NAN,
            (sum, n) => (sum / n as f64).sqrt(),
        }
    }

    /// Rewrites the live status line on stderr, at most twice a second ([`status_text`]),
    /// of the newest state `last` in a run of `end_s` seconds: the wall time left is
    /// estimated from the pace since the first status line (in real time the run's time
    /// left; in lockstep, many times less).
    pub fn status_line(&mut self, last: Option<StateSample>, end_s: f64, now_ns: u64) {
        if self.status_at_ns.is_some_and(|t| now_ns - t < 500_000_000) {
            return;
        }
        self.status_at_ns = Some(now_ns);
        let p99 = self.latency.histogram(Hop::SenseToActuate).value_at_quantile(0.99) as f64 / 1e3;
        let (t, misses) = last.map_or((0.0, 0), |s| (s.t_s, s.misses));
        let (t0_ns, t0) = *self.status_since.get_or_insert((now_ns, t));
        let pace = (now_ns - t0_ns) as f64 / 1e9 / (t - t0); // wall s per run s
        let left_s = (pace.is_finite() && pace > 0.0).then(|| (end_s - t).max(0.0) * pace);
        let text = status_text(t, end_s, self.last_err, p99, misses, left_s);
        let mut e = std::io::stderr().lock();
        let _ = write!(e, "\r{text}");
        let _ = e.flush();
    }

    /// Closes the files and writes the histograms and figures; returns the files written
    /// and the directory they are in (the output directory, or the fallback).
    pub fn finish(&mut self, title: &str, fallback: &Path) -> (Vec<String>, PathBuf) {
        if self.status_at_ns.is_some() {
            eprint!("\r{:100}\r", ""); // clear the status line
        }
        let mut files = Vec::new();
        if let Some(mut f) = self.files.take() {
            let [trace, timing] = &mut self.pending;
            let first = self.first_unflushed.take().unwrap_or_default();
            let mut written = f.hand_over(trace, timing, first, None);
            written.extend(f.close());
            self.take(written);
            if self.loss.is_none() {
                files.extend(["trace.csv".to_owned(), "timing.csv".to_owned()]);
            }
        }
        if let Some(e) = self.latency.log_error() {
            self.storage_errors.push(format!("interval logs (.hlog) incomplete: {e}"));
        } else {
            files.extend(Hop::ALL.iter().map(|h| format!("{}.hlog", h.name())));
        }
        let out = self.out.clone();
        let dir = match with_fallback(&out, fallback, |d| Ok(self.latency.finish(d)?)) {
            Ok((hgrm, dir)) => {
                files.extend(hgrm);
                dir
            }
            Err(e) => {
                self.storage_errors.push(format!("histograms (.hgrm) not written: {e:#}"));
                out.clone()
            }
        };
        if dir != out {
            self.storage_errors.push(format!("histograms written to {} instead", dir.display()));
        }
        match self.latency.plots(title).map_err(anyhow::Error::from).and_then(|mut f| {
            f.extend(tracking_figures(&out, title, &self.recorder, None)?);
            Ok(f)
        }) {
            Ok(f) => files.extend(f),
            Err(e) => self.storage_errors.push(format!("figures not written: {e:#}")),
        }
        if let Some(l) = &self.loss {
            self.storage_errors
                .push(format!("trace.csv incomplete from tick {}: {}", l.from_tick, l.reason));
        }
        (files, dir)
    }
}

/// The trace row of the joined row `j`: its tracking metrics and invariants (`metrics`
/// goes on from it) and the actuation delay in force.
pub(crate) fn trace_row(
    metrics: &mut Metrics,
    actuation: Actuation,
    dt: f64,
    j: &JoinedRow,
) -> TraceRow {
    let s = &j.state;
    let nan = DVec3::splat(f64::NAN);
    let (u, tau) = match j.torque {
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
    let rd = j.reference.reference_state();
    let mut row = metrics.observe_work(j.tick, s.t_s, &s.body_state(), &rd, u, tau, s.rotor_work_j);
    row.delay_s = j.following.map_or(f64::NAN, |f| f.first_effect_delay_s(dt));
    row
}

/// The metrics of a new report of `scenario`, from the plant's initial state, and the
/// run's actuation.
pub(crate) fn new_metrics(scenario: &Scenario) -> (Metrics, Actuation) {
    let actuation = scenario.actuation();
    let params = scenario.plant_params(actuation);
    // The initial state exactly as the plant's integrator holds it.
    let init = rotorloop_plant::Body::new(params, scenario.plant_init).state();
    (Metrics::new(params, &init).with_disturbance(scenario.disturbance), actuation)
}

/// Where a run of `domain` writes what its output directory cannot take:
/// `$TMPDIR/rotorloop-report-DOMAIN-XXXXXXXXXX`, the tail random (from the kernel), drawn
/// anew by each process; made only when needed ([`with_fallback`]: `mkdir` mode 0700, used
/// only while it is this user's own private directory), and named in the report. Another
/// user can neither guess it ahead of the run nor plant anything in it.
pub fn fallback_dir(domain: &str) -> PathBuf {
    let tail = rotorloop_common::private::random_name(10);
    std::env::temp_dir().join(format!("{}{tail}", fallback_prefix(domain)))
}

/// The beginning of the names of `domain`'s fallback directories in `$TMPDIR`.
pub fn fallback_prefix(domain: &str) -> String {
    format!("rotorloop-report-{domain}-")
}

/// Runs `write` on `out`, again on `out` after 100 ms, then on `fallback` (made privately);
/// returns its result and the directory it succeeded in.
pub fn with_fallback<T>(
    out: &Path,
    fallback: &Path,
    mut write: impl FnMut(&Path) -> anyhow::Result<T>,
) -> anyhow::Result<(T, PathBuf)> {
    let first = match write(out) {
        Ok(v) => return Ok((v, out.to_owned())),
        Err(e) => e,
    };
    std::thread::sleep(std::time::Duration::from_millis(100));
    if let Ok(v) = write(out) {
        return Ok((v, out.to_owned()));
    }
    // Made exclusively and privately; one already there is used only if it is this user's
    // own private directory (this process's, made by an earlier write).
    rotorloop_common::private::dir(fallback)
        .with_context(|| format!("{first:#}; fallback {} not usable either", fallback.display()))?;
    let v = write(fallback).with_context(|| format!("{first:#}; and in {}", fallback.display()))?;
    Ok((v, fallback.to_owned()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::RowJoiner;

    #[test]
    fn the_status_line_says_the_runs_length_and_the_time_left() {
        let line = status_text(4.0, 10.0, 3.541, 215.2, 95, Some(0.3));
        assert!(line.contains("t =    4.000 of 10.000 s ( 40 %, 0.3 s left)"), "{line}");
        assert!(line.contains("p99     215.2 µs") && line.contains("misses 95"), "{line}");
        // The first line has no pace yet.
        assert!(status_text(0.0, 10.0, 1.0, 1.0, 0, None).contains("(  0 %)"));
    }

    /// A restarted monitor cuts its files back to the lengths its slot claims: rows its
    /// predecessor's file thread wrote after the slot's last word (the thread runs ahead
    /// of the slot) are taken again, not written twice.
    #[test]
    fn a_restart_cuts_the_files_back_to_what_its_slot_claims() {
        let dir = tempfile::tempdir().expect("tmp");
        let (tp, mp) = (dir.path().join("trace.csv"), dir.path().join("timing.csv"));
        std::fs::write(&tp, "h\nr0\nr1\nr2,parti").expect("trace");
        std::fs::write(&mp, "H\nm0\nm1\n").expect("timing");
        let joiner = RowJoiner::new(10, 1.0, 0);
        let claimed = joiner.save(0.0, (0.0, 0), 0.0, Default::default());
        let claimed = MonitorResume { next_row: 1, trace_bytes: 5, timing_bytes: 5, ..claimed };
        let (mut f, lengths) = open_files(dir.path(), Some(&claimed), None).expect("open");
        assert_eq!(lengths, [5, 5]);
        let _ = f.hand_over(&mut b"r1\n".to_vec(), &mut b"m1\n".to_vec(), 1, None);
        let _ = f.close();
        assert_eq!(std::fs::read_to_string(&tp).expect("trace"), "h\nr0\nr1\n");
        assert_eq!(std::fs::read_to_string(&mp).expect("timing"), "H\nm0\nm1\n");
    }

    /// A new report's files start with their headers, and the lengths say so.
    #[test]
    fn new_files_start_with_their_headers() {
        let dir = tempfile::tempdir().expect("tmp");
        let (f, lengths) = open_files(dir.path(), None, None).expect("open");
        drop(f);
        for (name, len) in ["trace.csv", "timing.csv"].into_iter().zip(lengths) {
            let text = std::fs::read_to_string(dir.path().join(name)).expect(name);
            assert_eq!(text.len() as u64, len, "{name}");
            assert_eq!(text.lines().count(), 1, "{name}: {text}");
        }
    }
}
