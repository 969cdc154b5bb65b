//! A short `rotorloop bench` (two cells, one baseline, a fraction of a second each)
//! produces every output file, well formed. Numbers are not asserted: timing lives in
//! the bench itself, not in tests.

use std::path::PathBuf;
use std::time::Duration;

use crate::common::harness::{Harness, ok};

/// Runs `rotorloop bench ARGS --out DIR` (ARGS split on spaces) to success within
/// `limit_s` seconds; returns DIR.
fn bench(h: &Harness, args: &str, limit_s: u64) -> PathBuf {
    let out = h.path("bench");
    let mut all = vec!["bench"];
    all.extend(args.split_whitespace());
    all.extend(["--out", out.to_str().expect("utf8")]);
    ok(&h.rotorloop(&all, Duration::from_secs(limit_s)));
    out
}

#[test]
fn short_bench_writes_every_output_file() {
    let h = Harness::new("bench");
    let out = bench(
        &h,
        "--rates 500 --wait event --placement same-core,cross-core --baselines iceoryx2 --seconds 0.3",
        180,
    );
    // The machine state of the invocation, and of each loop's run.
    let doctor = crate::common::harness::json(&out.join("doctor.json"));
    assert!(doctor["items"].as_array().is_some_and(|i| !i.is_empty()), "{doctor}");
    let cell = out.join("cells/r500-event-cross-core-none/loop");
    assert!(cell.join("doctor.json").exists() && cell.join("cpus.json").exists());
    let csv = std::fs::read_to_string(out.join("bench.csv")).expect("bench.csv");
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    assert!(header.contains(&"p99_9_us") && header.contains(&"achieved_rate_hz"));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 4, "2 cells × (loop + iceoryx2)");
    for r in &rows {
        assert_eq!(r.len(), header.len());
        assert!(r[14].is_empty(), "nothing skipped here: {r:?}");
        let count: u64 = r[6].parse().expect("count");
        assert!(count > 0, "{r:?}");
        for col in 7..11 {
            let v: f64 = r[col].parse().expect("latency");
            assert!(v > 0.0, "{}: {v}", header[col]);
        }
        // The tracking error is the loop's (final and RMS over the run); a baseline has none.
        for name in ["err_deg_final", "err_deg_rms"] {
            let col = header.iter().position(|h| *h == name).expect(name);
            let v: f64 = r[col].parse().expect(name);
            match r[1] {
                "loop" => assert!(v.is_finite() && v > 0.0, "{name}: {r:?}"),
                _ => assert!(v.is_nan(), "{name} of a baseline: {r:?}"),
            }
        }
    }
    let md = std::fs::read_to_string(out.join("bench.md")).expect("bench.md");
    assert!(md.contains("loop/iceoryx2 p50") && md.contains("Highest rate with zero misses"));
    for cell in ["r500-event-same-core-none", "r500-event-cross-core-none"] {
        for f in ["loop.hgrm", "iceoryx2.hgrm"] {
            let text = std::fs::read_to_string(out.join("cells").join(cell).join(f)).expect(f);
            assert!(text.contains("Total count"), "{cell}/{f}");
        }
    }
    for png in [
        "spectrum_same-core_500hz_event.png",
        "spectrum_cross-core_500hz_event.png",
        "misses_by_rate.png",
    ] {
        let b = std::fs::read(out.join(png)).expect(png);
        assert_eq!(&b[..4], b"\x89PNG", "{png}");
    }
}

/// A combination that cannot work (busy-wait with both ends on one core) is skipped with
/// the reason, not run into the ground.
#[test]
fn impossible_cells_are_skipped_with_a_reason() {
    let h = Harness::new("benchskip");
    let out = bench(
        &h,
        "--rates 500 --wait spin --placement same-core --baselines atomic --seconds 0.2",
        60,
    );
    let csv = std::fs::read_to_string(out.join("bench.csv")).expect("bench.csv");
    let rows: Vec<&str> = csv.lines().skip(1).collect();
    assert_eq!(rows.len(), 2);
    for r in rows {
        assert!(r.contains("busy-wait with both ends on one core"), "{r}");
    }
}

/// The before/after, dedicated and scale options: `loop-before` rows beside the loop,
/// a `-x2` cell with a row per loop (each from its own report), the dedicated cell named
/// and skipped with its reason below 4 cores, and bench.md's breakdown, before/after and
/// scale sections filled from what was measured.
#[test]
fn before_after_dedicated_and_scale_cells_are_written_or_skipped_with_a_reason() {
    let h = Harness::new("benchscale");
    let out = bench(
        &h,
        "--rates 500 --wait event --placement unpinned,dedicated --baselines iceoryx2 --seconds 0.3 --before-after --loops 2",
        240,
    );
    let csv = std::fs::read_to_string(out.join("bench.csv")).expect("bench.csv");
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    let row = |cell: &str, kind: &str| {
        rows.iter()
            .find(|r| r[0] == cell && r[1] == kind)
            .unwrap_or_else(|| panic!("{cell} {kind}: {csv}"))
    };
    for (cell, kind) in [
        ("r500-event-unpinned-none", "loop"),
        ("r500-event-unpinned-none", "loop-before"),
        ("r500-event-unpinned-none", "iceoryx2"),
        ("r500-event-unpinned-none-x2", "loop-1"),
        ("r500-event-unpinned-none-x2", "loop-2"),
    ] {
        let r = row(cell, kind);
        assert!(r[14].is_empty(), "{cell} {kind} skipped: {r:?}");
        assert!(r[6].parse::<u64>().expect("count") > 0, "{r:?}");
    }
    for kind in ["loop-1", "loop-2"] {
        let summary = out.join("cells/r500-event-unpinned-none-x2").join(kind).join("summary.json");
        assert!(summary.exists(), "each loop of a scale cell has its own report");
    }
    // The dedicated preset spins: one cell whatever --wait lists.
    let dedicated: Vec<_> =
        rows.iter().filter(|r| r[0].starts_with("r500-spin-dedicated")).collect();
    assert!(!dedicated.is_empty(), "{csv}");
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    for r in &dedicated {
        if cores < 4 {
            assert!(r[14].contains("dedicated needs 4 cores"), "{r:?}");
        } else {
            assert!(r[14].is_empty(), "{r:?}");
        }
    }
    let md = std::fs::read_to_string(out.join("bench.md")).expect("bench.md");
    for section in [
        "## Where the microseconds go",
        "## Before and after (same invocation)",
        "## Scale: r500-event-unpinned-none",
        "Largest number of loops",
    ] {
        assert!(md.contains(section), "bench.md lacks {section}:\n{md}");
    }
    assert!(md.contains("| r500-event-unpinned-none | loop-before |"), "{md}");
}

/// `rotorloop run --preset dedicated` says what it needs on a machine that lacks it, and
/// refuses an unknown preset by name.
#[test]
fn run_presets_are_checked() {
    let h = Harness::new("preset");
    let out = h.path("run");
    let out = out.to_str().expect("utf8");
    let with_preset = |preset: &str| {
        let args = ["run", "--scenario", "paper-zero", "--duration", "0.1", "--out", out];
        let mut args = args.to_vec();
        args.extend(["--preset", preset]);
        h.rotorloop(&args, Duration::from_secs(60))
    };
    let unknown = with_preset("fast");
    assert_eq!(unknown.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&unknown.stderr);
    assert!(stderr.contains("--preset `fast` is not allowed: dedicated"), "{stderr}");
    if std::thread::available_parallelism().map_or(1, |n| n.get()) < 4 {
        let small = with_preset("dedicated");
        assert_eq!(small.status.code(), Some(2));
        let stderr = String::from_utf8_lossy(&small.stderr);
        assert!(stderr.contains("dedicated needs 4 cores"), "{stderr}");
    }
}

/// `--placement cross-host` measures the split loop and the bare iceoryx2 round trip
/// through two link gateways, skips what cannot cross hosts with the reason, and sets
/// each beside the same measurement on one host in "What the link costs".
#[test]
fn cross_host_cells_are_measured_through_the_link_beside_one_host() {
    let h = Harness::new("bench-xh");
    let out = bench(
        &h,
        "--rates 200 --wait event --placement unpinned,cross-host --baselines iceoryx2,uds --seconds 0.5",
        300,
    );
    let csv = std::fs::read_to_string(out.join("bench.csv")).expect("bench.csv");
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    let row = |placement: &str, kind: &str| {
        rows.iter()
            .find(|r| r[4] == placement && r[1] == kind)
            .unwrap_or_else(|| panic!("no {placement} {kind} row in {csv}"))
    };
    for kind in ["loop", "iceoryx2"] {
        let r = row("cross-host", kind);
        assert!(r[14].is_empty(), "measured: {r:?}");
        assert!(r[6].parse::<u64>().expect("count") > 0, "{r:?}");
        assert!(r[7].parse::<f64>().expect("p50") > 0.0, "{r:?}");
    }
    assert!(row("cross-host", "loop")[15].parse::<f64>().expect("error").is_finite());
    assert!(row("cross-host", "uds")[14].contains("do not cross hosts"));
    let md = std::fs::read_to_string(out.join("bench.md")).expect("bench.md");
    let costs = md.split("What the link costs").nth(1).expect("the link-cost section");
    assert!(
        costs.contains("| 200 | event | loop |") && costs.contains("| 200 | event | iceoryx2 |")
    );
    let cell = out.join("cells").join("r200-event-cross-host-none");
    for f in ["loop.hgrm", "iceoryx2.hgrm", "link-a.log", "link-b.log"] {
        assert!(cell.join(f).is_file(), "{f}");
    }
    // The bench's own domains (`bl<pid>-…`, `bb<pid>-…`) on hosts a and b are gone; no
    // other test of this file uses hosts.
    let left: Vec<String> = std::fs::read_dir("/dev/shm")
        .expect("/dev/shm")
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("rh_a_b") || n.starts_with("rh_b_b"))
        .collect();
    assert!(left.is_empty(), "left in /dev/shm: {left:?}");
}

/// `--baselines timer`: a bare thread sleeping to the plant's grid on the plant's core is
/// measured in the same invocation (one wake-up per tick of the cell), and `bench.md`
/// puts the plant's tick lateness beside it with the ratios. `--cpu-dma-latency 0` is
/// held for the invocation where the machine lets it (root) and `bench.md` says which.
#[test]
fn the_timer_baseline_is_measured_beside_the_plants_tick() {
    let h = Harness::new("benchtimer");
    let out = bench(
        &h,
        "--rates 500 --wait event --placement cross-core --baselines timer --seconds 0.5 \
         --cpu-dma-latency 0",
        180,
    );
    // The machine state of the invocation, and of each loop's run.
    let doctor = crate::common::harness::json(&out.join("doctor.json"));
    assert!(doctor["items"].as_array().is_some_and(|i| !i.is_empty()), "{doctor}");
    let cell = out.join("cells/r500-event-cross-core-none/loop");
    assert!(cell.join("doctor.json").exists() && cell.join("cpus.json").exists());
    let csv = std::fs::read_to_string(out.join("bench.csv")).expect("bench.csv");
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let col = |n: &str| header.iter().position(|h| *h == n).expect(n);
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    let kinds: Vec<&str> = rows.iter().map(|r| r[1]).collect();
    assert_eq!(kinds, ["loop", "timer"]);
    let num = |r: &[&str], n: &str| r[col(n)].parse::<f64>().expect(n);
    let (plant, timer) = (&rows[0], &rows[1]);
    // Ticks 0 to 250 of a 0.5 s grid at 500 Hz: one wake-up each.
    assert_eq!(timer[col("count")], "251", "{timer:?}");
    for n in ["p50_us", "p99_us", "p99_9_us"] {
        assert!(num(timer, n) > 0.0, "{n}: {timer:?}");
    }
    for n in ["tick_lateness_p50_us", "tick_lateness_p99_us", "tick_lateness_p99_9_us"] {
        assert!(num(plant, n) > 0.0, "{n}: {plant:?}");
    }
    let md = std::fs::read_to_string(out.join("bench.md")).expect("bench.md");
    // The idle-state request, held for the invocation where the device lets us (root).
    let writable = std::fs::OpenOptions::new().write(true).open("/dev/cpu_dma_latency").is_ok();
    let held = "`/dev/cpu_dma_latency` held at 0 µs for the invocation";
    assert_eq!(md.contains(held), writable, "{}", md.lines().nth(2).unwrap_or_default());
    let section = md.split("against the timer baseline").nth(1).expect("the timer section");
    let row = section
        .lines()
        .find(|l| l.starts_with("| r500-event-cross-core-none | loop |"))
        .expect("the loop beside its timer");
    let ratio: f64 = row.split('|').nth(5).expect("ratio p50").trim().parse().expect("a ratio");
    assert!(ratio > 0.0 && ratio.is_finite(), "{row}");
    let hgrm = std::fs::read_to_string(out.join("cells/r500-event-cross-core-none/timer.hgrm"));
    assert!(hgrm.expect("timer.hgrm").contains("Total count"));
}

/// The kind of each row of `out/bench.csv`, in order.
fn kinds(out: &std::path::Path) -> Vec<String> {
    let csv = std::fs::read_to_string(out.join("bench.csv")).expect("bench.csv");
    csv.lines().skip(1).map(|l| l.split(',').nth(1).unwrap_or("").to_owned()).collect()
}

/// `--before-after foxglove`: the loop alone and with the live Foxglove server and a viewer
/// subscribed to every topic, alternating; the viewer received the loop's messages,
/// `before-after.json` has the pairs' ratios with their interval and verdict, and
/// `bench.md` compares the two.
#[test]
fn before_after_foxglove_measures_the_loop_with_a_viewer_attached() {
    let h = Harness::new("benchfx");
    let out = bench(
        &h,
        "--rates 500 --wait event --placement cross-core --baselines iceoryx2 --seconds 1 \
         --before-after foxglove --pairs 2",
        180,
    );
    let kinds = kinds(&out);
    assert_eq!(kinds, ["loop", "loop-foxglove", "iceoryx2"]);
    let cell = out.join("cells/r500-event-cross-core-none");
    for pair in [cell.join("loop-foxglove"), cell.join("pair1/loop-foxglove")] {
        let v = crate::common::harness::json(&pair.join("viewer.json"));
        // 1 s at 500 Hz: states, torques, references, transforms, latency, tracking.
        assert!(v["messages"].as_u64().is_some_and(|n| n > 500), "{}: {v}", pair.display());
        assert!(pair.join("foxglove.addr").exists());
    }
    assert!(cell.join("pair1/loop/summary.json").exists(), "the plain loop measured twice");
    // The pairs' after / before ratios: with two pairs the interval is their range, at
    // level 1 − 2·(1/2)² = 0.5, and the verdict says where it lies against 1.
    let ba = crate::common::harness::json(&cell.join("before-after.json"));
    assert_eq!(ba["pairs"], 2, "{ba}");
    for q in ["p50", "p99"] {
        let r = &ba[format!("after_over_before_{q}")];
        let ratios: Vec<f64> = r["ratios"]
            .as_array()
            .unwrap_or_else(|| panic!("{q}: {ba}"))
            .iter()
            .map(|x| x.as_f64().expect("a ratio"))
            .collect();
        assert!(ratios.len() == 2 && ratios.iter().all(|x| *x > 0.0), "{q}: {r}");
        let (lo, hi) = (ratios[0].min(ratios[1]), ratios[0].max(ratios[1]));
        let f = |k: &str| r[k].as_f64().unwrap_or(f64::NAN);
        assert_eq!((f("ci_low"), f("ci_high"), f("level")), (lo, hi, 0.5), "{q}: {r}");
        assert!((f("median") - (lo + hi) / 2.0).abs() <= 1e-12 * hi, "{q}: {r}");
        let verdict = match (hi < 1.0, lo > 1.0) {
            (true, _) => "faster",
            (_, true) => "slower",
            _ => "indistinguishable",
        };
        assert_eq!(r["verdict"], verdict, "{q}: {r}");
    }
    // Every pair's misses, as each run's summary has them, and their sums.
    let misses = |run: &str| {
        let s = crate::common::harness::json(&cell.join(run).join("summary.json"));
        s["misses"].as_u64().expect("misses")
    };
    let m = &ba["misses"];
    let (before, after) = (
        [misses("loop"), misses("pair1/loop")],
        [misses("loop-foxglove"), misses("pair1/loop-foxglove")],
    );
    assert_eq!((m["before"].clone(), m["after"].clone()), (before.into(), after.into()), "{m}");
    assert_eq!(m["before_total"], before.iter().sum::<u64>(), "{m}");
    assert_eq!(m["after_total"], after.iter().sum::<u64>(), "{m}");
    let more = before.iter().zip(&after).filter(|(b, a)| a > b).count();
    assert_eq!(m["pairs_after_more"], more, "{m}");
    let md = std::fs::read_to_string(out.join("bench.md")).expect("bench.md");
    assert!(md.contains(": misses over 2 pair(s): before "), "{md}");
    assert!(md.contains("with the live Foxglove server"), "{md}");
    assert!(md.contains("| r500-event-cross-core-none |"), "{md}");
}

/// `--before-after hot-path`: the loop with its hot path as it was before its overhead was
/// cut (`loop-plain`) and as it is, in the same invocation; both stamp the plant's wake-up
/// → publish (`state_prep`) on every answered tick, and bench.md's breakdown shows both.
#[test]
fn before_after_hot_path_measures_the_plain_and_the_cut_hot_path() {
    let h = Harness::new("benchhp");
    let out = bench(
        &h,
        "--rates 500 --wait event --placement cross-core --baselines iceoryx2 --seconds 1 \
         --before-after hot-path",
        180,
    );
    let kinds = kinds(&out);
    assert_eq!(kinds, ["loop", "loop-plain", "iceoryx2"]);
    let cell = out.join("cells/r500-event-cross-core-none");
    for kind in ["loop", "loop-plain"] {
        let s = crate::common::harness::json(&cell.join(kind).join("summary.json"));
        let prep =
            s["stages"].as_array().and_then(|st| st.iter().find(|x| x["stage"] == "state_prep"));
        let prep = prep.unwrap_or_else(|| panic!("{kind}: no state_prep stage: {s}"));
        assert!(prep["count"].as_u64().is_some_and(|n| n > 250), "{kind}: {prep}");
    }
    let md = std::fs::read_to_string(out.join("bench.md")).expect("bench.md");
    assert!(md.contains("as it was before its overhead was cut"), "{md}");
    let breakdown = md.split("Where the microseconds go").nth(1).expect("the breakdown");
    assert!(breakdown.contains("| r500-event-cross-core-none | loop-plain |"), "{breakdown}");
    assert!(breakdown.contains("(plant wake → publish)"), "{breakdown}");
}

/// `--controllers mrp-pid,python`: the same cell with the second law and with the Python
/// example, beside the built-in law and the bare baseline; bench.md shows each one's
/// compute and law stage. Without `python3` the Python row is skipped with its reason.
#[test]
fn the_controller_axis_measures_each_law_in_the_same_invocation() {
    let h = Harness::new("benchctl");
    let py = crate::controller_cmd::python();
    let python = py.as_ref().map_or("python3".to_owned(), |p| p.display().to_string());
    let args = format!(
        "--rates 500 --wait event --placement cross-core --baselines iceoryx2 --seconds 1 \
         --controllers mrp-pid,python --python {python}"
    );
    let out = bench(&h, &args, 240);
    let csv = std::fs::read_to_string(out.join("bench.csv")).expect("bench.csv");
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    let kinds: Vec<&str> = rows.iter().map(|r| r[1]).collect();
    assert_eq!(kinds, ["loop", "loop-mrp-pid", "loop-python", "iceoryx2"]);
    let cell = out.join("cells/r500-event-cross-core-none");
    let law = |kind: &str| crate::common::harness::json(&cell.join(kind).join("summary.json"));
    assert_eq!(law("loop-mrp-pid")["completed"], true);
    let scenario = std::fs::read_to_string(cell.join("loop-mrp-pid.scenario.toml")).expect("toml");
    assert!(scenario.contains("law = \"mrp-pid\""), "{scenario}");
    let md = std::fs::read_to_string(out.join("bench.md")).expect("bench.md");
    let section = md.split("What each controller costs the loop").nth(1).expect("the section");
    assert!(section.contains("| loop-mrp-pid | "), "{section}");
    match py {
        Some(_) => {
            assert_eq!(law("loop-python")["completed"], true);
            assert!(rows[2][14].is_empty(), "python skipped: {}", rows[2][14]);
        }
        None => assert!(rows[2][14].contains("cannot import"), "{:?}", rows[2]),
    }
}

/// Two runs started at once with disjoint `--cpus` never share a core: every role's
/// affinity, as the kernel gave it (`cpus.json`, read from `/proc/PID/status`
/// `Cpus_allowed_list`), is inside its own run's set, and a `--pin` outside the run's set
/// or a `--cpus` outside the process's CPU set is refused naming the flag.
#[test]
fn runs_with_disjoint_cpus_get_disjoint_affinities() {
    use crate::common::harness::ROTORLOOP;
    use rotorloop::cpus::{allowed_now, parse_list};
    let mut h = Harness::new("cpus");
    let allowed = allowed_now();
    assert!(allowed.len() >= 2, "this test needs 2 CPUs in the process's set: {allowed:?}");
    let (a, b) = (allowed[0].to_string(), allowed[1].to_string());
    let start = |h: &mut Harness, cpu: &str, pin: Option<&str>| {
        let out = h.path(&format!("run-{cpu}"));
        let mut args: Vec<String> = ["run", "--scenario", "paper-zero", "--mode", "realtime"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        args.extend(["--duration", "1", "--quiet", "--no-mcap", "--cpus", cpu].map(String::from));
        args.extend(["--domain".into(), format!("{}-{cpu}", h.domain)]);
        args.extend(["--out".into(), out.display().to_string()]);
        if let Some(p) = pin {
            args.extend(["--pin".into(), p.to_owned()]);
        }
        h.spawn(ROTORLOOP, &args);
        out
    };
    let out_a = start(&mut h, &a, None);
    let out_b = start(&mut h, &b, Some(&format!("plant={b},controller={b}")));
    let statuses = h.wait_all(Duration::from_secs(120));
    assert!(statuses.iter().all(|s| s.success()), "{statuses:?}");
    for (out, mine) in [(&out_a, &a), (&out_b, &b)] {
        let record = crate::common::harness::json(&out.join("cpus.json"));
        assert_eq!(record["cpus"].as_str(), Some(mine.as_str()), "{record}");
        let roles = record["roles"].as_object().expect("roles");
        assert_eq!(roles.len(), 4, "{record}");
        for (role, r) in roles {
            let list = r["cpus_allowed_list"].as_str().unwrap_or_else(|| panic!("{role}: {r}"));
            let cpus = parse_list(list, "Cpus_allowed_list").expect("a CPU list");
            assert_eq!(cpus, vec![mine.parse::<usize>().expect("a CPU")], "{role} of {mine}");
        }
    }
    let outside = h.path("outside");
    let refused = |extra: &[&str]| {
        let mut args =
            vec!["run", "--scenario", "paper-zero", "--duration", "0.01", "--mode", "lockstep"];
        args.extend(["--out", outside.to_str().expect("utf-8")]);
        args.extend(extra);
        let o = h.rotorloop(&args, Duration::from_secs(60));
        assert_eq!(o.status.code(), Some(2), "{extra:?}");
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    let e = refused(&["--cpus", &a, "--pin", &format!("plant={b}")]);
    assert!(
        e.contains(&format!("--pin plant=`{b}` is not allowed: a CPU of the run's set")),
        "{e}"
    );
    let e = refused(&["--cpus", "4095"]);
    assert!(e.contains("--cpus `4095` is not allowed"), "{e}");
}

/// `--repeat 3`: the loop and each baseline measured three times in turn (a row each,
/// `repeat` 0 to 2); the loop rows carry each ratio's median and interval, the median
/// inside its interval, in columns that say what they are; bench.md shows them with
/// their level and verdicts. `rotorloop compare` of the bench with itself finds every
/// figure indistinguishable, and of two runs says there is no interval.
#[test]
fn repeated_cells_give_intervals_and_compare_reads_them() {
    let h = Harness::new("benchrepeat");
    let out = bench(
        &h,
        "--rates 500 --wait event --placement cross-core --baselines iceoryx2,timer --seconds 0.3 --repeat 3",
        300,
    );
    let csv = std::fs::read_to_string(out.join("bench.csv")).expect("bench.csv");
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let col =
        |name: &str| header.iter().position(|c| *c == name).unwrap_or_else(|| panic!("{name}"));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 9, "3 × (loop, iceoryx2, timer): {csv}");
    let loops: Vec<&Vec<&str>> = rows.iter().filter(|r| r[1] == "loop").collect();
    let reps: Vec<&str> = loops.iter().map(|r| r[col("repeat")]).collect();
    assert_eq!(reps, ["0", "1", "2"]);
    for r in &loops {
        for name in
            ["loop_over_iceoryx2_p50", "loop_over_iceoryx2_p99", "plant_over_timer_lateness_p99"]
        {
            let v = |s: &str| r[col(&format!("{name}_{s}"))].parse::<f64>().expect(name);
            assert!(v("ci_low") <= v("median") && v("median") <= v("ci_high"), "{name}: {r:?}");
            let verdict = r[col(&format!("{name}_verdict"))];
            assert!(["faster", "slower", "indistinguishable"].contains(&verdict), "{verdict}");
        }
        assert_eq!(r[col("repetitions")], "3");
        assert_eq!(r[col("ci_level")], "0.7500", "the range of 3 is a 75 % interval");
    }
    let md = std::fs::read_to_string(out.join("bench.md")).expect("bench.md");
    assert!(md.contains("## Repetitions"), "{md}");
    assert!(md.contains("| r500-event-cross-core-none | loop_over_iceoryx2_p50 |"), "{md}");
    let twice = h.rotorloop(
        &["compare", out.to_str().expect("utf-8"), out.to_str().expect("utf-8")],
        Duration::from_secs(60),
    );
    let text = ok(&twice);
    assert!(text.contains("| r500-event-cross-core-none | loop | p50 µs |"), "{text}");
    assert!(text.contains("indistinguishable (intervals overlap)"), "{text}");
    assert!(!text.contains("intervals apart"), "a bench against itself: {text}");
    let cell = out.join("cells/r500-event-cross-core-none");
    let (a, b) = (cell.join("loop"), cell.join("rep1/loop"));
    let runs = ok(&h.rotorloop(
        &["compare", a.to_str().expect("utf-8"), b.to_str().expect("utf-8")],
        Duration::from_secs(60),
    ));
    assert!(runs.contains("One run on each side: no interval"), "{runs}");
    let mixed = h.rotorloop(
        &["compare", a.to_str().expect("utf-8"), out.to_str().expect("utf-8")],
        Duration::from_secs(60),
    );
    assert_eq!(mixed.status.code(), Some(2));
}

/// `bench --smt` takes `idle` or `use` and refuses anything else naming the flag and both
/// values, before anything is measured.
#[test]
fn bench_smt_choice_is_checked() {
    let h = Harness::new("benchsmt");
    let out = h.path("bench");
    let o = h.rotorloop(
        &["bench", "--smt", "both", "--out", out.to_str().expect("utf-8")],
        Duration::from_secs(60),
    );
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--smt") && err.contains("idle, use"), "{err}");
    assert!(!out.join("bench.csv").exists());
}
