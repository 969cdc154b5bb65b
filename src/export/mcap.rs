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
use rotorloop_common::wire::{
    FLAG_REALTIME, FLAG_SAFE_MODE, NO_TICK, ReferenceSample, StateSample, TorqueSample,
};
use rotorloop_monitor::derive::Csv;
use rotorloop_monitor::rows::{TickRows, records_dir};
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
}

/// The records and files of one run directory.
struct Run {
    states: FlightLog<StateSample>,
    torques: Option<FlightLog<TorqueSample>>,
    /// The plant's record of what it received: the answer where the controller's record
    /// lacks it (a controller killed between its publish and its record).
    received: FlightLog<TorqueSample>,
    references: FlightLog<ReferenceSample>,
    /// `trace.csv`, a row at a time in tick order.
    trace: std::cell::RefCell<TickRows>,
    trace_columns: Vec<String>,
    summary: Option<Value>,
}

impl Run {
    fn read(dir: &Path) -> anyhow::Result<Self> {
        let summary = std::fs::read_to_string(dir.join("summary.json"))
            .ok()
            .and_then(|t| serde_json::from_str::<Value>(&t).ok());
        let flight = records_dir(dir, summary.as_ref());
        let missing = || {
            format!(
                "{} has no flight records to export (rotorloop run records them)",
                dir.display()
            )
        };
        // The run's ticks as its summary says (a later tick is not the run's; without a
        // summary the records' own geometry bounds them).
        let ticks = summary.as_ref().and_then(|s| s["ticks"].as_u64()).unwrap_or(u64::MAX);
        let limit = ticks.saturating_add(SPARE_SLOTS);
        let states = FlightLog::read(&flight, Stream::PlantState, limit).with_context(missing)?;
        let received =
            FlightLog::read(&flight, Stream::PlantTorque, limit).with_context(missing)?;
        let torques = FlightLog::read(&flight, Stream::ControllerTorque, limit).ok();
        let references =
            FlightLog::read(&flight, Stream::Reference, limit).with_context(missing)?;
        let trace = open_trace(dir)?;
        let trace_columns = trace.columns();
        let trace = trace.into();
        Ok(Self { states, torques, received, references, trace, trace_columns, summary })
    }

    fn torque(&self, k: u64) -> Option<TorqueSample> {
        self.torques.as_ref().and_then(|t| t.get(k)).or_else(|| self.received.get(k))
    }

    /// The trace row of tick `k` (asked for in increasing order), every value a float.
    fn trace_row(&self, k: u64) -> Option<Vec<f64>> {
        self.trace.borrow_mut().row(k).map(|l| parse_row(&l))
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
    writer: mcap::Writer<std::io::BufWriter<std::fs::File>>,
    channels: BTreeMap<&'static str, (u16, u32, u64)>,
}

impl FileSink {
    /// A sink writing `part` in chunks of `chunk` bytes of messages.
    fn create(part: &Path, chunk: u64) -> anyhow::Result<Self> {
        let file = std::fs::File::create(part)
            .with_context(|| format!("cannot write {}", part.display()))?;
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
        self.writer.into_inner().flush()?;
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

/// The per-tick latency of state `s` answered by `t` (ns; `null` where a stamp is
/// missing), the stages of the controller, and the state of the loop ([`topics::LATENCY`]).
pub(crate) fn latency(
    s: &StateSample,
    t: Option<&TorqueSample>,
    r: Option<&ReferenceSample>,
) -> Value {
    let d = |a: u64, b: u64| (a != 0 && b != 0 && a >= b).then(|| a - b);
    let answered = t.filter(|t| t.tick == s.tick);
    serde_json::json!({
        "tick": s.tick,
        "t_s": s.t_s,
        "state_transport_ns": answered.and_then(|t| d(t.state_recv_ns, s.publish_ns)),
        "controller_compute_ns": answered.and_then(|t| d(t.publish_ns, t.state_recv_ns)),
        "validate_ns": answered.and_then(|t| d(t.validated_ns, t.state_recv_ns)),
        "pair_ns": answered.and_then(|t| d(t.paired_ns, t.validated_ns)),
        "law_ns": answered.and_then(|t| d(t.computed_ns, t.paired_ns)),
        "publish_prep_ns": answered.and_then(|t| d(t.publish_ns, t.computed_ns)),
        "tick_lateness_ns": (s.flags & FLAG_REALTIME != 0).then(|| d(s.wake_ns, s.deadline_ns)).flatten(),
        "state_prep_ns": (s.flags & FLAG_REALTIME != 0).then(|| d(s.publish_ns, s.wake_ns)).flatten(),
        "reference_lead_ns": r.and_then(|r| d(s.publish_ns, r.publish_ns)),
        "state_send_ns": s.prev_publish.send_ns,
        "misses": s.misses,
        "safe_mode": s.flags & FLAG_SAFE_MODE != 0,
        "torque_in_force_tick": (s.applied_torque_tick != NO_TICK).then_some(s.applied_torque_tick),
        "torque_in_force_recv_ns": s.applied_torque_recv_ns,
    })
}

/// Writes `DIR/run.mcap` from the run in `dir` (records, `trace.csv`, `summary.json`,
/// `incidents.csv`): through a `.part` file renamed when complete, so a reader never sees
/// half a file.
pub fn write(dir: &Path) -> anyhow::Result<McapCounts> {
    // A run in process (`sim`, `sim --replay`, `paper`'s in-process runs) has no flight
    // records: its trace alone (attitudes, tracking) in simulated time.
    let records = Stream::PlantState.path(&records_dir(dir, None)).exists()
        || !dir.join("trace.csv").exists();
    let run = if records { Some(Run::read(dir)?) } else { None };
    let path = dir.join("run.mcap");
    let part = dir.join("run.mcap.part");
    let long = match &run {
        Some(run) => run.summary.as_ref().and_then(|s| s["ticks"].as_u64()),
        None => std::fs::metadata(dir.join("trace.csv")).ok().map(|m| m.len() / TRACE_ROW_BYTES),
    }
    .is_some_and(|ticks| ticks >= LONG_RUN_TICKS);
    let chunk = if long { MCAP_LONG_CHUNK_BYTES } else { MCAP_CHUNK_BYTES };
    let written = FileSink::create(&part, chunk).and_then(|mut sink| {
        match &run {
            Some(run) => write_messages(&mut sink, run, dir)?,
            None => write_trace_messages(&mut sink, dir)?,
        }
        let counts = sink.counts();
        sink.finish()?;
        Ok(counts)
    });
    let counts = match written {
        Ok(c) => c,
        Err(e) => {
            let _ = std::fs::remove_file(&part);
            return Err(e.context(format!("cannot write {}", path.display())));
        }
    };
    std::fs::rename(&part, &path).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(McapCounts { path: path.display().to_string(), messages: counts })
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
/// Ticks from which a run is written in the longer chunks: an hour at 1 kHz.
const LONG_RUN_TICKS: u64 = 3_600_000;
/// About the bytes of a `trace.csv` row: what a run in process (no summary) is counted by
/// (measured: 796 a row in a 4 s real-time `paper-sinusoid` trace).
const TRACE_ROW_BYTES: u64 = 800;

fn write_messages(sink: &mut FileSink, run: &Run, dir: &Path) -> anyhow::Result<()> {
    let first = run.states.iter().next();
    let first = first.as_ref();
    let realtime = first.is_some_and(|s| s.publish_ns != 0);
    // Without stamps (a run in process) the log time is the simulated time.
    let time = |stamp: u64, t_s: f64| if realtime { stamp } else { (t_s * 1e9) as u64 };
    let t0 = first.map_or(0, |s| time(s.publish_ns, s.t_s));
    sink.writer.write_metadata(&mcap::records::Metadata {
        name: "rotorloop".into(),
        metadata: metadata(run, first),
    })?;
    if let Some(s) = &run.summary {
        sink.writer.attach(&mcap::Attachment {
            log_time: t0,
            create_time: t0,
            name: "summary.json".into(),
            media_type: "application/json".into(),
            data: serde_json::to_vec_pretty(s)?.into(),
        })?;
    }
    let mut incidents = Incidents::open(&dir.join("incidents.csv"));
    // An incident's message is at its first tick's state, else at its start after `t0`.
    let incident_time = |i: &Value| {
        let at_s = i["start_s"].as_f64().unwrap_or_default();
        let start = i["start_tick"].as_u64().unwrap_or_default();
        run.states.get(start).map_or(t0 + (at_s * 1e9) as u64, |s| time(s.publish_ns, s.t_s))
    };
    let columns = &run.trace_columns;
    let mut safe = false;
    for s in run.states.iter() {
        let s = &s;
        let k = s.tick;
        let ns = time(s.publish_ns, s.t_s);
        // The incidents that start by this tick, each at its start's time.
        while let Some(i) = incidents.starting_by(k) {
            sink.json(topics::INCIDENTS.topic, &i, incident_time(&i))?;
        }
        sink.json(topics::STATE.topic, &topics::state_json(s), ns)?;
        let t = run.torque(k);
        let t = t.as_ref();
        if let Some(t) = t {
            sink.json(topics::TORQUE.topic, &topics::torque_json(t), time(t.publish_ns, s.t_s))?;
        }
        let r = run.references.get(k);
        let r = r.as_ref();
        if let Some(r) = r {
            let at = time(r.publish_ns, r.t_s);
            sink.json(topics::REFERENCE.topic, &topics::reference_json(r), at)?;
            sink.encoded(topics::TF, &transform("world", "reference", &r.r_d_row_major, ns), ns)?;
        }
        sink.encoded(topics::TF, &transform("world", "body", &s.r_row_major, ns), ns)?;
        sink.json(topics::LATENCY.topic, &latency(s, t, r), ns)?;
        if let Some(row) = run.trace_row(k) {
            let row = tracking_row(columns, &row, Some(incidents.holds(k)));
            sink.json(topics::TRACKING.topic, &row, ns)?;
        }
        let now_safe = s.flags & FLAG_SAFE_MODE != 0;
        if now_safe != safe {
            let m = safe_mode_message(now_safe, k);
            sink.encoded(topics::LOG, &log_message(ns, m.0, "plant", m.1), ns)?;
            safe = now_safe;
        }
    }
    // Those that start after the last state (a fault outside the loop at its end).
    while let Some(i) = incidents.starting_by(u64::MAX) {
        sink.json(topics::INCIDENTS.topic, &i, incident_time(&i))?;
    }
    for (ns, level, name, message) in events(run, t0) {
        sink.encoded(topics::LOG, &log_message(ns, level, &name, message), ns)?;
    }
    Ok(())
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
        if self.next.is_none() {
            self.next = self.read();
        }
        let start = self.next.as_ref()?["start_tick"].as_u64()?;
        if start > k {
            return None;
        }
        let i = self.next.take()?;
        self.open.push([start, i["end_tick"].as_u64().unwrap_or(start)]);
        Some(i)
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
fn write_trace_messages(sink: &mut FileSink, dir: &Path) -> anyhow::Result<()> {
    let mut rows = open_trace(dir)?;
    let columns = rows.columns();
    let col = |n: &str| {
        columns.iter().position(|c| c == n).with_context(|| format!("trace.csv has no {n} column"))
    };
    let (t, r11, rd11) = (col("t")?, col("R11")?, col("Rd11")?);
    let nine = |row: &[f64], at: usize| -> [f64; 9] {
        let mut m = [0.0; 9];
        m.copy_from_slice(&row[at..at + 9]);
        m
    };
    let mut meta = BTreeMap::from([("clock".to_owned(), "simulated time (ns)".to_owned())]);
    meta.insert("rotorloop_version".into(), env!("CARGO_PKG_VERSION").into());
    let summary = std::fs::read(dir.join("summary.json")).ok();
    if let Some(v) = summary.as_deref().and_then(|b| serde_json::from_slice::<Value>(b).ok()) {
        for key in ["name", "ticks", "dt", "actuation"] {
            if !v[key].is_null() {
                meta.insert(key.into(), v[key].to_string().trim_matches('"').to_owned());
            }
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
    while let Some((_, line)) = rows.next_row() {
        let row = parse_row(&line);
        if row.len() != columns.len() {
            continue;
        }
        let ns = (row[t] * 1e9).round() as u64;
        sink.encoded(topics::TF, &transform("world", "body", &nine(&row[..], r11), ns), ns)?;
        sink.encoded(topics::TF, &transform("world", "reference", &nine(&row[..], rd11), ns), ns)?;
        // A run in process has no incidents (nothing of it is late).
        sink.json(topics::TRACKING.topic, &tracking_row(&columns, &row, None), ns)?;
    }
    Ok(())
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
    for f in s["faults"].as_array().into_iter().flatten() {
        let role = f["role"].as_str().unwrap_or("?").to_owned();
        let (kind, detail) =
            (f["kind"].as_str().unwrap_or("?"), f["detail"].as_str().unwrap_or(""));
        let tick = f["kill_tick"].as_u64().map_or(String::new(), |k| format!(" (after tick {k})"));
        let at_s = f["kill_s"].as_f64().unwrap_or(0.0);
        out.push((at(at_s), Level::Error, role.clone(), format!("fault: {kind}{tick}: {detail}")));
        if let Some(r) = f["restart_s"].as_f64() {
            out.push((at(r), Level::Info, role.clone(), format!("{kind}: restarted or continued")));
        }
        if let (Some(how), Some(e)) = (f["ended"].as_str(), f["ended_s"].as_f64()) {
            out.push((at(e), Level::Info, role, format!("stop ended: {how}")));
        }
    }
    let last = run.states.last().and_then(|k| run.states.get(k));
    let end =
        last.map_or(t0, |l| if l.publish_ns != 0 { l.publish_ns } else { (l.t_s * 1e9) as u64 });
    for w in s["storage_errors"].as_array().into_iter().flatten().filter_map(Value::as_str) {
        out.push((end, Level::Warning, "monitor".into(), w.to_owned()));
    }
    for w in s["warnings"].as_array().into_iter().flatten().filter_map(Value::as_str) {
        out.push((end, Level::Warning, "launcher".into(), w.to_owned()));
    }
    out.sort_by_key(|e| e.0);
    out
}

/// The metadata record: the run, its clock, and where to find its wall time.
fn metadata(run: &Run, first: Option<&StateSample>) -> BTreeMap<String, String> {
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
            if !s[key].is_null() {
                m.insert(key.into(), s[key].to_string().trim_matches('"').to_owned());
            }
        }
    }
    if let Some(s) = first {
        m.insert("first_state_publish_ns".into(), s.publish_ns.to_string());
    }
    m.insert("rotorloop_version".into(), env!("CARGO_PKG_VERSION").into());
    m
}

#[cfg(test)]
mod tests {
    use super::*;

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
