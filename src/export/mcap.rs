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
//! | `/rotorloop/tracking` | JSON: attitude and rate error, momentum drift, energy residual, delay in force | tick (from `trace.csv`) |
//! | `/rotorloop/latency` | JSON: the hops, stages, lateness, misses, safe mode, the torque in force | tick |
//! | `/rotorloop/log` | `foxglove.Log`: faults, safe mode entered and left, the report's warnings | event |
//! | `/tf` | `foxglove.FrameTransform`: `world → body` and `world → reference` | tick, each |
//!
//! Log times are the loop's own `CLOCK_MONOTONIC` stamps (the state's publish time, the
//! torque's and the reference's), not wall time; a run in process (no stamps) uses its
//! simulated time. The file's metadata record `rotorloop` says how to map them to wall
//! time: `clock`, and the wall time of the first state's publish where the run recorded it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::Context as _;
use foxglove::messages::{FrameTransform, Log, Quaternion, Timestamp, Vector3};
use foxglove::{Channel, ChannelBuilder, Context, McapAttachment, McapWriter, RawChannel, Schema};
use glam::{DMat3, DQuat};
use rotorloop_common::flight::{FlightLog, SPARE_SLOTS, Stream};
use rotorloop_common::wire::{
    FLAG_REALTIME, FLAG_SAFE_MODE, ReferenceSample, StateSample, TorqueSample,
};
use rotorloop_monitor::rows::TickRows;
use serde::Serialize;
use serde_json::Value;

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

/// Where a run directory's flight records are: `DIR/flight`, or where its summary says
/// they stayed (a run whose records could not be moved).
fn records_dir(dir: &Path, summary: Option<&Value>) -> PathBuf {
    let kept = dir.join("flight");
    if Stream::PlantState.path(&kept).exists() {
        return kept;
    }
    summary
        .and_then(|s| s["flight"]["dir"].as_str())
        .map(PathBuf::from)
        .filter(|d| Stream::PlantState.path(d).exists())
        .unwrap_or(kept)
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
        let trace = open_trace(&dir.join("trace.csv"))?;
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

/// Opens `trace.csv` to be read a row at a time.
fn open_trace(path: &Path) -> anyhow::Result<TickRows> {
    TickRows::open(path)
        .with_context(|| format!("cannot read {} (the run's report)", path.display()))
}

/// A trace row's values (NaN where one is not a number).
fn parse_row(line: &str) -> Vec<f64> {
    line.split(',').map(|v| v.parse().unwrap_or(f64::NAN)).collect()
}

/// A JSON channel with a JSON schema derived from its first message.
pub(crate) struct JsonChannel {
    ctx: Arc<Context>,
    topic: String,
    schema_name: &'static str,
    channel: Option<Arc<RawChannel>>,
    count: u64,
}

impl JsonChannel {
    pub(crate) fn new(ctx: &Arc<Context>, topic: &str, schema_name: &'static str) -> Self {
        let (ctx, topic) = (ctx.clone(), topic.to_owned());
        Self { ctx, topic, schema_name, channel: None, count: 0 }
    }

    /// Logs `value` as JSON at `log_time`: serialized straight to bytes (a [`Value`] tree is
    /// built only once, for the schema of the first message).
    pub(crate) fn log<T: Serialize>(&mut self, value: &T, log_time: u64) -> anyhow::Result<()> {
        if self.channel.is_none() {
            let schema = serde_json::to_vec(&json_schema(&serde_json::to_value(value)?))?;
            let c = ChannelBuilder::new(self.topic.as_str())
                .context(&self.ctx)
                .message_encoding("json")
                .schema(Schema::new(self.schema_name, "jsonschema", schema))
                .build_raw()
                .with_context(|| format!("cannot make the MCAP channel {}", self.topic))?;
            self.channel = Some(c);
        }
        if let Some(c) = self.channel.as_ref().filter(|c| c.has_sinks()) {
            let bytes = serde_json::to_vec(value)?;
            c.log_with_meta(&bytes, foxglove::PartialMetadata { log_time: Some(log_time) });
        }
        self.count += 1;
        Ok(())
    }
}

/// A JSON schema of `v`'s shape (what Foxglove's plot panels offer as message paths).
fn json_schema(v: &Value) -> Value {
    match v {
        Value::Object(m) => serde_json::json!({
            "type": "object",
            "properties": m.iter().map(|(k, v)| (k.clone(), json_schema(v))).collect::<serde_json::Map<_, _>>(),
        }),
        Value::Array(a) => serde_json::json!({
            "type": "array",
            "items": a.first().map_or(serde_json::json!({}), json_schema),
        }),
        Value::Number(n) if n.is_u64() || n.is_i64() => serde_json::json!({"type": "integer"}),
        // NaN is written as null: a number or null.
        Value::Number(_) | Value::Null => serde_json::json!({"type": ["number", "null"]}),
        Value::String(_) => serde_json::json!({"type": "string"}),
        Value::Bool(_) => serde_json::json!({"type": "boolean"}),
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

/// The per-tick latency of state `s` answered by `t` (ns; `None` where a stamp is
/// missing), the stages of the controller, and the state of the loop.
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
        "torque_in_force_tick": s.applied_torque_tick as i64,
        "torque_in_force_recv_ns": s.applied_torque_recv_ns,
    })
}

/// Writes `DIR/run.mcap` from the run in `dir` (records, `trace.csv`, `summary.json`):
/// through a `.part` file renamed when complete, so a reader never sees half a file.
pub fn write(dir: &Path) -> anyhow::Result<McapCounts> {
    // A run in process (`sim`, `sim --replay`, `paper`'s in-process runs) has no flight
    // records: its trace alone (attitudes, tracking) in simulated time.
    let records = Stream::PlantState.path(&records_dir(dir, None)).exists()
        || !dir.join("trace.csv").exists();
    let run = if records { Some(Run::read(dir)?) } else { None };
    let path = dir.join("run.mcap");
    let part = dir.join("run.mcap.part");
    let ctx = Context::new();
    let file =
        std::fs::File::create(&part).with_context(|| format!("cannot write {}", part.display()))?;
    // zstd at level 1: with the writer's default, compression was over 40 % of the
    // export's time (perf), and the file was 10 % larger (docs/measurements.md).
    let options = foxglove::McapWriteOptions::default().compression_level(MCAP_ZSTD_LEVEL);
    let mcap = McapWriter::with_options(options)
        .context(&ctx)
        .create(std::io::BufWriter::new(file))
        .with_context(|| format!("cannot write {}", part.display()))?;
    let counts = match &run {
        Some(run) => write_messages(&ctx, run, &mcap),
        None => write_trace_messages(&ctx, dir, &mcap),
    };
    let closed = mcap.close().map_err(anyhow::Error::from).and_then(|mut w| {
        use std::io::Write;
        w.flush()?;
        Ok(())
    });
    let counts = match (counts, closed) {
        (Ok(c), Ok(())) => c,
        (Err(e), _) | (_, Err(e)) => {
            let _ = std::fs::remove_file(&part);
            return Err(e.context(format!("cannot write {}", path.display())));
        }
    };
    std::fs::rename(&part, &path).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(McapCounts { path: path.display().to_string(), messages: counts })
}

/// The zstd level of `run.mcap`'s chunks.
const MCAP_ZSTD_LEVEL: u32 = 1;

type Handle = foxglove::McapWriterHandle<std::io::BufWriter<std::fs::File>>;

fn write_messages(
    ctx: &Arc<Context>,
    run: &Run,
    mcap: &Handle,
) -> anyhow::Result<BTreeMap<String, u64>> {
    use foxglove::messages::log::Level;
    let mut state = JsonChannel::new(ctx, "/rotorloop/state", "rotorloop.StateSample");
    let mut torque = JsonChannel::new(ctx, "/rotorloop/torque", "rotorloop.TorqueSample");
    let mut reference = JsonChannel::new(ctx, "/rotorloop/reference", "rotorloop.ReferenceSample");
    let mut tracking = JsonChannel::new(ctx, "/rotorloop/tracking", "rotorloop.Tracking");
    let mut lat = JsonChannel::new(ctx, "/rotorloop/latency", "rotorloop.Latency");
    let tf: Channel<FrameTransform> = ChannelBuilder::new("/tf").context(ctx).build();
    let log: Channel<Log> = ChannelBuilder::new("/rotorloop/log").context(ctx).build();
    let (mut tfs, mut logs) = (0u64, 0u64);
    let first = run.states.iter().next();
    let first = first.as_ref();
    let realtime = first.is_some_and(|s| s.publish_ns != 0);
    // Without stamps (a run in process) the log time is the simulated time.
    let time = |stamp: u64, t_s: f64| if realtime { stamp } else { (t_s * 1e9) as u64 };
    let t0 = first.map_or(0, |s| time(s.publish_ns, s.t_s));
    mcap.write_metadata("rotorloop", metadata(run, first))?;
    if let Some(s) = &run.summary {
        mcap.attach(&McapAttachment {
            log_time: t0,
            create_time: t0,
            name: "summary.json".into(),
            media_type: "application/json".into(),
            data: serde_json::to_vec_pretty(s)?.into(),
        })?;
    }
    let columns = &run.trace_columns;
    let mut safe = false;
    for s in run.states.iter() {
        let s = &s;
        let k = s.tick;
        let ns = time(s.publish_ns, s.t_s);
        state.log(s, ns)?;
        let t = run.torque(k);
        let t = t.as_ref();
        if let Some(t) = t {
            torque.log(t, time(t.publish_ns, s.t_s))?;
        }
        let r = run.references.get(k);
        let r = r.as_ref();
        if let Some(r) = r {
            reference.log(r, time(r.publish_ns, r.t_s))?;
            tf.log_with_time(&transform("world", "reference", &r.r_d_row_major, ns), ns);
            tfs += 1;
        }
        tf.log_with_time(&transform("world", "body", &s.r_row_major, ns), ns);
        tfs += 1;
        lat.log(&latency(s, t, r), ns)?;
        if let Some(row) = run.trace_row(k) {
            tracking.log(&tracking_row(columns, &row), ns)?;
        }
        let now_safe = s.flags & FLAG_SAFE_MODE != 0;
        if now_safe != safe {
            let what = if now_safe { "entered safe mode" } else { "left safe mode" };
            log.log_with_time(
                &log_message(ns, Level::Warning, "plant", format!("tick {k}: {what}")),
                ns,
            );
            logs += 1;
            safe = now_safe;
        }
    }
    for (ns, level, name, message) in events(run, t0) {
        log.log_with_time(&log_message(ns, level, &name, message), ns);
        logs += 1;
    }
    let mut counts = BTreeMap::new();
    for c in [&state, &torque, &reference, &tracking, &lat] {
        counts.insert(c.topic.clone(), c.count);
    }
    counts.insert("/tf".into(), tfs);
    counts.insert("/rotorloop/log".into(), logs);
    Ok(counts)
}

/// A run without flight records, from its `trace.csv` (and `summary.json`, attached):
/// `/tf` and `/rotorloop/tracking` at the simulated time of each row.
fn write_trace_messages(
    ctx: &Arc<Context>,
    dir: &Path,
    mcap: &Handle,
) -> anyhow::Result<BTreeMap<String, u64>> {
    let mut rows = open_trace(&dir.join("trace.csv"))?;
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
    mcap.write_metadata("rotorloop", meta)?;
    if let Some(data) = summary {
        let name = "summary.json".into();
        let media_type = "application/json".into();
        let a = McapAttachment { log_time: 0, create_time: 0, name, media_type, data: data.into() };
        mcap.attach(&a)?;
    }
    let mut tracking = JsonChannel::new(ctx, "/rotorloop/tracking", "rotorloop.Tracking");
    let tf: Channel<FrameTransform> = ChannelBuilder::new("/tf").context(ctx).build();
    let mut tfs = 0u64;
    while let Some((_, line)) = rows.next_row() {
        let row = parse_row(&line);
        if row.len() != columns.len() {
            continue;
        }
        let ns = (row[t] * 1e9).round() as u64;
        tf.log_with_time(&transform("world", "body", &nine(&row[..], r11), ns), ns);
        tf.log_with_time(&transform("world", "reference", &nine(&row[..], rd11), ns), ns);
        tfs += 2;
        tracking.log(&tracking_row(&columns, &row), ns)?;
    }
    Ok(BTreeMap::from([("/tf".to_owned(), tfs), (tracking.topic.clone(), tracking.count)]))
}

/// A `trace.csv` row's [`TRACKING`] columns as a JSON object.
fn tracking_row(columns: &[String], row: &[f64]) -> Value {
    let m: serde_json::Map<String, Value> = columns
        .iter()
        .zip(row)
        .filter(|(c, _)| TRACKING.contains(&c.as_str()))
        .map(|(c, v)| (c.clone(), serde_json::json!(v)))
        .collect();
    Value::Object(m)
}

/// `trace.csv`'s columns on `/rotorloop/tracking`.
const TRACKING: &[&str] = &[
    "t",
    "tick",
    "err_deg",
    "werr",
    "h_drift_rel",
    "energy_residual",
    "delay_s",
    "u1",
    "u2",
    "u3",
];

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

    /// A schema follows its message's shape: integers, numbers or null, arrays, objects.
    #[test]
    fn the_schema_follows_the_message() {
        let v = serde_json::json!({"tick": 3, "x": 0.5, "r": [1.0, 2.0], "nan": null});
        let s = json_schema(&v);
        assert_eq!(s["properties"]["tick"]["type"], "integer");
        assert_eq!(s["properties"]["r"]["items"]["type"], serde_json::json!(["number", "null"]));
        assert_eq!(s["properties"]["nan"]["type"], serde_json::json!(["number", "null"]));
    }
}
