//! A run's memory does not grow with its length, after the last tick as before it: two
//! lockstep runs, one ten times the other, with flight rings of 512 slots so that both
//! span many segments, and a controller killed and restarted in each (the fault report,
//! an incident and its cost after the run); every `rotorloop` process of each (the launcher, the four roles)
//! and every reader of the finished run (`explain`, `export --mcap`, `sim --replay`)
//! reports its peak resident memory as it ends (`ROTORLOOP_PEAK_RSS`, src/main.rs), and
//! the longer run's peaks are the shorter's within a small constant.
//!
//! Before the readers were bounded (44dbcd5) this failed: at 3 s against 30 s the
//! launcher's peak went from about 23 to 60 MiB, `export --mcap` from 18 to 90 and
//! `sim --replay` from 24 to 110 (each held the whole run).

use std::collections::BTreeMap;
use std::process::Command;
use std::time::Duration;

use crate::common::harness::{Harness, ROTORLOOP, group, wait_output};

/// What a longer run's process may take beyond the shorter's (KiB): allocator noise and
/// the few structures that grow with the number of segments (a path per segment).
const SLACK_KIB: u64 = 8 * 1024;

/// Runs `rotorloop args` with the peak report going to `file`; panics on failure.
fn rotorloop(args: &[&str], file: &std::path::Path) {
    let child = group(&mut Command::new(ROTORLOOP))
        .args(args)
        .env("ROTORLOOP_PEAK_RSS", file)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("spawn rotorloop");
    let out = wait_output(child, Duration::from_secs(600));
    assert!(
        out.status.success(),
        "rotorloop {args:?}: {:?}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A run of `seconds` and its readers: each process's peak (KiB) by what it was (`run`,
/// `role plant`, …, `explain`, `export`, `sim`).
fn peaks(h: &Harness, seconds: u64) -> BTreeMap<String, u64> {
    let out = h.path(&format!("run-{seconds}"));
    let file = h.path(&format!("peaks-{seconds}.tsv"));
    let (out_s, duration) = (out.display().to_string(), seconds.to_string());
    let domain = format!("{}-{seconds}", h.domain);
    rotorloop(
        &[
            "run",
            "--scenario",
            "paper-sinusoid",
            "--mode",
            "lockstep",
            "--duration",
            &duration,
            "--flight-ring-ticks",
            "512",
            "--fault",
            "controller:kill@1:restart@1.5",
            "--domain",
            &domain,
            "--out",
            &out_s,
            "--quiet",
        ],
        &file,
    );
    let segments = std::fs::read_dir(out.join("flight")).expect("flight").count();
    assert!(segments as u64 > seconds, "{segments} files: the run spans many segments");
    rotorloop(&["explain", &out_s], &file);
    rotorloop(&["export", &out_s, "--mcap"], &file);
    let replay = out.join("replay").display().to_string();
    rotorloop(&["sim", "--replay", &out_s, "--out", &replay], &file);
    let verdict = std::fs::read_to_string(out.join("replay/replay.json")).expect("replay.json");
    assert!(verdict.contains("\"identical\": true"), "{verdict}");
    let text = std::fs::read_to_string(&file).expect("peaks");
    let mut peaks = BTreeMap::new();
    for line in text.lines() {
        let (args, kib) = line.split_once('\t').expect("args TAB kib");
        let words: Vec<&str> = args.split(' ').collect();
        let what = match words[0] {
            "role" => format!("role {}", words[1]),
            w => w.to_owned(),
        };
        let kib: u64 = kib.parse().expect("KiB");
        let e = peaks.entry(what).or_insert(0);
        *e = (*e).max(kib);
    }
    peaks
}

#[test]
fn peak_memory_of_every_process_and_reader_does_not_grow_with_the_runs_length() {
    let h = Harness::new("memory");
    let (short, long) = (peaks(&h, 3), peaks(&h, 30));
    let want = ["run", "role plant", "role controller", "role reference", "role monitor"];
    for what in want.into_iter().chain(["explain", "export", "sim"]) {
        let (s, l) = (short.get(what), long.get(what));
        let (Some(s), Some(l)) = (s, l) else {
            panic!("{what}: no peak reported (short {short:?}, long {long:?})");
        };
        assert!(
            *l <= s + SLACK_KIB,
            "{what}: {l} KiB for a 30 s run against {s} KiB for 3 s (every peak: short \
             {short:?}, long {long:?})"
        );
    }
}

/// A run whose output cannot fit is refused before anything starts, naming the space it
/// needs, the free space and `--force`; a run that fits says what it will write.
#[test]
fn a_run_too_large_for_its_disk_is_refused_before_it_starts_and_others_say_their_size() {
    let h = Harness::new("budget");
    let out = h.path("huge");
    let o = h.rotorloop(
        &[
            "run",
            "--scenario",
            "paper-sinusoid",
            "--duration",
            "86400",
            "--rate",
            "100000",
            "--domain",
            &h.domain,
            "--out",
            &out.display().to_string(),
        ],
        Duration::from_secs(60),
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("its output needs about") && err.contains("--force"), "{err}");
    assert!(err.contains("free there"), "{err}");
    // A long run is told what a long run's output would take (from an hour of ticks on,
    // with its `run.mcap`, an overview).
    assert!(err.contains("with --no-csv it would write about"), "{err}");
    assert!(!out.exists(), "nothing of the refused run was made");
    let small = h.path("small");
    let o = h.rotorloop(
        &[
            "run",
            "--scenario",
            "paper-constant",
            "--duration",
            "0.5",
            "--domain",
            &h.domain,
            "--out",
            &small.display().to_string(),
        ],
        Duration::from_secs(120),
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("run: 0.5 s at 1000 Hz writes about"), "{err}");
}

/// A long run's output (`run --no-csv --no-mcap`): no `trace.csv`, `timing.csv` or
/// `run.mcap`, the scheduler samples compressed (`sched.csv.zst`), its segments packed (well under a third of a raw slot's bytes a tick); yet
/// `sim --replay` reads the records directly and finds the run byte for byte, `export
/// --csv` derives the trace the simulator writes, byte for byte (lockstep), and `export
/// --mcap` writes `run.mcap` from the records, the same file as from the derived CSV.
#[test]
fn a_run_without_csv_files_replays_and_derives_them_from_its_packed_records() {
    let h = Harness::new("nocsv");
    let out = h.path("run");
    let out_s = out.display().to_string();
    let said = crate::common::harness::ok(&h.rotorloop(
        &[
            "run",
            "--scenario",
            "paper-sinusoid",
            "--mode",
            "lockstep",
            "--duration",
            "10",
            "--flight-ring-ticks",
            "1024",
            "--no-csv",
            "--no-mcap",
            "--domain",
            &h.domain,
            "--out",
            &out_s,
            "--quiet",
        ],
        Duration::from_secs(300),
    ));
    for f in ["trace.csv", "timing.csv", "run.mcap", "sched.csv"] {
        assert!(!out.join(f).exists(), "{f} written: {said}");
    }
    let s = crate::common::harness::json(&out.join("summary.json"));
    assert_eq!(s["completed"], true, "{s}");
    // The kernel's view compressed, and read by the incidents.
    assert!(out.join("sched.csv.zst").exists(), "{said}");
    assert_eq!(s["incidents"]["kernel_view"], true, "{s}");
    assert_eq!(s["trace_rows"], 10_001, "{s}");
    // The segments: 9 halves of 512 ticks of each stream, packed.
    let (mut bytes, mut ticks) = (0u64, 0u64);
    for e in std::fs::read_dir(out.join("flight")).expect("flight").flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if name.split('.').count() == 3 {
            bytes += e.metadata().expect("segment").len();
            ticks += u64::from(name.starts_with("plant-state.")) * 512;
        }
    }
    assert!(ticks >= 9 * 512, "{ticks} ticks in segments");
    let per_tick = bytes / ticks;
    assert!(per_tick < 1176 / 3, "{per_tick} bytes a tick in the segments (raw: 1176)");
    let replay = out.join("replay");
    let said = crate::common::harness::ok(&h.rotorloop(
        &["sim", "--replay", &out_s, "--out", replay.to_str().expect("utf8")],
        Duration::from_secs(300),
    ));
    let verdict = crate::common::harness::json(&replay.join("replay.json"));
    assert_eq!(verdict["identical"], true, "{said} {verdict}");
    assert_eq!(verdict["rows"], 10_001, "{verdict}");
    let said = crate::common::harness::ok(
        &h.rotorloop(&["export", &out_s, "--mcap"], Duration::from_secs(300)),
    );
    assert!(out.join("run.mcap").exists() && !out.join("trace.csv").exists(), "{said}");
    crate::common::harness::ok(
        &h.rotorloop(&["export", &out_s, "--csv"], Duration::from_secs(300)),
    );
    // The tracking rows taken from the records unformatted are those of the trace's text:
    // the file from the derived `trace.csv` is the same, byte for byte.
    let from_records = std::fs::read(out.join("run.mcap")).expect("run.mcap");
    std::fs::remove_file(out.join("run.mcap")).expect("rm");
    crate::common::harness::ok(
        &h.rotorloop(&["export", &out_s, "--mcap"], Duration::from_secs(300)),
    );
    let from_csv = std::fs::read(out.join("run.mcap")).expect("run.mcap again");
    assert!(from_records == from_csv, "run.mcap from the records differs from the CSV's");
    let derived = std::fs::read(out.join("trace.csv")).expect("derived trace");
    let sim = crate::common::harness::sim_trace(&h, "paper-sinusoid", "10", &[]);
    crate::common::harness::assert_same_trace("derived from the records", &derived, &sim);
    let timing = crate::common::harness::timing_rows(&out);
    assert_eq!(timing.len(), 10_001);
    h.assert_no_leftovers();
}
