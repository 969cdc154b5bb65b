//! `run.mcap`: a run as an MCAP file, read back with the `mcap` crate and `prost` (not
//! with the writer's own code), as Foxglove would read it.

use std::collections::BTreeMap;
use std::time::Duration;

use crate::common::harness::{Harness, json, ok};
use crate::common::schemas::Schemas;

const LIMIT: Duration = Duration::from_secs(180);

/// The attitude of a unit quaternion (x, y, z, w), row major: the textbook formula, not
/// the writer's conversion.
fn rotation(x: f64, y: f64, z: f64, w: f64) -> [f64; 9] {
    [
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - z * w),
        2.0 * (x * z + y * w),
        2.0 * (x * y + z * w),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - x * w),
        2.0 * (x * z - y * w),
        2.0 * (y * z + x * w),
        1.0 - 2.0 * (x * x + y * y),
    ]
}

/// `trace.csv`'s attitude `R` by tick.
fn trace_attitudes(out: &std::path::Path) -> BTreeMap<u64, [f64; 9]> {
    let text = std::fs::read_to_string(out.join("trace.csv")).expect("trace");
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let col = |n: &str| header.iter().position(|h| *h == n).expect(n);
    let (r11, tick) = (col("R11"), col("tick"));
    lines
        .map(|l| {
            let f: Vec<f64> = l.split(',').map(|v| v.parse().expect("number")).collect();
            let mut r = [0.0; 9];
            r.copy_from_slice(&f[r11..r11 + 9]);
            (f[tick] as u64, r)
        })
        .collect()
}

/// Every channel of the file (its summary's, also those without a message): topic →
/// (schema name, schema data, messages).
fn channels(bytes: &[u8]) -> BTreeMap<String, (String, Vec<u8>, u64)> {
    let summary = mcap::Summary::read(bytes).expect("readable").expect("a summary");
    let counts =
        summary.stats.as_ref().map(|s| s.channel_message_counts.clone()).unwrap_or_default();
    summary
        .channels
        .values()
        .map(|c| {
            let (name, data) =
                c.schema.as_ref().map(|s| (s.name.clone(), s.data.to_vec())).unwrap_or_default();
            (c.topic.clone(), (name, data, counts.get(&c.id).copied().unwrap_or(0)))
        })
        .collect()
}

/// A real-time run whose controller and monitor were killed (SIGKILL) and restarted is one
/// MCAP file: one state message per tick, the body's and the reference's attitudes as
/// `foxglove.FrameTransform`s whose quaternions give back `trace.csv`'s `R` within 1e-12,
/// every fault of the report as a log message, every JSON message valid against its
/// channel's schema (a JSON Schema validator) and none carrying `NO_TICK` as a number, one
/// `/rotorloop/incidents` message per row of `incidents.csv` with the incidents' ticks
/// marked on `/rotorloop/tracking`, and `rotorloop export` writes the same file again from
/// the run directory.
#[test]
fn a_run_with_kills_is_one_mcap_file_with_every_tick_its_attitudes_and_its_faults() {
    let h = Harness::new("mcap");
    let out = h.path("rt");
    let dir = out.to_str().expect("utf8");
    let mut args = vec!["run", "--scenario", "paper-zero", "--duration", "4", "--mode", "realtime"];
    let faults = "controller:kill@1:restart@1.2 monitor:kill@2:restart@2.3";
    args.extend(faults.split(' ').flat_map(|f| ["--fault", f]));
    args.extend(["--domain", &h.domain, "--out", dir]);
    let said = ok(&h.rotorloop(&args, LIMIT));
    let s = json(&out.join("summary.json"));
    let kinds: Vec<&str> =
        s["faults"].as_array().expect("faults").iter().filter_map(|f| f["role"].as_str()).collect();
    assert!(kinds.contains(&"controller") && kinds.contains(&"monitor"), "{s}");
    let bytes = std::fs::read(out.join("run.mcap")).unwrap_or_else(|e| panic!("{e}: {said}"));

    let mut states: BTreeMap<u64, u64> = BTreeMap::new(); // publish ns → tick
    let mut ticks_seen = Vec::new();
    let mut bodies = Vec::new();
    let mut references = 0;
    let mut logs = Vec::new();
    let declared = channels(&bytes);
    let schemas: BTreeMap<String, Vec<u8>> =
        declared.iter().map(|(t, (_, data, _))| (t.clone(), data.clone())).collect();
    let mut valid = Schemas::default();
    let json_channels =
        declared.iter().filter(|(t, c)| t.starts_with("/rotorloop/") && c.0 != "foxglove.Log");
    json_channels.for_each(|(topic, (_, data, _))| valid.declare(topic, data));
    let (mut incidents, mut marked) = (Vec::new(), 0u64);
    for m in mcap::MessageStream::new(&bytes).expect("an MCAP file") {
        let m = m.expect("a message");
        if m.channel.message_encoding == "json" {
            valid.check(&m.channel.topic, &m.data);
        }
        match m.channel.topic.as_str() {
            t @ ("/rotorloop/incidents" | "/rotorloop/tracking") => {
                let v: serde_json::Value = serde_json::from_slice(&m.data).expect("json");
                match t.ends_with("incidents") {
                    true => incidents.push((v["start_tick"].as_u64(), v["end_tick"].as_u64())),
                    false => marked += v["in_incident"].as_u64().expect("known after the run"),
                }
            }
            "/rotorloop/state" => {
                assert_eq!(m.channel.message_encoding, "json");
                let v: serde_json::Value = serde_json::from_slice(&m.data).expect("json");
                let k = v["tick"].as_u64().expect("tick");
                assert_eq!(v["publish_ns"].as_u64(), Some(m.log_time), "log time: the publish");
                states.insert(m.log_time, k);
                ticks_seen.push(k);
            }
            "/tf" => {
                let schema = m.channel.schema.as_ref().expect("schema");
                assert_eq!(schema.name, "foxglove.FrameTransform");
                let t = <foxglove::messages::FrameTransform as prost::Message>::decode(&m.data[..])
                    .expect("a FrameTransform");
                assert_eq!(t.parent_frame_id, "world");
                match t.child_frame_id.as_str() {
                    "body" => bodies.push((m.log_time, t.rotation.expect("rotation"))),
                    "reference" => references += 1,
                    other => panic!("frame {other}"),
                }
            }
            "/rotorloop/log" => {
                let l = <foxglove::messages::Log as prost::Message>::decode(&m.data[..])
                    .expect("a Log");
                logs.push((l.name, l.message));
            }
            _ => {}
        }
    }
    let ticks = 4000;
    ticks_seen.sort_unstable();
    assert_eq!(ticks_seen, (0..=ticks).collect::<Vec<u64>>(), "one state message per tick");
    assert_eq!(bodies.len() as u64, ticks + 1);
    assert_eq!(references, ticks + 1, "one reference frame per tick");
    let trace = trace_attitudes(&out);
    assert_eq!(trace.len() as u64, ticks + 1);
    let mut worst = 0.0f64;
    for (ns, q) in &bodies {
        let k = states[ns];
        let r = rotation(q.x, q.y, q.z, q.w);
        let d = r.iter().zip(&trace[&k]).fold(0.0f64, |a, (x, y)| a.max((x - y).abs()));
        worst = worst.max(d);
    }
    assert!(worst < 1e-12, "quaternions against trace.csv: {worst:e}");
    for f in s["faults"].as_array().expect("faults") {
        let (role, kind) = (f["role"].as_str().expect("role"), f["kind"].as_str().expect("kind"));
        let said = format!("fault: {kind}");
        let logged = logs.iter().any(|(name, l)| name == role && l.starts_with(&said));
        assert!(logged, "{role} {kind} not in the log: {logs:?}");
    }
    check_validated_and_incidents(&out, &valid, incidents, marked);
    check_layout(&schemas);
    // Rebuilt from the run directory: the same file.
    std::fs::remove_file(out.join("run.mcap")).expect("rm");
    ok(&h.rotorloop(&["export", dir, "--mcap"], LIMIT));
    assert!(
        std::fs::read(out.join("run.mcap")).expect("again") == bytes,
        "export wrote another file"
    );
    h.assert_no_leftovers();
}

/// Every JSON topic had messages validated; one incidents message per row of
/// `incidents.csv`, with its window, and `marked` (the tracking rows with `in_incident`)
/// the ticks of their windows.
fn check_validated_and_incidents(
    out: &std::path::Path,
    valid: &Schemas,
    mut incidents: Vec<(Option<u64>, Option<u64>)>,
    marked: u64,
) {
    for topic in ["state", "torque", "reference", "tracking", "latency", "incidents"] {
        let n = valid.checked.get(&format!("/rotorloop/{topic}")).copied().unwrap_or(0);
        assert!(n > 0, "{topic}: {n} messages validated: {:?}", valid.checked);
    }
    // The incidents of incidents.csv, one message each, their ticks marked on tracking.
    let csv = std::fs::read_to_string(out.join("incidents.csv")).expect("incidents.csv");
    let rows: Vec<(Option<u64>, Option<u64>)> = csv
        .lines()
        .skip(1)
        .map(|l| {
            let mut f = l.split(',').map(|v| v.parse().ok());
            (f.next().flatten(), f.next().flatten())
        })
        .collect();
    assert!(!rows.is_empty(), "a run with kills has incidents");
    incidents.sort();
    let mut sorted = rows.clone();
    sorted.sort();
    assert_eq!(incidents, sorted, "one message per incident, with its window");
    let in_windows: u64 = {
        let mut ticks = std::collections::BTreeSet::new();
        for (a, b) in rows.iter().filter_map(|(a, b)| Some((a.as_ref()?, b.as_ref()?))) {
            ticks.extend((*a..=*b).filter(|k| *k <= 4000));
        }
        ticks.len() as u64
    };
    assert_eq!(marked, in_windows, "the ticks of the incidents' windows are marked");
}

/// Every message path of `docs/foxglove-layout.json` is a topic of the file with that
/// field in its JSON schema, its log panel's topic is there, and the frames its 3D panel
/// shows are the transforms' (what can be checked of a layout without a display).
fn check_layout(schemas: &BTreeMap<String, Vec<u8>>) {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/foxglove-layout.json");
    let layout: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path).expect("layout")).expect("json");
    let panels = layout["configById"].as_object().expect("panels");
    let mut checked = 0;
    for (id, config) in panels {
        for p in config["paths"].as_array().into_iter().flatten() {
            let value = p["value"].as_str().expect("a message path");
            let (topic, field) = value.rsplit_once('.').expect("topic.field");
            let schema = schemas.get(topic).unwrap_or_else(|| panic!("{id}: no topic {topic}"));
            let schema: serde_json::Value = serde_json::from_slice(schema).expect("a JSON schema");
            assert!(schema["properties"][field].is_object(), "{id}: {topic} has no field {field}");
            checked += 1;
        }
        for key in ["topicToRender", "topicPath"] {
            if let Some(topic) = config[key].as_str() {
                assert!(schemas.contains_key(topic), "{id}: no topic {topic}");
                checked += 1;
            }
        }
        for frame in config["transforms"].as_object().into_iter().flat_map(|t| t.keys()) {
            let frame = frame.strip_prefix("frame:").expect("frame:NAME");
            assert!(["world", "body", "reference"].contains(&frame), "{id}: frame {frame}");
            checked += 1;
        }
    }
    assert!(checked >= 12, "the layout names what it shows: {checked}");
}

/// A run in process (`sim`) has no flight records: its `run.mcap` holds the trace's
/// attitudes as transforms (giving back `R` and `R_d` within 1e-12) and its tracking rows,
/// one each per row, at the simulated time; the log and incidents channels are in it,
/// without a message (what the layout names is in every file).
#[test]
fn a_sim_run_is_an_mcap_file_of_its_trace() {
    let h = Harness::new("mcapsim");
    let out = h.path("sim");
    let dir = out.to_str().expect("utf8");
    let args = ["sim", "--scenario", "paper-sinusoid", "--duration", "2", "--no-figures"];
    ok(&h.rotorloop(&args.into_iter().chain(["--out", dir]).collect::<Vec<_>>(), LIMIT));
    let bytes = std::fs::read(out.join("run.mcap")).expect("run.mcap");
    let trace = trace_attitudes(&out);
    let text = std::fs::read_to_string(out.join("trace.csv")).expect("trace");
    let header: Vec<&str> = text.lines().next().expect("header").split(',').collect();
    let rd11 = header.iter().position(|h| *h == "Rd11").expect("Rd11");
    let desired: Vec<[f64; 9]> = text
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<f64> = l.split(',').map(|v| v.parse().expect("number")).collect();
            let mut r = [0.0; 9];
            r.copy_from_slice(&f[rd11..rd11 + 9]);
            r
        })
        .collect();
    let (mut body, mut reference, mut tracking) = (Vec::new(), Vec::new(), 0);
    for m in mcap::MessageStream::new(&bytes).expect("an MCAP file") {
        let m = m.expect("a message");
        match m.channel.topic.as_str() {
            "/tf" => {
                let t = <foxglove::messages::FrameTransform as prost::Message>::decode(&m.data[..])
                    .expect("a FrameTransform");
                let q = t.rotation.expect("rotation");
                let r = rotation(q.x, q.y, q.z, q.w);
                match t.child_frame_id.as_str() {
                    "body" => body.push(r),
                    _ => reference.push(r),
                }
            }
            "/rotorloop/tracking" => tracking += 1,
            _ => {}
        }
    }
    assert_eq!((body.len(), reference.len(), tracking), (2001, 2001, 2001));
    // A run without an event: its log and incidents channels are there, empty.
    let declared = channels(&bytes);
    for topic in ["/rotorloop/log", "/rotorloop/incidents"] {
        assert_eq!(declared.get(topic).map(|c| c.2), Some(0), "{topic}: {:?}", declared.keys());
    }
    let worst = |a: &[[f64; 9]], b: &mut dyn Iterator<Item = [f64; 9]>| {
        a.iter()
            .zip(b)
            .fold(0.0f64, |w, (x, y)| x.iter().zip(&y).fold(w, |w, (p, q)| w.max((p - q).abs())))
    };
    assert!(worst(&body, &mut trace.values().copied()) < 1e-12, "body");
    assert!(worst(&reference, &mut desired.into_iter()) < 1e-12, "reference");
}

/// Each message of `bytes` on the per-tick JSON topics by (topic, tick), and the
/// `/rotorloop/window` messages in order.
type ByTick = BTreeMap<(String, u64), Vec<u8>>;

fn per_tick(bytes: &[u8]) -> (ByTick, Vec<serde_json::Value>) {
    let (mut ticks, mut windows) = (BTreeMap::new(), Vec::new());
    for m in mcap::MessageStream::new(bytes).expect("an MCAP file") {
        let m = m.expect("a message");
        let topic = m.channel.topic.clone();
        if m.channel.message_encoding != "json" || topic == "/rotorloop/incidents" {
            continue;
        }
        let v: serde_json::Value = serde_json::from_slice(&m.data).expect("json");
        if topic == "/rotorloop/window" {
            windows.push(v);
            continue;
        }
        let k = v["tick"].as_u64().unwrap_or_else(|| panic!("{topic}: no tick in {v}"));
        assert!(ticks.insert((topic.clone(), k), m.data.to_vec()).is_none(), "{topic} {k} twice");
    }
    (ticks, windows)
}

/// An overview (`export --mcap --detail overview`, what a run of an hour or more gets) of
/// a real-time run with a kill: its `/rotorloop/window` messages are the full file's, and
/// each one's extremes are those of the full file's ticks in it (the largest of each hop,
/// attitude and rate error, the misses in it); its per-tick messages are the full file's
/// for the ticks it keeps, and it keeps exactly one tick a window (ticks 0, 100, …) and
/// every tick from 100 before each incident to a second after it. The incidents are
/// written for the test (`incidents.csv`, whose rows the export reads), so that what is
/// kept does not depend on how loaded the machine was.
#[test]
fn an_overview_keeps_a_tick_a_window_every_windows_extremes_and_the_incidents_in_full() {
    let h = Harness::new("mcapov");
    let out = h.path("rt");
    let dir = out.to_str().expect("utf8");
    let args = ["run", "--scenario", "paper-zero", "--duration", "4", "--mode", "realtime"];
    let mut args = args.to_vec();
    args.extend(["--fault", "controller:kill@1:restart@1.2", "--domain", &h.domain]);
    args.extend(["--out", dir]);
    ok(&h.rotorloop(&args, LIMIT));
    // Three incidents: two whose windows overlap, one near the end.
    let csv = std::fs::read_to_string(out.join("incidents.csv")).expect("incidents.csv");
    let header: Vec<&str> = csv.lines().next().expect("header").split(',').collect();
    let incidents: [(u64, u64); 3] = [(1500, 1510), (1520, 1600), (3950, 3990)];
    let mut rows = vec![header.join(",")];
    for (a, b) in incidents {
        let field = |n: &&str| match *n {
            "start_tick" => a.to_string(),
            "end_tick" => b.to_string(),
            "kind" => "test".into(),
            _ => String::new(),
        };
        rows.push(header.iter().map(field).collect::<Vec<_>>().join(","));
    }
    std::fs::write(out.join("incidents.csv"), rows.join("\n") + "\n").expect("incidents.csv");
    ok(&h.rotorloop(&["export", dir, "--mcap", "--detail", "full"], LIMIT));
    let full = std::fs::read(out.join("run.mcap")).expect("run.mcap");
    let said = ok(&h.rotorloop(&["export", dir, "--mcap", "--detail", "overview"], LIMIT));
    assert!(said.contains("an overview: "), "{said}");
    let overview = std::fs::read(out.join("run.mcap")).expect("the overview");
    assert!(overview.len() * 2 < full.len(), "{} of {} bytes", overview.len(), full.len());
    let (all, windows) = per_tick(&full);
    let (kept, overview_windows) = per_tick(&overview);
    assert_eq!(windows, overview_windows, "the same windows");

    // Each window's extremes, from the full file's ticks.
    let value = |topic: &str, k: u64| -> Option<serde_json::Value> {
        let m = all.get(&(format!("/rotorloop/{topic}"), k))?;
        Some(serde_json::from_slice(m).expect("json"))
    };
    let hops = ["state_transport_ns", "controller_compute_ns", "law_ns", "tick_lateness_ns"];
    let mut misses_before = 0;
    assert_eq!(windows.len(), 41, "4 001 ticks in windows of 100");
    for w in &windows {
        let (a, b) =
            (w["first_tick"].as_u64().expect("first"), w["last_tick"].as_u64().expect("b"));
        assert_eq!((a % 100, b - a), (0, if a == 4000 { 0 } else { 99 }), "{w}");
        let lat: Vec<serde_json::Value> = (a..=b).filter_map(|k| value("latency", k)).collect();
        assert_eq!(w["ticks"].as_u64(), Some(lat.len() as u64), "{w}");
        for hop in hops {
            let max = lat.iter().filter_map(|l| l[hop].as_u64()).max();
            assert_eq!(w[format!("{hop}_max")].as_u64(), max, "{hop} in {w}");
        }
        let err = (a..=b).filter_map(|k| value("tracking", k)?["err_deg"].as_f64());
        let err = err.fold(f64::NAN, f64::max);
        assert_eq!(w["err_deg_max"].as_f64().map(f64::to_bits), Some(err.to_bits()), "{w}");
        let misses = lat.iter().filter_map(|l| l["misses"].as_u64()).max().expect("misses");
        assert_eq!(w["misses"].as_u64(), Some(misses - misses_before), "{w}");
        misses_before = misses;
    }
    assert!(misses_before > 0, "the kill left ticks without a torque");

    // The ticks kept: one a window, and each incident's from a window before to a second
    // after; each kept message is the full file's.
    let in_full =
        |k: u64| incidents.iter().any(|(a, b)| a.saturating_sub(100) <= k && k <= b + 1000);
    let states = |m: &ByTick| -> Vec<u64> {
        m.keys().filter(|(t, _)| t == "/rotorloop/state").map(|(_, k)| *k).collect()
    };
    let want: Vec<u64> = states(&all).into_iter().filter(|k| k % 100 == 0 || in_full(*k)).collect();
    // 41 of the windows; 1 400–2 600 but its 13 hundreds; 3 850–4 000 but 3 900, 4 000.
    assert_eq!(want.len(), 41 + (1201 - 13) + (151 - 2), "the ticks to keep");
    assert_eq!(states(&kept), want, "the ticks kept");
    for (key, data) in &kept {
        assert_eq!(all.get(key), Some(data), "{key:?}: not the full file's message");
    }
    for topic in ["/rotorloop/latency", "/rotorloop/tracking", "/rotorloop/reference"] {
        let n = kept.keys().filter(|(t, _)| t == topic).count();
        assert_eq!(n, want.len(), "{topic}");
    }
    h.assert_no_leftovers();
}
