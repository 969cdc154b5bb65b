//! Property tests of everything a user types: seeded random mutations of the shipped
//! scenario files, and random argument values for `sim` and `run`. Every case ends in a
//! valid run or a clear error with exit code 2; never a panic, never an output directory
//! that looks like a finished run (one with `summary.json`) after an error.

use std::path::Path;
use std::time::Duration;

use crate::common::harness::Harness;
use crate::common::rng;
use rand::Rng;
use rand::seq::IndexedRandom;
use rotorloop::sim::closed_loop::ClosedLoop;
use rotorloop_common::scenario::BUILTIN;
use rotorloop_common::scenario::{Actuation, Scenario, ScenarioError};

/// Values that replace a number in a scenario file: valid, out of range, wrong type, and
/// (issue 45) an extra item that makes its array oversize, or a table in an array.
const VALUES: [&str; 27] = [
    "1.0, 9.0",
    "{ x = 1 }",
    "2.0, \"ignored\"",
    "nan",
    "inf",
    "-inf",
    "-1.0",
    "0.0",
    "-0.0",
    "1e308",
    "-1e308",
    "1e-320",
    "1e7",
    "\"x\"",
    "[]",
    "true",
    "[1.0, 2.0]",
    "{}",
    "3",
    "0.5",
    "2.0",
    "100.0",
    "1e-9",
    "7",
    "-3.5",
    "0.999",
    "[[1.0]]",
];

fn mutate(rng: &mut impl Rng, text: &str) -> String {
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    for _ in 0..rng.random_range(1..=3) {
        let n = lines.len().max(1);
        let i = rng.random_range(0..n);
        match rng.random_range(0..9) {
            0..=2 => {
                // Replace one number on a random line.
                let Some(line) = lines.get_mut(i) else { continue };
                let spans: Vec<(usize, usize)> = number_spans(line);
                if let Some(&(a, b)) = spans.choose(rng) {
                    let v = VALUES.choose(rng).expect("values");
                    line.replace_range(a..b, v);
                }
            }
            3 => {
                if !lines.is_empty() {
                    lines.remove(i.min(lines.len() - 1));
                }
            }
            4 => {
                let l = lines.get(i).cloned().unwrap_or_default();
                lines.insert(i, l);
            }
            5 => lines.insert(i, "bogus_key = 1".into()),
            6 => {
                let j = rng.random_range(0..n);
                if i < lines.len() && j < lines.len() {
                    lines.swap(i, j);
                }
            }
            7 => {
                // Truncate the file at a random byte (on a char boundary).
                let joined = lines.join("\n");
                let mut cut = rng.random_range(0..=joined.len());
                while !joined.is_char_boundary(cut) {
                    cut -= 1;
                }
                lines = joined[..cut].lines().map(str::to_owned).collect();
            }
            _ => {
                // A random printable byte somewhere.
                let Some(line) = lines.get_mut(i) else { continue };
                if line.is_ascii() && !line.is_empty() {
                    let at = rng.random_range(0..line.len());
                    let c = rng.random_range(0x20u8..0x7f) as char;
                    line.replace_range(at..=at, &c.to_string());
                }
            }
        }
    }
    lines.join("\n")
}

/// Byte ranges of the numbers in a line (outside comments).
fn number_spans(line: &str) -> Vec<(usize, usize)> {
    let code = line.split('#').next().unwrap_or("");
    let b = code.as_bytes();
    let mut spans = Vec::new();
    let mut i = 0;
    while i < b.len() {
        let starts =
            b[i].is_ascii_digit() || (b[i] == b'-' && b.get(i + 1).is_some_and(u8::is_ascii_digit));
        if starts && (i == 0 || !b[i - 1].is_ascii_alphanumeric() && b[i - 1] != b'_') {
            let a = i;
            i += 1;
            while i < b.len() && (b[i].is_ascii_digit() || b"+-.eE".contains(&b[i])) {
                i += 1;
            }
            spans.push((a, i));
        } else {
            i += 1;
        }
    }
    spans
}

/// 3000 mutated scenario files: each is a valid scenario whose loop runs without a panic,
/// or an error that names what is wrong. Both outcomes occur often enough to matter.
#[test]
fn mutated_scenario_files_are_valid_runs_or_named_errors_never_panics() {
    let (valid, invalid) = mutated_scenario_files(0x5eed_f00d, 3000);
    assert!(valid > 150 && invalid > 1500, "coverage: {valid} valid, {invalid} invalid");
}

/// The long run of [`mutated_scenario_files_are_valid_runs_or_named_errors_never_panics`]:
/// 100 000 files from another seed, `ROTORLOOP_FUZZ_SEED` if set (docs/tests.md).
#[test]
#[ignore = "the long run of the scenario fuzzer; docs/tests.md"]
fn many_mutated_scenario_files_are_valid_runs_or_named_errors_never_panics() {
    let seed = std::env::var("ROTORLOOP_FUZZ_SEED").ok().and_then(|s| s.parse().ok());
    let (valid, invalid) = mutated_scenario_files(seed.unwrap_or(0x10_0000), 100_000);
    assert!(valid > 5_000 && invalid > 50_000, "coverage: {valid} valid, {invalid} invalid");
}

/// `n` mutated scenario files from `seed`, each parsed and (when valid) run 200 ticks:
/// how many were valid and how many refused, naming what is wrong.
fn mutated_scenario_files(seed: u64, n: usize) -> (usize, usize) {
    let mut r = rng(seed);
    let (mut valid, mut invalid) = (0, 0);
    for case in 0..n {
        let (_, base) = BUILTIN.choose(&mut r).expect("builtin");
        let text = mutate(&mut r, base);
        let parsed = std::panic::catch_unwind(|| Scenario::from_toml(&text, "fuzz"));
        let parsed = parsed.unwrap_or_else(|_| panic!("case {case}: panic on\n{text}"));
        match parsed {
            Ok(s) => {
                // The law checks its own parameters (`[controller.law_params]`): a value it
                // refuses is a named error too, never a panic.
                let ran = std::panic::catch_unwind(|| {
                    let mut lp = ClosedLoop::new(&s, Actuation::Internal, None)?;
                    for _ in 0..s.ticks().min(200) {
                        lp.tick();
                    }
                    Ok::<(), rotorloop_controller::law::UnknownLaw>(())
                });
                match ran {
                    Ok(Ok(())) => valid += 1,
                    Ok(Err(e)) => {
                        invalid += 1;
                        let msg = e.to_string();
                        assert!(msg.starts_with("controller.law"), "case {case}: {msg}");
                    }
                    Err(_) => panic!("case {case}: the loop panicked on\n{text}"),
                }
            }
            Err(e) => {
                invalid += 1;
                let msg = e.to_string();
                assert!(!msg.is_empty(), "case {case}: empty message");
                if let ScenarioError::Invalid { field, allowed, .. } = &e {
                    assert!(!field.is_empty() && !allowed.is_empty(), "case {case}: {msg}");
                    assert!(msg.contains("is not allowed"), "case {case}: {msg}");
                }
                assert!(msg.len() < 2000, "case {case}: {} bytes: {msg}", msg.len());
            }
        }
    }
    (valid, invalid)
}

fn assert_outcome(case: usize, out: &std::process::Output, dir: &Path, what: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    match out.status.code() {
        Some(0) => {
            assert!(dir.join("summary.json").exists(), "case {case}: {what}: ok, no summary")
        }
        Some(2) => {
            assert!(err.contains("error"), "case {case}: {what}: exit 2 without an error: {err}");
            assert!(
                !dir.join("summary.json").exists(),
                "case {case}: {what}: failed but left a summary.json"
            );
        }
        other => panic!("case {case}: {what}: exit {other:?}, want 0 or 2:\n{err}"),
    }
}

/// Random argument values for `rotorloop sim` with mutated scenario files: exit 0 with a
/// complete report, or exit 2 with an error and no summary.json.
#[test]
fn random_sim_arguments_give_a_report_or_exit_2() {
    let h = Harness::new("fuzz-sim");
    let mut r = rng(0xc11);
    // Each flag's value is drawn from its valid pool with probability 0.7.
    let flags: [(&str, &[&str], &[&str]); 5] = [
        ("--duration", &["0.05", "0.2", "0.1"], &["-1", "0", "nan", "abc", "1e9", "inf", ""]),
        ("--rate", &["1000", "250", "100000"], &["0", "-5", "1e6", "nan", "x"]),
        ("--actuation", &["internal", "external"], &["gas", "", "INTERNAL"]),
        ("--open-loop", &["0,0,0", "0.1,0.2,0.3"], &["1,2", "a,b,c", "nan,0,0", "1e7,0,0"]),
        ("--trace-every", &["1", "10"], &["0", "-3", "x"]),
    ];
    let (mut zero, mut two) = (0, 0);
    for case in 0..60 {
        let scenario = h.path(&format!("s{case}.toml"));
        let (_, base) = BUILTIN.choose(&mut r).expect("builtin");
        let text = if r.random_bool(0.6) { base.to_string() } else { mutate(&mut r, base) };
        std::fs::write(&scenario, text).expect("write scenario");
        let dir = h.path(&format!("out{case}"));
        let mut args: Vec<String> = vec!["sim".into(), "--no-figures".into()];
        args.extend(["--scenario".into(), scenario.to_string_lossy().into_owned()]);
        args.extend(["--out".into(), dir.to_string_lossy().into_owned()]);
        for (i, (flag, valid, invalid)) in flags.iter().enumerate() {
            // Always a duration: a valid file may ask for a day of simulated time.
            if i == 0 || r.random_bool(0.3) {
                let pool = if r.random_bool(0.7) { valid } else { invalid };
                args.extend([flag.to_string(), pool.choose(&mut r).expect("present").to_string()]);
            }
        }
        let argv: Vec<&str> = args.iter().map(String::as_str).collect();
        let out = h.rotorloop(&argv, Duration::from_secs(120));
        assert_outcome(case, &out, &dir, &args.join(" "));
        match out.status.code() {
            Some(0) => zero += 1,
            _ => two += 1,
        }
    }
    assert!(zero >= 5 && two >= 20, "coverage: {zero} runs, {two} errors");
}

/// One bad value at a time for `rotorloop run`: exit 2 with an error naming the flag,
/// before any process starts (no summary.json, nothing left in shared memory).
#[test]
fn bad_run_arguments_exit_2_before_starting_anything() {
    let h = Harness::new("fuzz-run");
    let bad: [(&str, &[&str]); 11] = [
        ("--pin", &["plant", "plant=99", "nobody=0", "plant=-1", "plant=0,controller=x"]),
        ("--cpus", &["", "x", "3-1", "0,,1", "4096"]),
        (
            "--fault",
            &["plant", "plant:kill", "x:kill@1", "plant:kill@-1", "plant:kill@2:restart@1"],
        ),
        ("--corrupt", &["plant", "plant:nan", "controller:skew@3", "monitor:nan@1", "plant:zap@1"]),
        ("--domain", &["", "a/b", "this-domain-name-is-far-too-long-for-a-socket", "spa ce"]),
        ("--rate", &["0", "-1", "nan", "1e9"]),
        ("--duration", &["0", "-2", "inf"]),
        ("--mode", &["fast", ""]),
        ("--wait", &["busy", "SPIN"]),
        ("--rt-priority", &["0", "100", "x"]),
        ("--hold-ticks", &["-1", "x"]),
    ];
    let mut case = 0;
    for (flag, values) in bad {
        for v in values {
            let dir = h.path(&format!("run{case}"));
            let domain = format!("{}-{case}", h.domain);
            let mut args = vec!["run", "--scenario", "paper-zero", "--quiet"];
            args.extend(["--out", dir.to_str().expect("present")]);
            for (f, default) in
                [("--mode", "lockstep"), ("--duration", "0.01"), ("--domain", &domain)]
            {
                if f != flag {
                    args.extend([f, default]);
                }
            }
            args.extend([flag, v]);
            let out = h.rotorloop(&args, Duration::from_secs(60));
            let err = String::from_utf8_lossy(&out.stderr);
            assert_eq!(out.status.code(), Some(2), "{flag} {v:?}: {err}");
            let flag_named = err.contains(flag) || err.contains(&flag[2..]);
            assert!(flag_named, "{flag} {v:?}: the error should name it: {err}");
            assert!(!dir.join("summary.json").exists(), "{flag} {v:?}: summary left");
            case += 1;
        }
    }
}

/// Where a damaged value goes: a key path of a scenario file (`plant.rotor_inertia`).
fn set(table: &mut toml::Table, path: &str, value: toml::Value) {
    let (head, key) = path.rsplit_once('.').unwrap_or(("", path));
    let mut t = table;
    for part in head.split('.').filter(|p| !p.is_empty()) {
        t = t.get_mut(part).and_then(toml::Value::as_table_mut).expect("a section");
    }
    t.insert(key.to_owned(), value);
}

/// Every 3-vector, 3×3 matrix and section of a parsed scenario file, by key path.
fn shaped_keys(t: &toml::Table, path: &str, out: &mut Vec<(String, toml::Value)>) {
    for (k, v) in t {
        let p = if path.is_empty() { k.clone() } else { format!("{path}.{k}") };
        match v {
            toml::Value::Table(inner) if k != "law_params" => {
                out.push((p.clone(), v.clone()));
                shaped_keys(inner, &p, out);
            }
            toml::Value::Array(a) if a.len() == 3 => out.push((p, v.clone())),
            _ => {}
        }
    }
}

/// The damage done to a 3-vector, a 3×3 matrix or a section: oversize (with and without
/// items of the wrong type), undersize, a mistyped item, a table written as an array.
fn damaged(v: &toml::Value, long: usize) -> Vec<toml::Value> {
    use toml::Value::{Array, Float, Integer, String as Text, Table};
    let mut out = Vec::new();
    match v {
        Array(items) => {
            let matrix = items.iter().all(toml::Value::is_array);
            let item = |i: usize| items[i].clone();
            let mut four = items.clone();
            four.push(if matrix { item(0) } else { Float(1.0) });
            out.push(Array(four));
            let mut tail = items.clone();
            tail.extend([
                Text("ignored".into()),
                Table(toml::Table::from_iter([("x".into(), Integer(1))])),
            ]);
            out.push(Array(tail));
            out.push(Array(items[..2].to_vec()));
            out.push(Array((0..long).map(|_| item(0)).collect()));
            for bad in [Text("1.0".into()), toml::Value::Boolean(true), Array(vec![])] {
                let mut typed = items.clone();
                typed[1] = bad;
                out.push(Array(typed));
            }
            if matrix {
                let mut wide = items.clone();
                wide[2].as_array_mut().expect("row").push(Float(0.0));
                out.push(Array(wide));
            }
        }
        Table(t) => {
            out.push(Array(vec![Integer(1), Integer(2)]));
            out.push(Array(t.values().cloned().collect()));
            out.push(Float(3.0));
        }
        _ => {}
    }
    out
}

/// The one rule for sizes, for every vector, matrix and section of every built-in
/// scenario: each damage (`damaged`) is refused naming the key, with a bounded message.
/// Before issue 45 oversize arrays ran on their first three items (a 4×4 inertia, a
/// million-item `rotor_inertia`), and `run = [1, 2]` ran at 2 Hz.
#[test]
fn oversize_and_mistyped_arrays_and_tables_as_arrays_are_refused_naming_the_key() {
    let mut cases = 0;
    for (name, text) in BUILTIN {
        let file: toml::Table = toml::from_str(text).expect("a built-in parses");
        let mut keys = Vec::new();
        shaped_keys(&file, "", &mut keys);
        assert!(keys.len() >= 10, "{name}: {keys:?}");
        for (key, value) in keys {
            for bad in damaged(&value, 100_000) {
                let mut t = file.clone();
                set(&mut t, &key, bad.clone());
                let changed = toml::to_string(&t).expect("serialise");
                let e = Scenario::from_toml(&changed, name).expect_err(&format!("{key} = {bad}"));
                let msg = e.to_string();
                match &e {
                    ScenarioError::Invalid { field, .. } => assert_eq!(field, &key, "{msg}"),
                    _ => panic!("{name}: {key}: not refused by the rule: {msg}"),
                }
                assert!(msg.contains("is not allowed") && msg.len() < 400, "{msg}");
                cases += 1;
            }
        }
    }
    assert!(cases > 600, "{cases} cases");
}

/// A flag's value and how it is refused: every numeric flag of every command gets
/// negative, non-finite, huge and malformed values; each exits 2 naming the flag and what
/// is allowed, before anything starts. `all`: every value (`--ignored`), else a seeded
/// sample of three a flag.
fn flag_values_are_refused(all: bool) {
    let h = Harness::new("fuzz-flags");
    let mut r = rng(0xf1a9);
    let out = h.path("out");
    let out = out.to_str().expect("utf-8");
    let run = h.path("run");
    std::fs::create_dir_all(&run).expect("run dir");
    let run = run.to_str().expect("utf-8");
    let sc = ["--scenario", "paper-zero"];
    let commands: Vec<(Vec<&str>, &[&str])> = vec![
        (
            vec!["sim", sc[0], sc[1], "--out", out],
            &["--duration", "--rate", "--trace-every", "--actuation-delay", "--seed"],
        ),
        (
            vec!["run", sc[0], sc[1], "--out", out],
            &[
                "--duration",
                "--rate",
                "--hold-ticks",
                "--watchdog-ms",
                "--spin-before-tick-us",
                "--cpu-dma-latency",
                "--flight-ring-ticks",
                "--rt-priority",
                "--actuation-delay",
                "--core",
                "--cpus",
            ],
        ),
        (vec!["paper", "--out", out], &["--duration", "--rate"]),
        (
            vec!["montecarlo", "--out", out],
            &["--runs", "--seed", "--duration", "--rate", "--near-pi-every", "--max-rate"],
        ),
        (vec!["watch", "--domain", "none", "--once"], &["--seconds", "--sample-hz"]),
        (vec!["ps"], &["--sample-ms"]),
        (vec!["doctor"], &["--rate", "--seconds", "--cpus"]),
        (vec!["foxglove", "--domain", "none"], &["--wait-s"]),
        (vec!["margin", "--out", out], &["--duration", "--rate", "--delays"]),
        (vec!["explain", run], &["--threshold-ticks"]),
        (
            vec!["role", "timer", "--out", out],
            &["--rate", "--seconds", "--core", "--rt-priority", "--spin-before-tick-us"],
        ),
        (
            vec!["role", "pingpong", "--kind", "uds", "--side", "ping", "--name", "fuzz"],
            &["--rate", "--seconds", "--core"],
        ),
        (
            vec!["bench", "--out", out],
            &[
                "--rates",
                "--seconds",
                "--loops",
                "--pairs",
                "--repeat",
                "--spin-before-tick-us",
                "--cpu-dma-latency",
                "--rt-priority",
            ],
        ),
        (
            vec!["role", "plant", sc[0], sc[1]],
            &["--subscribers", "--hold-ticks", "--spin-before-tick-us"],
        ),
        (vec!["role", "controller", sc[0], sc[1]], &["--reference-hold-ticks"]),
    ];
    let values =
        ["-1", "-0.5", "nan", "inf", "-inf", "1e300", "-1e300", "18446744073709551616", "x", ""];
    let mut n = 0;
    for (base, flags) in &commands {
        for flag in *flags {
            let picked: Vec<&str> = match all {
                true => values.to_vec(),
                false => values.choose_multiple(&mut r, 3).copied().collect(),
            };
            for v in picked {
                let mut args = base.clone();
                args.extend([*flag, v]);
                let o = h.rotorloop(&args, Duration::from_secs(60));
                let err = String::from_utf8_lossy(&o.stderr);
                assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
                assert!(
                    err.contains(&format!("{flag} ")) || err.contains(&format!("'{flag} ")),
                    "{args:?}: the flag is not named: {err}"
                );
                assert!(err.contains("allowed"), "{args:?}: what is allowed is not said: {err}");
                assert!(!Path::new(out).join("summary.json").exists(), "{args:?}: a summary");
                n += 1;
            }
        }
    }
    assert!(n >= 100, "{n} cases");
}

/// Negative and non-finite flag values, a seeded sample (the whole set: the `--ignored`
/// test below). Before issue 45 `watch --seconds` of −1, NaN or ∞ returned at once with
/// exit 0, `--wait-s NaN` exited 1 ("within NaN s"), `--flight-ring-ticks` of 2⁶³ and up
/// crashed the plant, and `--actuation-delay -0` was "unexpected argument '-0'".
#[test]
fn negative_and_non_finite_flag_values_exit_2_naming_the_flag() {
    flag_values_are_refused(false);
}

/// Every value of [`flag_values_are_refused`] for every flag (about 600 invocations;
/// `cargo test --test tests fuzz_inputs -- --ignored`, docs/tests.md).
#[test]
#[ignore = "the long run of the flag fuzzer; docs/tests.md"]
fn every_flag_value_of_the_fuzzer_exits_2_naming_the_flag() {
    flag_values_are_refused(true);
}

/// Makes a FIFO at `path` (what the fuzzer named as `--scenario` and `--delay-from`).
fn mkfifo(path: &Path) {
    let c = std::ffi::CString::new(path.as_os_str().as_encoded_bytes()).expect("path");
    // SAFETY: a valid NUL-terminated path for the call.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0, "mkfifo {}", path.display());
}

/// A change made to a `launch.json`.
type Damage = Box<dyn Fn(&mut serde_json::Value)>;

/// A run directory's `launch.json`, damaged where it holds arguments and the scenario:
/// `recover` refuses each with exit 2, naming the file and the key or flag (`run = [1, 2]`
/// was read by position, a ring of 2⁶³ ticks passed), and a FIFO in its place is refused,
/// not waited on.
#[test]
fn damaged_launch_json_is_refused_naming_the_file_and_the_key() {
    let h = Harness::new("fuzz-launch");
    let record = rotorloop::run::recover::LaunchRecord {
        domain: h.domain.clone(),
        hosts: None,
        role_args: vec![
            "--domain".into(),
            h.domain.clone(),
            "--scenario".into(),
            "paper-zero".into(),
        ],
        scenario: rotorloop_common::scenario::ScenarioFile::load("paper-zero").expect("built-in"),
        staging: None,
        moved: false,
        csv: true,
        launcher_pid: 1,
    };
    let sound = serde_json::to_value(&record).expect("json");
    let ring = ["--flight-ring-ticks", "9223372036854775808"];
    let cases: Vec<(&str, Damage, &str)> = vec![
        (
            "run as array",
            Box::new(|j| j["scenario"]["run"] = serde_json::json!([1, 2])),
            "run = [1, 2] is not allowed",
        ),
        (
            "4 items",
            Box::new(|j| {
                j["scenario"]["plant"]["rotor_inertia"] = serde_json::json!([5.0, 6.0, 7.0, "x"])
            }),
            "plant.rotor_inertia",
        ),
        (
            "4x4",
            Box::new(|j| {
                j["scenario"]["reference"]["inertia"] = serde_json::json!([
                    [1.0, 0, 0, 0],
                    [0, 1.0, 0, 0],
                    [0, 0, 1.0, 0],
                    [0, 0, 0, 1.0]
                ])
            }),
            "reference.inertia",
        ),
        (
            "torque as array",
            Box::new(|j| {
                j["scenario"]["reference"]["torque"] =
                    serde_json::json!(["constant", [0.2, 0.1, 0.2]])
            }),
            "reference.torque",
        ),
        (
            "gain",
            Box::new(|j| j["scenario"]["controller"]["kp"] = serde_json::json!(-1.0)),
            "controller.kp",
        ),
        (
            "ring",
            Box::new(move |j| {
                j["role_args"].as_array_mut().expect("args").extend(ring.map(|a| a.into()))
            }),
            "--flight-ring-ticks",
        ),
        (
            "duration",
            Box::new(|j| {
                j["role_args"]
                    .as_array_mut()
                    .expect("args")
                    .extend(["--duration".into(), "nan".into()])
            }),
            "--duration",
        ),
        ("scenario as number", Box::new(|j| j["scenario"] = serde_json::json!(3)), "launch.json"),
    ];
    for (i, (what, damage, needle)) in cases.iter().enumerate() {
        let dir = h.path(&format!("run{i}"));
        std::fs::create_dir_all(&dir).expect("dir");
        let mut j = sound.clone();
        damage(&mut j);
        std::fs::write(dir.join("launch.json"), j.to_string()).expect("write");
        let o = h.rotorloop(&["recover", dir.to_str().expect("utf-8")], Duration::from_secs(60));
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{what}: {err}");
        assert!(err.contains("launch.json") && err.contains(needle), "{what}: {err}");
    }
    let dir = h.path("fifo");
    std::fs::create_dir_all(&dir).expect("dir");
    mkfifo(&dir.join("launch.json"));
    let o = h.rotorloop(&["recover", dir.to_str().expect("utf-8")], Duration::from_secs(60));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "FIFO: {err}");
    assert!(err.contains("a FIFO, not a regular file"), "FIFO: {err}");
}

/// Inputs that are not what their flag reads: a FIFO as `--scenario`, `--delay-from` or
/// `--latency-from` (each blocked in `open` for ever), a scenario line of 900 kB (echoed
/// whole, twice), bytes that are not UTF-8 (no line), delays of 1e300 µs (ran), a
/// summary of −1 figures with count 0 (accepted), a missing run directory for `export`
/// (exit 1) and an `--out` that is a file (exit 1). Each exits 2 naming what is wrong.
#[test]
fn inputs_that_are_not_what_their_flag_reads_exit_2_without_waiting() {
    let h = Harness::new("fuzz-files");
    let p = |n: &str| h.path(n).to_str().expect("utf-8").to_owned();
    let (fifo, out) = (p("fifo"), p("out"));
    mkfifo(Path::new(&fifo));
    let base = BUILTIN[0].1;
    let long = base.replacen("kp = 1.0", &format!("kp = 1.0{}", "9x".repeat(450_000)), 1);
    std::fs::write(p("long.toml"), long).expect("write");
    let mut bad = base.as_bytes().to_vec();
    bad.splice(0..0, b"# \xff\n".iter().copied());
    std::fs::write(p("bytes.toml"), bad).expect("write");
    std::fs::write(p("far.hgrm"), "1.0 0.0 1\n1e300 1.0 2\n").expect("write");
    let zero = r#"{"hops": {"sense_to_actuate": {"count": 0, "p50": -1, "p99": -1, "max": -1}}}"#;
    std::fs::write(p("summary.json"), zero).expect("write");
    std::fs::write(p("file"), "").expect("write");
    let sim = |extra: &[&str]| -> Vec<String> {
        let mut a: Vec<String> = ["sim", "--out", &out, "--no-figures"].map(String::from).to_vec();
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    let cases: Vec<(Vec<String>, &str)> = vec![
        (sim(&["--scenario", &fifo]), "a FIFO, not a regular file"),
        (sim(&["--scenario", "paper-zero", "--delay-from", &fifo]), "a FIFO, not a regular file"),
        (sim(&["--scenario", &p("long.toml")]), "line 24, column "),
        (sim(&["--scenario", &p("bytes.toml")]), "line 1, column 3: byte 0xff is not UTF-8"),
        (
            sim(&["--scenario", "paper-zero", "--delay-from", &p("far.hgrm")]),
            "line 2: `1e300 1.0 2`",
        ),
        (["margin", "--latency-from", &fifo, "--out", &out].map(String::from).to_vec(), "a FIFO"),
        (
            ["margin", "--latency-from", &p("summary.json"), "--out", &out]
                .map(String::from)
                .to_vec(),
            "count = 0",
        ),
        (["export", &p("none"), "--mcap"].map(String::from).to_vec(), "a run directory"),
        (
            ["sim", "--scenario", "paper-zero", "--out", &p("file")].map(String::from).to_vec(),
            "is a file, not a directory",
        ),
    ];
    for (args, needle) in cases {
        let argv: Vec<&str> = args.iter().map(String::as_str).collect();
        let o = h.rotorloop(&argv, Duration::from_secs(60));
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {}", &err[..err.len().min(2000)]);
        assert!(err.contains(needle), "{args:?}: {}", &err[..err.len().min(2000)]);
        assert!(err.len() < 4000, "{args:?}: {} bytes of errors", err.len());
    }
}

/// One exit-code rule: a run stopped by a role that exited 2 (it refused its input, or the
/// run diverged: the plant's `diverged`) exits 2, as `sim` does for the same scenario;
/// it exited 1. A controller of the user's own that exits 2 at once stands for it.
#[test]
fn a_run_stopped_by_a_role_that_refused_its_input_exits_2() {
    use std::os::unix::fs::PermissionsExt;
    let h = Harness::new("fuzz-exit2");
    let ctl = h.path("refuses.sh");
    std::fs::write(&ctl, "#!/bin/sh\necho 'controller: error: a value it refuses' >&2\nexit 2\n")
        .expect("write");
    std::fs::set_permissions(&ctl, std::fs::Permissions::from_mode(0o755)).expect("chmod");
    let out = h.path("out");
    let args = [
        "run",
        "--scenario",
        "paper-zero",
        "--mode",
        "lockstep",
        "--duration",
        "0.05",
        "--quiet",
        "--domain",
        &h.domain,
        "--controller-cmd",
        ctl.to_str().expect("utf-8"),
        "--out",
        out.to_str().expect("utf-8"),
    ];
    let o = h.rotorloop(&args, Duration::from_secs(120));
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("controller") && err.contains("not restarted"), "{err}");
    h.assert_no_leftovers();
}

/// A `paper-constant` run of `h` with `args` into `h`'s `run` directory, finished: the
/// directory and its path as text.
fn finished_run(h: &Harness, args: &[&str]) -> (std::path::PathBuf, String) {
    let dir = h.path("run");
    let d = dir.display().to_string();
    let mut run = vec!["run", "--scenario", "paper-constant", "--domain", &h.domain];
    run.extend(args);
    run.extend(["--out", &d, "--quiet"]);
    let o = h.rotorloop(&run, Duration::from_secs(120));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    (dir, d)
}

/// Damaged flight records and a `launch.json` that claims more than its records hold
/// (issue 45, points 1 and 5): a far-future tick in every stream (tag and sample agreeing
/// on capacity × 2⁴⁰, which made `explain`, `export --mcap` and `recover` abort allocating
/// exabytes), a torn and a zero-length segment, then a claim of 86 400 s at 100 kHz over
/// 2001 recorded ticks (which `recover` looped over). Each reader ends, reads what is
/// sound, and names in `summary.json` what it skipped.
#[test]
fn damaged_records_and_claims_are_read_as_far_as_they_are_sound() {
    let h = Harness::new("damaged-records");
    // Raw records (a run of an earlier build): a far tick is written into a ring's slot.
    let args = ["--duration", "2", "--mode", "lockstep", "--flight-ring-ticks", "512"];
    let (dir, d) = finished_run(&h, &[&args[..], &["--raw-segments"]].concat());
    let flight = dir.join("flight");
    for stream in ["plant-state", "plant-torque", "controller-torque", "reference"] {
        use std::os::unix::fs::FileExt;
        let f = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(flight.join(format!("{stream}.flight")))
            .expect("ring");
        let mut capacity = [0u8; 8];
        f.read_exact_at(&mut capacity, 24).expect("header");
        let k = u64::from_ne_bytes(capacity) << 40;
        let slot: Vec<u8> = [(k + 1).to_ne_bytes(), k.to_ne_bytes()].concat();
        f.write_all_at(&slot, 64).expect("far tick");
    }
    let torn = flight.join("plant-state.000001.flight");
    let len = std::fs::metadata(&torn).expect("segment 1").len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&torn)
        .expect("open")
        .set_len(len / 3)
        .expect("tear");
    std::fs::write(flight.join("reference.000002.flight"), b"").expect("zero-length");
    let launch = dir.join("launch.json");
    let mut j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&launch).expect("launch.json"))
            .expect("json");
    j["scenario"]["run"]["duration_s"] = serde_json::json!(86400.0);
    j["scenario"]["run"]["rate_hz"] = serde_json::json!(100000.0);
    std::fs::write(&launch, j.to_string()).expect("claim");
    for args in [vec!["explain", &d], vec!["export", &d, "--mcap"], vec!["recover", &d]] {
        let o = h.rotorloop(&args, Duration::from_secs(120));
        assert!(
            o.status.success(),
            "{args:?}: {:?}\n{}",
            o.status,
            String::from_utf8_lossy(&o.stderr)
        );
    }
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).expect("summary"))
            .expect("json");
    let streams = summary["flight"]["streams"].as_array().expect("streams");
    let problems = |name: &str| {
        let s = streams.iter().find(|s| s["stream"] == name).expect("stream");
        s["problems"].to_string()
    };
    assert!(
        problems("plant-state").contains("plant-state.000001.flight"),
        "{}",
        problems("plant-state")
    );
    assert!(problems("plant-state").contains("beyond the run"), "{}", problems("plant-state"));
    assert!(problems("reference").contains("reference.000002.flight"), "{}", problems("reference"));
    let state = streams.iter().find(|s| s["stream"] == "plant-state").expect("state");
    // Tick 0's ring slot held tick 1536 by the end, which its segment still has: only
    // the torn segment's ticks are missing.
    assert_eq!(state["missing"], serde_json::json!([[256, 511]]), "the torn segment's ticks");
    // A row needs its state and its reference: the torn state segment's ticks and the
    // empty reference segment's (512–767) have none; every other tick has its row.
    assert_eq!(summary["trace_rows"], serde_json::json!(2001 - 256 - 256));
}

/// A role's `--record` where nothing can be made (a kernel file system, a path under a
/// file, an existing file) is refused with exit 2 naming the flag, before the role makes
/// anything in /dev/shm (issue 64: it was exit 1, leaving the domain's files behind).
#[test]
fn a_record_directory_that_cannot_be_made_is_refused_before_anything_is_made() {
    let h = Harness::new("bad-record");
    let file = h.path("a-file");
    std::fs::create_dir_all(file.parent().expect("parent")).expect("harness dir");
    std::fs::write(&file, b"x").expect("a file");
    let under = file.join("flight");
    let mut dirs = vec![file.to_str().expect("utf-8"), under.to_str().expect("utf-8")];
    if Path::new("/proc/self").exists() {
        dirs.push("/proc/rotorloop-record");
    }
    for role in ["plant", "controller", "reference"] {
        for dir in &dirs {
            let args = ["role", role, "--scenario", "paper-zero", "--domain", &h.domain];
            let o = h.rotorloop(&[&args[..], &["--record", dir]].concat(), Duration::from_secs(60));
            let err = String::from_utf8_lossy(&o.stderr);
            assert_eq!(o.status.code(), Some(2), "{role} --record {dir}: {err}");
            assert!(err.contains("'--record <DIR>'"), "{role} --record {dir}: {err}");
            h.assert_no_leftovers();
        }
    }
}

/// A record whose header names another layout (damaged, or of another build) is the
/// input's fault: the readers of the run directory exit 2 naming the file, as
/// docs/running.md's table says (issue 64; it was exit 1).
#[test]
fn a_record_of_another_layout_is_refused_with_exit_2_naming_it() {
    use std::os::unix::fs::FileExt;
    let h = Harness::new("foreign-record");
    let (dir, d) = finished_run(&h, &["--duration", "1", "--mode", "lockstep"]);
    let record = dir.join("flight/plant-state.flight");
    let f = std::fs::OpenOptions::new().write(true).open(&record).expect("record");
    f.write_all_at(&[0xff; 16], 8).expect("the layout words");
    for args in [vec!["explain", &d], vec!["recover", &d]] {
        let o = h.rotorloop(&args, Duration::from_secs(120));
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(stderr.contains("plant-state.flight: written by layout v"), "{args:?}: {stderr}");
    }
}

/// A damaged `summary.json` (not JSON, no scenario, a scenario claiming a day at 100 kHz,
/// an absurd tick count) fed to the readers of a finished run: each ends at once, with
/// exit 2 naming `summary.json` where it needs what is damaged, or reads the run from its
/// records (`export` only attaches the summary), never looping over a claim.
#[test]
fn a_damaged_summary_is_refused_by_name_or_read_around() {
    let h = Harness::new("damaged-summary");
    let (dir, d) = finished_run(&h, &["--duration", "1", "--mode", "realtime"]);
    let path = dir.join("summary.json");
    let good: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).expect("summary")).expect("json");
    let mut claim = good.clone();
    claim["scenario"]["run"]["duration_s"] = serde_json::json!(86400.0);
    claim["scenario"]["run"]["rate_hz"] = serde_json::json!(100000.0);
    let mut no_scenario = good.clone();
    no_scenario["scenario"] = serde_json::Value::Null;
    let mut ticks = good.clone();
    ticks["ticks"] = serde_json::json!(u64::MAX);
    let cases = [
        ("not JSON", "{\"scenario\": [1, 2".to_owned()),
        ("no scenario", no_scenario.to_string()),
        ("a day at 100 kHz", claim.to_string()),
        ("2^64 - 1 ticks", ticks.to_string()),
    ];
    let replay = h.path("replay").display().to_string();
    for (what, text) in cases {
        for args in [
            vec!["explain", &d],
            vec!["export", &d, "--mcap"],
            vec!["sim", "--replay", &d, "--out", &replay],
        ] {
            std::fs::write(&path, &text).expect("damage");
            let o = h.rotorloop(&args, Duration::from_secs(60));
            let err = String::from_utf8_lossy(&o.stderr);
            match o.status.code() {
                Some(0) => {}
                Some(1) if args[0] == "sim" => {
                    assert!(err.contains("replay.json"), "{what}: {args:?}: {err}")
                }
                Some(2) => assert!(err.contains("summary.json"), "{what}: {args:?}: {err}"),
                c => panic!("{what}: {args:?}: exit {c:?}: {err}"),
            }
        }
    }
}
