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

/// Values that replace a number in a scenario file: valid, out of range, wrong type.
const VALUES: [&str; 24] = [
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
    let mut r = rng(0x5eed_f00d);
    let (mut valid, mut invalid) = (0, 0);
    for case in 0..3000 {
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
            }
        }
    }
    assert!(valid > 150 && invalid > 1500, "coverage: {valid} valid, {invalid} invalid");
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
    let bad: [(&str, &[&str]); 10] = [
        ("--pin", &["plant", "plant=99", "nobody=0", "plant=-1", "plant=0,controller=x"]),
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
