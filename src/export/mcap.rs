//! `run.mcap`: a run as an MCAP file for Foxglove (or Lichtblick, or any MCAP reader),
//! assembled after the run from its flight records, its `trace.csv` and its
//! `summary.json`, like the report: complete whatever was killed, and nothing of it is
//! written on the hot path.
//!
//! Topics (docs/foxglove.md has the layout that shows them):
//!
//! | topic | schema | one message per |
//! |---|---|---|
//! | `/rotorloop/state` | JSON, every field of the state sample | tick |
//! | `/rotorloop/torque` | JSON, every field of the torque sample that answered it | answered tick |
//! | `/rotorloop/reference` | JSON, every field of the reference sample | tick |
//! | `/rotorloop/tracking` | JSON: attitude and rate error, momentum drift, energy residual, delay in force, in an incident or not | tick (from `trace.csv`) |
//! | `/rotorloop/latency` | JSON: the hops, stages, lateness, misses, safe mode, the torque in force | tick |
//! | `/rotorloop/incidents` | JSON: window, kind, cause, evidence, peak deviation, recovery (`incidents.csv`) | incident |
//! | `/rotorloop/log` | `foxglove.Log`: faults, safe mode entered and left, the report's warnings | event |
//! | `/tf` | `foxglove.FrameTransform`: `world → body` and `world → reference` | tick, each |
//!
//! Every channel is declared before the first message, so each is in every file, also
//! without a message (the log of a run without an event). Their schemas are
//! [`super::topics`]', the live view's too.
//!
//! Log times are the loop's own `CLOCK_MONOTONIC` stamps (the state's publish time, the
//! torque's and the reference's), not wall time; a run in process (no stamps) uses its
//! simulated time. The file's metadata record `rotorloop` says how to map them to wall
//! time: `clock`, and the wall time of the first state's publish where the run recorded it.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::Context as _;
use foxglove::messages::{FrameTransform, Log, Quaternion, Timestamp, Vector3};
use glam::{DMat3, DQuat};
use rotorloop_common::flight::{FlightLog, SPARE_SLOTS, Stream};
use rotorloop_common::graph::Role;
use rotorloop_common::role::UsageError;
use rotorloop_common::wire::{
    FLAG_REALTIME, FLAG_SAFE_MODE, NO_TICK, ReferenceSample, StateSample, TorqueSample,
};
use rotorloop_monitor::derive::{Csv, DerivedRows};
use rotorloop_monitor::metrics::TraceRow;
use rotorloop_monitor::rows::{TickRows, records_dir};
use rotorloop_monitor::summary::Summary;
use serde::Serialize;
use serde_json::Value;

use super::topics;

/// What [`write()`] put into the file.
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct McapCounts {
    /// The file.
    pub path: String,
    /// Messages per topic.
    pub messages: BTreeMap<String, u64>,
    /// `full` (every tick) or `overview` ([`Detail::Overview`]).
    pub detail: String,
    /// Ticks a `/rotorloop/window` message.
    pub window_ticks: u64,
    /// The ticks whose messages it holds (every one: `full`), and of those the ticks of
    /// the incidents' windows kept at full rate beside the overview's one a window.
    pub ticks_kept: Kept,
}

impl McapCounts {
    /// What of the run it holds, in words.
    pub fn said(&self) -> String {
        let k = &self.ticks_kept;
        match self.detail.as_str() {
            "overview" => format!(
                "an overview: {} ticks of the run's, one a window of {} ticks with the \
                 window's extremes, and {} ticks of {} of its {} incidents at full rate \
                 (`export --mcap --detail full` for every tick)",
                k.ticks, self.window_ticks, k.incident_ticks, k.incidents_at_full_rate, k.incidents
            ),
            _ => format!("every tick ({})", k.ticks),
        }
    }
}

/// The ticks a file holds the messages of.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq)]
pub struct Kept {
    /// Ticks with their messages.
    pub ticks: u64,
    /// Of those, kept only for an incident's window (overview).
    pub incident_ticks: u64,
    /// The incidents whose windows were kept at full rate, wholly or in part.
    pub incidents_at_full_rate: u64,
    /// The run's incidents.
    pub incidents: u64,
}

/// The records and files of one run directory.
struct Run {
    states: FlightLog<StateSample>,
    torques: Option<FlightLog<TorqueSample>>,
    /// The plant's record of what it received: the answer where the controller's record
    /// lacks it (a controller killed between its publish and its record).
    received: FlightLog<TorqueSample>,
    references: FlightLog<ReferenceSample>,
    /// The trace rows, a row at a time in tick order.
    trace: std::cell::RefCell<TraceSource>,
    trace_columns: Vec<String>,
    summary: Option<Summary>,
}

/// A run's trace rows in tick order, as values in `trace.csv`'s columns.
enum TraceSource {
    /// Its `trace.csv`.
    File(TickRows),
    /// Derived from its records (`run --no-csv`), unformatted, with the row read ahead.
    Derived(Box<(DerivedRows, Option<TraceRow>)>),
}

impl TraceSource {
    /// The file, else the rows derived from the records (as [`open_trace`]).
    fn open(dir: &Path) -> anyhow::Result<(Self, Vec<String>)> {
        if dir.join(Csv::Trace.name()).exists() {
            let rows = open_trace(dir)?;
            let columns = rows.columns();
            return Ok((Self::File(rows), columns));
        }
        let rows = DerivedRows::of_run(dir).with_context(|| {
            format!("cannot read {} (the run's report)", dir.join("trace.csv").display())
        })?;
        let columns = rotorloop_monitor::trace::HEADER.split(',').map(str::to_owned).collect();
        Ok((Self::Derived(Box::new((rows, None))), columns))
    }

    /// The row of tick `k` (asked for in increasing order), every value a float.
    fn row(&mut self, k: u64) -> Option<Vec<f64>> {
        match self {
            Self::File(rows) => rows.row(k).map(|l| parse_row(&l)),
            Self::Derived(derived) => loop {
                let (rows, ahead) = &mut **derived;
                match ahead {
                    Some(r) if r.tick > k => return None,
                    Some(r) if r.tick == k => {
                        return ahead.take().map(|r| rotorloop_monitor::trace::values(&r));
                    }
                    _ => *ahead = Some(rows.next_trace()?),
                }
            },
        }
    }
}

impl Run {
    fn read(dir: &Path) -> anyhow::Result<Self> {
        let summary = Summary::read(dir).ok();
        let flight = records_dir(dir, summary.as_ref());
        let missing = || {
            format!(
                "{} has no flight records to export (rotorloop run records them)",
                dir.display()
            )
        };
        // The run's ticks as its summary says (a later tick is not the run's; without a
        // summary the records' own geometry bounds them).
        let ticks = summary.as_ref().and_then(|s| s.ticks).unwrap_or(u64::MAX);
        let limit = ticks.saturating_add(SPARE_SLOTS);
        // Whatever of the records is sound; refused (exit 2) only where the states are
        // missing or damaged in every file.
        let states = FlightLog::read(&flight, Stream::PlantState, limit)
            .map_err(|e| UsageError(format!("{}: {e}", missing())))?;
        let (trace, trace_columns) = TraceSource::open(dir)?;
        // Rows derived from the records read them as the export goes: its readers share
        // their blocks, so each is unpacked once (it was most of an overview's time).
        let shared = match &trace {
            TraceSource::Derived(d) => Some(d.0.records().shared()),
            TraceSource::File(_) => None,
        };
        let (states, torques, received, references) = match shared {
            Some(records) => records,
            None => (
                states,
                FlightLog::read(&flight, Stream::ControllerTorque, limit).ok(),
                FlightLog::read(&flight, Stream::PlantTorque, limit)
                    .unwrap_or_else(|e| FlightLog::unreadable(&e)),
                FlightLog::read(&flight, Stream::Reference, limit)
                    .unwrap_or_else(|e| FlightLog::unreadable(&e)),
            ),
        };
        let trace = trace.into();
        Ok(Self { states, torques, received, references, trace, trace_columns, summary })
    }

    fn torque(&self, k: u64) -> Option<TorqueSample> {
        self.torques.as_ref().and_then(|t| t.get(k)).or_else(|| self.received.get(k))
    }

    /// The trace row of tick `k` (asked for in increasing order), every value a float.
    fn trace_row(&self, k: u64) -> Option<Vec<f64>> {
        self.trace.borrow_mut().row(k)
    }
}

/// The run's trace rows: its `trace.csv`, or derived from its records (`run --no-csv`).
fn open_trace(dir: &Path) -> anyhow::Result<TickRows> {
    rotorloop_monitor::derive::run_rows(dir, Csv::Trace).with_context(|| {
        format!("cannot read {} (the run's report)", dir.join("trace.csv").display())
    })
}

/// A trace row's values (NaN where one is not a number).
fn parse_row(line: &str) -> Vec<f64> {
    line.split(',').map(|v| v.parse().unwrap_or(f64::NAN)).collect()
}

/// The file's channels, all declared before the first message, so that a channel with no
/// message (the log of a run without an event, the incidents of a clean run) is in every
/// file: the schemas are [`super::topics`]', the same as the live view's.
struct FileSink {
    writer: mcap::Writer<std::io::BufWriter<rotorloop_common::outdir::Atomic>>,
    channels: BTreeMap<&'static str, (u16, u32, u64)>,
}

impl FileSink {
    /// A sink writing `path` (through an exclusive temporary beside it, renamed by
    /// [`FileSink::finish`]) in chunks of `chunk` bytes of messages.
    fn create(path: &Path, chunk: u64) -> anyhow::Result<Self> {
        let file = rotorloop_common::outdir::split(path)
            .map_err(anyhow::Error::from)
            .and_then(|(dir, name)| Ok(rotorloop_common::outdir::OutDir::open(dir)?.atomic(name)?))
            .with_context(|| format!("cannot write {}", path.display()))?;
        // zstd at level 1: with the writer's default, compression was over 40 % of the
        // export's time (perf), and the file was 10 % larger (docs/measurements.md).
        let options = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(MCAP_ZSTD_LEVEL)
            .chunk_size(Some(chunk))
            .library(format!("rotorloop {}", env!("CARGO_PKG_VERSION")));
        let mut sink = Self {
            writer: options.create(std::io::BufWriter::new(file))?,
            channels: BTreeMap::new(),
        };
        for t in topics::JSON_TOPICS {
            sink.declare(t.topic, t.schema_name, "jsonschema", &t.schema_bytes(), "json")?;
        }
        sink.declare_encoded::<Log>(topics::LOG)?;
        sink.declare_encoded::<FrameTransform>(topics::TF)?;
        Ok(sink)
    }

    fn declare(
        &mut self,
        topic: &'static str,
        name: &str,
        schema_encoding: &str,
        schema: &[u8],
        encoding: &str,
    ) -> anyhow::Result<()> {
        let schema = self.writer.add_schema(name, schema_encoding, schema)?;
        let id = self.writer.add_channel(schema, topic, encoding, &BTreeMap::new())?;
        self.channels.insert(topic, (id, 0, 0));
        Ok(())
    }

    fn declare_encoded<T: foxglove::Encode>(&mut self, topic: &'static str) -> anyhow::Result<()> {
        let s = T::get_schema().context("a Foxglove message without its schema")?;
        self.declare(topic, &s.name, &s.encoding, &s.data, &T::get_message_encoding())
    }

    fn bytes(&mut self, topic: &str, data: &[u8], log_time: u64) -> anyhow::Result<()> {
        let (id, sequence, count) =
            self.channels.get_mut(topic).with_context(|| format!("no channel {topic}"))?;
        *sequence += 1;
        *count += 1;
        let header = mcap::records::MessageHeader {
            channel_id: *id,
            sequence: *sequence,
            log_time,
            publish_time: log_time,
        };
        self.writer.write_to_known_channel(&header, data)?;
        Ok(())
    }

    /// Logs `value` as JSON on `topic` at `log_time`.
    fn json<T: Serialize>(&mut self, topic: &str, value: &T, log_time: u64) -> anyhow::Result<()> {
        let data = serde_json::to_vec(value)?;
        self.bytes(topic, &data, log_time)
    }

    /// Logs a Foxglove message (protobuf) on `topic` at `log_time`.
    fn encoded<T: foxglove::Encode>(
        &mut self,
        topic: &str,
        m: &T,
        log_time: u64,
    ) -> anyhow::Result<()> {
        let mut data = Vec::with_capacity(m.encoded_len().unwrap_or(256));
        m.encode(&mut data).map_err(|e| anyhow::anyhow!("cannot encode for {topic}: {e}"))?;
        self.bytes(topic, &data, log_time)
    }

    fn counts(&self) -> BTreeMap<String, u64> {
        self.channels.iter().map(|(t, (_, _, n))| ((*t).to_owned(), *n)).collect()
    }

    fn finish(mut self) -> anyhow::Result<()> {
        use std::io::Write;
        self.writer.finish()?;
        let mut file = self.writer.into_inner().into_inner().map_err(|e| e.into_error())?;
        file.flush()?;
        file.commit()?;
        Ok(())
    }
}

/// The attitude `r_row_major` as a unit quaternion (x, y, z, w).
pub fn quaternion(r_row_major: &[f64; 9]) -> DQuat {
    let m = DMat3::from_cols_array(r_row_major).transpose();
    DQuat::from_mat3(&m).normalize()
}

pub(crate) fn transform(parent: &str, child: &str, r: &[f64; 9], ns: u64) -> FrameTransform {
    let q = quaternion(r);
    FrameTransform {
        timestamp: Some(timestamp(ns)),
        parent_frame_id: parent.to_owned(),
        child_frame_id: child.to_owned(),
        translation: Some(Vector3 { x: 0.0, y: 0.0, z: 0.0 }),
        rotation: Some(Quaternion { x: q.x, y: q.y, z: q.z, w: q.w }),
    }
}

fn timestamp(ns: u64) -> Timestamp {
    Timestamp::new((ns / 1_000_000_000) as u32, (ns % 1_000_000_000) as u32)
}

pub(crate) fn log_message(
    ns: u64,
    level: foxglove::messages::log::Level,
    name: &str,
    message: String,
) -> Log {
    Log {
        timestamp: Some(timestamp(ns)),
        level: level as i32,
        message,
        name: name.to_owned(),
        ..Default::default()
    }
}

/// The per-tick hops and stages of state `s` answered by `t` ([`topics::LATENCY_HOPS`],
/// in its order; `None` where a stamp is missing).
pub(crate) fn hops(
    s: &StateSample,
    t: Option<&TorqueSample>,
    r: Option<&ReferenceSample>,
) -> [Option<u64>; 9] {
    let d = |a: u64, b: u64| (a != 0 && b != 0 && a >= b).then(|| a - b);
    let answered = t.filter(|t| t.tick == s.tick);
    let realtime = s.flags & FLAG_REALTIME != 0;
    [
        answered.and_then(|t| d(t.state_recv_ns, s.publish_ns)),
        answered.and_then(|t| d(t.publish_ns, t.state_recv_ns)),
        answered.and_then(|t| d(t.validated_ns, t.state_recv_ns)),
        answered.and_then(|t| d(t.paired_ns, t.validated_ns)),
        answered.and_then(|t| d(t.computed_ns, t.paired_ns)),
        answered.and_then(|t| d(t.publish_ns, t.computed_ns)),
        realtime.then(|| d(s.wake_ns, s.deadline_ns)).flatten(),
        realtime.then(|| d(s.publish_ns, s.wake_ns)).flatten(),
        r.and_then(|r| d(s.publish_ns, r.publish_ns)),
    ]
}

/// The per-tick latency of state `s` answered by `t` (ns; `null` where a stamp is
/// missing), the stages of the controller, and the state of the loop ([`topics::LATENCY`]).
pub(crate) fn latency(
    s: &StateSample,
    t: Option<&TorqueSample>,
    r: Option<&ReferenceSample>,
) -> Value {
    latency_of(s, &hops(s, t, r))
}

fn latency_of(s: &StateSample, hops: &[Option<u64>; 9]) -> Value {
    let mut m = serde_json::Map::new();
    m.insert("tick".into(), s.tick.into());
    m.insert("t_s".into(), serde_json::json!(s.t_s));
    for (name, v) in topics::LATENCY_HOPS.iter().zip(hops) {
        m.insert((*name).into(), serde_json::json!(v));
    }
    m.insert("state_send_ns".into(), s.prev_publish.send_ns.into());
    m.insert("misses".into(), s.misses.into());
    m.insert("safe_mode".into(), (s.flags & FLAG_SAFE_MODE != 0).into());
    let in_force = (s.applied_torque_tick != NO_TICK).then_some(s.applied_torque_tick);
    m.insert("torque_in_force_tick".into(), serde_json::json!(in_force));
    m.insert("torque_in_force_recv_ns".into(), s.applied_torque_recv_ns.into());
    Value::Object(m)
}

/// How much of its run's ticks `run.mcap` holds (`export --mcap --detail`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Detail {
    /// `overview` for a run of [`LONG_RUN_TICKS`] or more (an hour at 1 kHz), `full`
    /// below.
    #[default]
    Auto,
    /// Every tick's messages.
    Full,
    /// The messages of one tick a window (a tenth of a second of the loop's time), one
    /// `/rotorloop/window` message with the extremes of every window, and every tick of
    /// the incidents' windows (from a window before each to a second after it), up to a
    /// hundredth of the run's ticks or ten seconds' worth, the more.
    Overview,
}

/// What a file holds of its run, decided from the run's length and rate.
#[derive(Debug, Clone, Copy)]
struct Plan {
    overview: bool,
    /// Ticks a window (of [`topics::WINDOW`], and of the overview's kept ticks).
    window: u64,
    /// Ticks kept at full rate before an incident (a window's) and after it (a second).
    before: u64,
    after: u64,
    /// Ticks the overview may keep at full rate in the incidents' windows.
    full_rate_ticks: u64,
}

impl Plan {
    fn of(detail: Detail, ticks: Option<u64>, rate_hz: Option<f64>) -> Self {
        let rate = rate_hz.filter(|r| r.is_finite() && *r > 0.0).unwrap_or(1000.0);
        let overview = match detail {
            Detail::Full => false,
            Detail::Overview => true,
            Detail::Auto => ticks.is_some_and(|t| t >= LONG_RUN_TICKS),
        };
        let window = ((rate / WINDOWS_A_SECOND).round() as u64).max(1);
        let second = rate.round() as u64;
        let share = ticks.unwrap_or(0) / FULL_RATE_SHARE;
        Self {
            overview,
            window,
            before: window,
            after: second,
            full_rate_ticks: share.max(FULL_RATE_SECONDS * second),
        }
    }

    fn name(&self) -> &'static str {
        if self.overview { "overview" } else { "full" }
    }
}

/// Windows of [`topics::WINDOW`] a second of the loop's time (and the overview's kept
/// ticks a second).
const WINDOWS_A_SECOND: f64 = 10.0;
/// The overview keeps at most one tick in this many at full rate in the incidents'
/// windows (or [`FULL_RATE_SECONDS`], the more): the first incidents' windows, in the order
/// of their first ticks, each from its start on.
const FULL_RATE_SHARE: u64 = 100;
/// Seconds of the loop's ticks the overview may keep at full rate, whatever its length.
const FULL_RATE_SECONDS: u64 = 10;

/// Writes `DIR/run.mcap` from the run in `dir` (records, `trace.csv`, `summary.json`,
/// `incidents.csv`), with [`Detail::Auto`]: see [`write_with`].
pub fn write(dir: &Path) -> anyhow::Result<McapCounts> {
    write_with(dir, Detail::Auto)
}

/// Writes `DIR/run.mcap` from the run in `dir` with `detail`: through an exclusive
/// temporary renamed when complete (removed on failure), so a reader never sees half a
/// file.
pub fn write_with(dir: &Path, detail: Detail) -> anyhow::Result<McapCounts> {
    // A run in process (`sim`, `sim --replay`, `paper`'s in-process runs) has no flight
    // records: its trace alone (attitudes, tracking) in simulated time.
    let records = Stream::PlantState.path(&records_dir(dir, None)).exists()
        || !dir.join("trace.csv").exists();
    let run = if records { Some(Run::read(dir)?) } else { None };
    let path = dir.join("run.mcap");
    let summary = match &run {
        Some(run) => run.summary.clone(),
        None => Summary::read(dir).ok(),
    };
    let ticks = match &run {
        Some(run) => run.summary.as_ref().and_then(|s| s.ticks),
        None => std::fs::metadata(dir.join("trace.csv")).ok().map(|m| m.len() / TRACE_ROW_BYTES),
    };
    let rate = summary.and_then(|s| s.rate_hz.or_else(|| s.dt.map(|dt| 1.0 / dt)));
    let plan = Plan::of(detail, ticks, rate);
    let long = ticks.is_some_and(|t| t >= LONG_RUN_TICKS);
    let chunk = if long { MCAP_LONG_CHUNK_BYTES } else { MCAP_CHUNK_BYTES };
    let written = FileSink::create(&path, chunk).and_then(|mut sink| {
        let kept = match &run {
            Some(run) => write_messages(&mut sink, run, dir, plan)?,
            None => write_trace_messages(&mut sink, dir, plan)?,
        };
        let counts = sink.counts();
        sink.finish()?;
        Ok((counts, kept))
    });
    let (counts, kept) = written.with_context(|| format!("cannot write {}", path.display()))?;
    Ok(McapCounts {
        path: path.display().to_string(),
        messages: counts,
        detail: plan.name().into(),
        window_ticks: plan.window,
        ticks_kept: kept,
    })
}

/// The zstd level of `run.mcap`'s chunks.
const MCAP_ZSTD_LEVEL: u32 = 1;

/// Bytes of messages per MCAP chunk (the crate's default). The writer keeps an index entry
/// per chunk until the file's summary is written (about 0.5 kB each): a 6 000 s export
/// held 8 MB more than a 600 s one, an hour's about 5 MB.
const MCAP_CHUNK_BYTES: u64 = 1 << 20;
/// Bytes of messages per chunk from [`LONG_RUN_TICKS`] on: a day's index about 15 MB, for
/// 9 MB more of chunk buffers (docs/measurements.md).
const MCAP_LONG_CHUNK_BYTES: u64 = 8 << 20;
/// Ticks from which a run is written in the longer chunks, and as an overview
/// ([`Detail::Auto`]): an hour at 1 kHz.
pub const LONG_RUN_TICKS: u64 = 3_600_000;
/// About the bytes of a `trace.csv` row: what a run in process (no summary) is counted by
/// (measured: 796 a row in a 4 s real-time `paper-sinusoid` trace).
const TRACE_ROW_BYTES: u64 = 800;

fn write_messages(sink: &mut FileSink, run: &Run, dir: &Path, plan: Plan) -> anyhow::Result<Kept> {
    let first = run.states.iter().next();
    let first = first.as_ref();
    let realtime = first.is_some_and(|s| s.publish_ns != 0);
    // Without stamps (a run in process) the log time is the simulated time.
    let time = |stamp: u64, t_s: f64| if realtime { stamp } else { (t_s * 1e9) as u64 };
    let t0 = first.map_or(0, |s| time(s.publish_ns, s.t_s));
    write_head(sink, run, first, plan, t0)?;
    let incidents_csv = dir.join("incidents.csv");
    let mut incidents = Incidents::open(&incidents_csv);
    let mut full_rate = FullRate::new(&incidents_csv, plan);
    // An incident's message is at its first tick's state, else at its start after `t0`.
    let incident_time = |i: &Value| {
        let at_s = i["start_s"].as_f64().unwrap_or_default();
        let start = i["start_tick"].as_u64().unwrap_or_default();
        run.states.get(start).map_or(t0 + (at_s * 1e9) as u64, |s| time(s.publish_ns, s.t_s))
    };
    let columns = &run.trace_columns;
    let tracked = topics::WINDOW_TRACKING.map(|c| columns.iter().position(|n| n == c));
    let mut window = Window::default();
    let mut kept = Kept::default();
    let mut safe = false;
    for s in run.states.iter() {
        let s = &s;
        let k = s.tick;
        let ns = time(s.publish_ns, s.t_s);
        // The incidents that start by this tick, each at its start's time.
        while let Some(i) = incidents.starting_by(k) {
            sink.json(topics::INCIDENTS.topic, &i, incident_time(&i))?;
        }
        let in_incident = incidents.holds(k);
        let t = run.torque(k);
        let t = t.as_ref();
        let r = run.references.get(k);
        let r = r.as_ref();
        let hops = hops(s, t, r);
        let row = run.trace_row(k);
        if window.first.is_some_and(|f| f / plan.window != k / plan.window) {
            let (at, message) = window.take();
            sink.json(topics::WINDOW.topic, &message, at)?;
        }
        let value = |i: Option<usize>| i.and_then(|i| row.as_ref()?.get(i).copied());
        let tracking = tracked.map(|i| value(i).unwrap_or(f64::NAN));
        window.add(s, ns, t.is_some_and(|t| t.tick == k), &hops, &tracking, in_incident);
        let now_safe = s.flags & FLAG_SAFE_MODE != 0;
        if now_safe != safe {
            let m = safe_mode_message(now_safe, k);
            sink.encoded(topics::LOG, &log_message(ns, m.0, Role::Plant.name(), m.1), ns)?;
            safe = now_safe;
        }
        let sampled = !plan.overview || k % plan.window == 0;
        let for_incident = plan.overview && full_rate.holds(k);
        if !(sampled || for_incident) {
            continue;
        }
        kept.ticks += 1;
        kept.incident_ticks += u64::from(!sampled);
        sink.json(topics::STATE.topic, &topics::state_json(s), ns)?;
        if let Some(t) = t {
            sink.json(topics::TORQUE.topic, &topics::torque_json(t), time(t.publish_ns, s.t_s))?;
        }
        if let Some(r) = r {
            let at = time(r.publish_ns, r.t_s);
            sink.json(topics::REFERENCE.topic, &topics::reference_json(r), at)?;
            sink.encoded(topics::TF, &transform("world", "reference", &r.r_d_row_major, ns), ns)?;
        }
        sink.encoded(topics::TF, &transform("world", "body", &s.r_row_major, ns), ns)?;
        sink.json(topics::LATENCY.topic, &latency_of(s, &hops), ns)?;
        if let Some(row) = row {
            let row = tracking_row(columns, &row, Some(in_incident));
            sink.json(topics::TRACKING.topic, &row, ns)?;
        }
    }
    if window.first.is_some() {
        let (at, message) = window.take();
        sink.json(topics::WINDOW.topic, &message, at)?;
    }
    // Those that start after the last state (a fault outside the loop at its end).
    while let Some(i) = incidents.starting_by(u64::MAX) {
        sink.json(topics::INCIDENTS.topic, &i, incident_time(&i))?;
    }
    for (ns, level, name, message) in events(run, t0) {
        sink.encoded(topics::LOG, &log_message(ns, level, &name, message), ns)?;
    }
    kept.incidents = full_rate.incidents;
    kept.incidents_at_full_rate = full_rate.windows;
    if plan.overview {
        let m = BTreeMap::from([
            ("ticks".to_owned(), kept.ticks.to_string()),
            ("incident_ticks".to_owned(), kept.incident_ticks.to_string()),
            ("incidents".to_owned(), kept.incidents.to_string()),
            ("incidents_at_full_rate".to_owned(), kept.incidents_at_full_rate.to_string()),
        ]);
        let name = "rotorloop.kept".into();
        sink.writer.write_metadata(&mcap::records::Metadata { name, metadata: m })?;
    }
    Ok(kept)
}

/// The file's metadata record and the run's `summary.json` attached (at `t0`).
fn write_head(
    sink: &mut FileSink,
    run: &Run,
    first: Option<&StateSample>,
    plan: Plan,
    t0: u64,
) -> anyhow::Result<()> {
    sink.writer.write_metadata(&mcap::records::Metadata {
        name: "rotorloop".into(),
        metadata: metadata(run, first, plan),
    })?;
    if let Some(s) = &run.summary {
        sink.writer.attach(&mcap::Attachment {
            log_time: t0,
            create_time: t0,
            name: "summary.json".into(),
            media_type: "application/json".into(),
            data: serde_json::to_vec_pretty(&s.json)?.into(),
        })?;
    }
    Ok(())
}

/// One window of ticks ([`topics::WINDOW`]): what its ticks were at their worst.
#[derive(Debug)]
struct Window {
    first: Option<u64>,
    last: u64,
    t_s: f64,
    ns: u64,
    ticks: u64,
    answered: u64,
    /// The cumulative misses before the window, and at its newest tick.
    misses_before: u64,
    misses: u64,
    safe_mode: u64,
    in_incident: u64,
    tracking: [f64; 2],
    hops: [Option<u64>; 9],
}

impl Default for Window {
    fn default() -> Self {
        Self {
            first: None,
            last: 0,
            t_s: 0.0,
            ns: 0,
            ticks: 0,
            answered: 0,
            misses_before: 0,
            misses: 0,
            safe_mode: 0,
            in_incident: 0,
            tracking: [f64::NAN; 2],
            hops: [None; 9],
        }
    }
}

impl Window {
    fn add(
        &mut self,
        s: &StateSample,
        ns: u64,
        answered: bool,
        hops: &[Option<u64>; 9],
        tracking: &[f64; 2],
        in_incident: bool,
    ) {
        self.first.get_or_insert(s.tick);
        (self.last, self.t_s, self.ns) = (s.tick, s.t_s, ns);
        self.ticks += 1;
        self.answered += u64::from(answered);
        self.misses = self.misses.max(s.misses);
        self.safe_mode += u64::from(s.flags & FLAG_SAFE_MODE != 0);
        self.in_incident += u64::from(in_incident);
        for (m, v) in self.tracking.iter_mut().zip(tracking) {
            // `f64::max` keeps the number where one of the two is NaN.
            *m = m.max(*v);
        }
        for (m, v) in self.hops.iter_mut().zip(hops) {
            *m = (*m).max(*v);
        }
    }

    /// Its message and log time (its newest tick's); the window after it starts empty.
    fn take(&mut self) -> (u64, Value) {
        let mut m = serde_json::Map::new();
        m.insert("first_tick".into(), self.first.unwrap_or(self.last).into());
        m.insert("last_tick".into(), self.last.into());
        m.insert("t_s".into(), serde_json::json!(self.t_s));
        m.insert("ticks".into(), self.ticks.into());
        m.insert("answered".into(), self.answered.into());
        m.insert("misses".into(), self.misses.saturating_sub(self.misses_before).into());
        m.insert("safe_mode_ticks".into(), self.safe_mode.into());
        m.insert("in_incident_ticks".into(), self.in_incident.into());
        for (c, v) in topics::WINDOW_TRACKING.iter().zip(&self.tracking) {
            m.insert(format!("{c}_max"), serde_json::json!(v.is_finite().then_some(*v)));
        }
        for (h, v) in topics::LATENCY_HOPS.iter().zip(&self.hops) {
            m.insert(format!("{h}_max"), serde_json::json!(v));
        }
        let at = self.ns;
        *self = Self { misses_before: self.misses, misses: self.misses, ..Self::default() };
        (at, Value::Object(m))
    }
}

/// The ticks an overview keeps at full rate: the incidents' windows with a lead-in and a
/// tail, within a budget of ticks for the run ([`Plan`]), read ahead of the ticks written.
struct FullRate {
    ahead: Incidents,
    before: u64,
    after: u64,
    left: u64,
    /// The windows begun and not yet passed, and the newest tick any of them covers.
    open: Vec<[u64; 2]>,
    covered_to: Option<u64>,
    /// The incidents seen, and those with ticks kept.
    incidents: u64,
    windows: u64,
}

impl FullRate {
    fn new(incidents_csv: &Path, plan: Plan) -> Self {
        Self {
            ahead: Incidents::open(incidents_csv),
            before: plan.before,
            after: plan.after,
            left: plan.full_rate_ticks,
            open: Vec::new(),
            covered_to: None,
            incidents: 0,
            windows: 0,
        }
    }

    /// Whether tick `k` (asked for in increasing order) is kept at full rate.
    fn holds(&mut self, k: u64) -> bool {
        while let Some(i) = self.ahead.read_by(k.saturating_add(self.before)) {
            self.incidents += 1;
            let start = i["start_tick"].as_u64().unwrap_or_default();
            let end = i["end_tick"].as_u64().unwrap_or(start).saturating_add(self.after);
            let from = start.saturating_sub(self.before).max(self.covered_to.map_or(0, |c| c + 1));
            if from > end {
                // Within the window before it.
                self.windows += 1;
                continue;
            }
            if self.left == 0 {
                continue;
            }
            let to = end.min(from + self.left - 1);
            self.left -= to - from + 1;
            self.open.push([from, to]);
            self.covered_to = Some(to);
            self.windows += 1;
        }
        self.open.retain(|w| w[1] >= k);
        self.open.iter().any(|w| w[0] <= k)
    }
}

/// The log line of safe mode entered (`true`) or left at tick `k`: the same words and
/// level in `run.mcap` and live.
pub(crate) fn safe_mode_message(entered: bool, k: u64) -> (foxglove::messages::log::Level, String) {
    use foxglove::messages::log::Level;
    match entered {
        true => (Level::Warning, format!("tick {k}: entered safe mode")),
        false => (Level::Info, format!("tick {k}: left safe mode")),
    }
}

/// `incidents.csv` (`rotorloop explain`'s, written after the run, in the order of the
/// incidents' first ticks) read a row at a time as the export's ticks reach them: what is
/// held is the windows still open at the current tick, not the run's incidents.
struct Incidents {
    lines: Option<std::io::Lines<std::io::BufReader<std::fs::File>>>,
    header: Vec<String>,
    /// The next row, read but not yet due.
    next: Option<Value>,
    /// The windows begun by the current tick that had not ended before it.
    open: Vec<[u64; 2]>,
}

impl Incidents {
    /// The file's rows; none without the file.
    fn open(path: &Path) -> Self {
        use std::io::BufRead;
        let mut lines = std::fs::File::open(path).ok().map(|f| std::io::BufReader::new(f).lines());
        let header = lines
            .as_mut()
            .and_then(|l| l.next())
            .and_then(Result::ok)
            .map(|h| split_csv(&h))
            .unwrap_or_default();
        Self { lines, header, next: None, open: Vec::new() }
    }

    /// The next incident whose first tick is at most `k`, as its [`topics::INCIDENTS`]
    /// message; its window counts for [`Incidents::holds`] from then on.
    fn starting_by(&mut self, k: u64) -> Option<Value> {
        let i = self.read_by(k)?;
        let start = i["start_tick"].as_u64().unwrap_or_default();
        self.open.push([start, i["end_tick"].as_u64().unwrap_or(start)]);
        Some(i)
    }

    /// The next incident whose first tick is at most `k`, its window not counted (a
    /// reader ahead of the ticks, as [`FullRate`]'s).
    fn read_by(&mut self, k: u64) -> Option<Value> {
        if self.next.is_none() {
            self.next = self.read();
        }
        let start = self.next.as_ref()?["start_tick"].as_u64()?;
        if start > k {
            return None;
        }
        self.next.take()
    }

    /// Whether tick `k` (asked for in increasing order, after [`Incidents::starting_by`]
    /// for it) is in one of the incidents' windows.
    fn holds(&mut self, k: u64) -> bool {
        self.open.retain(|w| w[1] >= k);
        self.open.iter().any(|w| w[0] <= k)
    }

    /// The next row that is an incident (others are skipped).
    fn read(&mut self) -> Option<Value> {
        loop {
            let line = self.lines.as_mut()?.next()?.ok()?;
            if let Some(i) = incident_of(&self.header, &line) {
                return Some(i);
            }
        }
    }
}

/// One row of `incidents.csv` as its [`topics::INCIDENTS`] message, if it is one.
fn incident_of(header: &[String], line: &str) -> Option<Value> {
    let fields = split_csv(line);
    if fields.len() != header.len() {
        return None;
    }
    let get = |n: &str| header.iter().position(|h| h == n).map(|i| fields[i].as_str());
    let int = |n: &str| get(n).and_then(|v| v.parse::<u64>().ok());
    let num = |n: &str| get(n).and_then(|v| v.parse::<f64>().ok()).filter(|v| v.is_finite());
    let text = |n: &str| get(n).map(str::to_owned);
    let (start, end) = (int("start_tick")?, int("end_tick")?);
    Some(serde_json::json!({
        "start_tick": start,
        "end_tick": end,
        "start_s": num("start_s"),
        "duration_s": num("duration_s"),
        "kind": text("kind").unwrap_or_default(),
        "cause_role": text("cause_role"),
        "cause_stage": text("cause_stage"),
        "evidence": text("evidence"),
        "flags": text("flags").unwrap_or_default(),
        "misses": int("misses").unwrap_or_default(),
        "peak_deviation_deg": num("peak_deviation_deg"),
        "recovery_s": num("recovery_s"),
        "analysed": true,
    }))
}

/// A CSV line's fields (`"…"` quoted, `""` a quote inside).
fn split_csv(line: &str) -> Vec<String> {
    let (mut fields, mut field, mut quoted) = (Vec::new(), String::new(), false);
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        match (c, quoted) {
            ('"', true) if chars.peek() == Some(&'"') => {
                field.push('"');
                chars.next();
            }
            ('"', _) => quoted = !quoted,
            (',', false) => fields.push(std::mem::take(&mut field)),
            (c, _) => field.push(c),
        }
    }
    fields.push(field);
    fields
}

/// A run without flight records, from its `trace.csv` (and `summary.json`, attached):
/// `/tf` and `/rotorloop/tracking` at the simulated time of each row.
fn write_trace_messages(sink: &mut FileSink, dir: &Path, plan: Plan) -> anyhow::Result<Kept> {
    let mut rows = open_trace(dir)?;
    let columns = rows.columns();
    let col = |n: &str| {
        columns.iter().position(|c| c == n).with_context(|| format!("trace.csv has no {n} column"))
    };
    let (t, r11, rd11, tick) = (col("t")?, col("R11")?, col("Rd11")?, col("tick")?);
    let nine = |row: &[f64], at: usize| -> [f64; 9] {
        let mut m = [0.0; 9];
        m.copy_from_slice(&row[at..at + 9]);
        m
    };
    let mut meta = BTreeMap::from([("clock".to_owned(), "simulated time (ns)".to_owned())]);
    meta.insert("rotorloop_version".into(), env!("CARGO_PKG_VERSION").into());
    meta.insert("detail".into(), plan.name().into());
    meta.insert("window_ticks".into(), plan.window.to_string());
    // The file attached as it is; its keys in the metadata where it reads as a summary.
    let summary = std::fs::read(dir.join("summary.json")).ok();
    if let Ok(s) = Summary::read(dir) {
        for key in ["name", "ticks", "dt", "actuation"] {
            meta.extend(s.text(key).map(|v| (key.to_owned(), v)));
        }
    }
    let metadata = mcap::records::Metadata { name: "rotorloop".into(), metadata: meta };
    sink.writer.write_metadata(&metadata)?;
    if let Some(data) = summary {
        let name = "summary.json".into();
        let media_type = "application/json".into();
        let a =
            mcap::Attachment { log_time: 0, create_time: 0, name, media_type, data: data.into() };
        sink.writer.attach(&a)?;
    }
    let mut kept = Kept::default();
    while let Some((_, line)) = rows.next_row() {
        let row = parse_row(&line);
        if row.len() != columns.len() {
            continue;
        }
        if plan.overview && (row[tick].max(0.0) as u64) % plan.window != 0 {
            continue;
        }
        kept.ticks += 1;
        let ns = (row[t] * 1e9).round() as u64;
        sink.encoded(topics::TF, &transform("world", "body", &nine(&row[..], r11), ns), ns)?;
        sink.encoded(topics::TF, &transform("world", "reference", &nine(&row[..], rd11), ns), ns)?;
        // A run in process has no incidents (nothing of it is late).
        sink.json(topics::TRACKING.topic, &tracking_row(&columns, &row, None), ns)?;
    }
    Ok(kept)
}

/// A `trace.csv` row as its [`topics::TRACKING`] message: the tick, the
/// [`topics::TRACKING_COLUMNS`] (`null` where the trace has no such column, or NaN), and
/// whether the tick is in an incident's window (`None`: not known).
fn tracking_row(columns: &[String], row: &[f64], in_incident: Option<bool>) -> Value {
    let mut m = serde_json::Map::new();
    for c in topics::TRACKING_COLUMNS {
        let v = columns.iter().position(|n| n == c).and_then(|i| row.get(i)).copied();
        m.insert((*c).to_owned(), serde_json::json!(v.filter(|v| v.is_finite())));
    }
    let tick = columns.iter().position(|n| n == "tick").and_then(|i| row.get(i)).copied();
    m.insert("tick".into(), serde_json::json!(tick.unwrap_or_default().max(0.0) as u64));
    m.insert("in_incident".into(), serde_json::json!(in_incident.map(u8::from)));
    Value::Object(m)
}

/// The run's faults and warnings from `summary.json`, at their times: a fault's `kill_s`
/// is seconds after the first state's publish (`t0`).
fn events(run: &Run, t0: u64) -> Vec<(u64, foxglove::messages::log::Level, String, String)> {
    use foxglove::messages::log::Level;
    let Some(s) = &run.summary else { return Vec::new() };
    let at = |secs: f64| t0 + (secs.max(0.0) * 1e9) as u64;
    let mut out = Vec::new();
    for f in &s.faults {
        let (role, kind, detail, at_s) = (f.role.clone(), &f.kind, &f.detail, at(f.kill_s));
        let tick = f.kill_tick.map_or(String::new(), |k| format!(" (after tick {k})"));
        out.push((at_s, Level::Error, role.clone(), format!("fault: {kind}{tick}: {detail}")));
        if let Some(r) = f.restart_s {
            out.push((at(r), Level::Info, role.clone(), format!("{kind}: restarted or continued")));
        }
        if let (Some(how), Some(e)) = (&f.ended, f.ended_s) {
            out.push((at(e), Level::Info, role, format!("stop ended: {how}")));
        }
    }
    let last = run.states.last().and_then(|k| run.states.get(k));
    let end =
        last.map_or(t0, |l| if l.publish_ns != 0 { l.publish_ns } else { (l.t_s * 1e9) as u64 });
    for w in &s.storage_errors {
        out.push((end, Level::Warning, Role::Monitor.name().into(), w.clone()));
    }
    for w in &s.warnings {
        out.push((end, Level::Warning, "launcher".into(), w.clone()));
    }
    out.sort_by_key(|e| e.0);
    out
}

/// The metadata record: the run, its clock, and where to find its wall time.
fn metadata(run: &Run, first: Option<&StateSample>, plan: Plan) -> BTreeMap<String, String> {
    let mut m = BTreeMap::new();
    let realtime = first.is_some_and(|s| s.publish_ns != 0);
    m.insert(
        "clock".into(),
        if realtime { "CLOCK_MONOTONIC ns (the loop's own stamps)" } else { "simulated time (ns)" }
            .into(),
    );
    if let Some(s) = &run.summary {
        for key in ["scenario", "mode", "rate_hz", "ticks", "completed", "wall_clock_start_unix_ns"]
        {
            m.extend(s.text(key).map(|v| (key.to_owned(), v)));
        }
    }
    if let Some(s) = first {
        m.insert("first_state_publish_ns".into(), s.publish_ns.to_string());
    }
    m.insert("rotorloop_version".into(), env!("CARGO_PKG_VERSION").into());
    m.insert("detail".into(), plan.name().into());
    m.insert("window_ticks".into(), plan.window.to_string());
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The ticks an overview keeps at full rate: each incident's window from `before`
    /// ticks ahead of it to `after` past its end, overlapping windows once, the first
    /// incidents' first, until the budget is spent (the last window cut short, the
    /// incidents after it not kept, but counted).
    #[test]
    fn full_rate_windows_follow_the_incidents_within_their_budget() {
        let dir = tempfile::tempdir().expect("tempdir");
        let csv = dir.path().join("incidents.csv");
        let rows = ["start_tick,end_tick", "100,110", "115,130", "500,520", "900,950"];
        std::fs::write(&csv, rows.join("\n") + "\n").expect("write");
        let plan = Plan { overview: true, window: 10, before: 10, after: 20, full_rate_ticks: 100 };
        let mut f = FullRate::new(&csv, plan);
        let kept: Vec<u64> = (0..1000).filter(|k| f.holds(*k)).collect();
        // 90–150 (61 ticks: the first two windows as one), then 490–528 (39: the budget).
        let want: Vec<u64> = (90..=150).chain(490..=528).collect();
        assert_eq!(kept, want);
        assert_eq!((f.incidents, f.windows, f.left), (4, 3, 0));
    }

    /// The quaternion of an attitude gives back the attitude (to rounding), for rotations
    /// near 0 and near π, where a careless conversion loses the axis.
    #[test]
    fn a_quaternion_gives_back_its_attitude() {
        for (axis, angle) in [
            (glam::DVec3::X, 0.0),
            (glam::DVec3::new(1.0, 2.0, 3.0).normalize(), 1.0),
            (glam::DVec3::new(-1.0, 0.5, 0.2).normalize(), std::f64::consts::PI - 1e-9),
        ] {
            let m = DMat3::from_axis_angle(axis, angle);
            let r = m.transpose().to_cols_array(); // row major
            let q = quaternion(&r);
            let back = DMat3::from_quat(q);
            let diff = (back - m).to_cols_array().iter().fold(0.0f64, |a, v| a.max(v.abs()));
            assert!(diff < 1e-12, "{axis:?} {angle}: {diff}");
        }
    }
}
