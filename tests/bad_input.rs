//! Every class of bad scenario value is refused with an error naming the field and what
//! is allowed (exit code 2 from the CLI, no summary written); odd-but-valid inputs warn
//! and run.

use std::process::Command;

use rotorloop_common::scenario::Scenario;

const PAPER: &str = include_str!("../scenarios/paper-zero.toml");

/// The paper scenario with one line replaced (the line must exist).
fn with(find: &str, replace: &str) -> String {
    assert!(PAPER.contains(find), "test bug: `{find}` not in the paper scenario");
    PAPER.replacen(find, replace, 1)
}

fn refused(text: &str, field: &str, allowed_hint: &str) {
    let err = Scenario::from_toml(text, "test.toml").expect_err("must be refused").to_string();
    assert!(err.contains(field), "error does not name `{field}`: {err}");
    assert!(
        err.contains(allowed_hint),
        "error does not say what is allowed (`{allowed_hint}`): {err}"
    );
}

#[test]
fn inertia_not_symmetric_positive_definite_is_refused() {
    refused(
        &with("inertia = [[4.0, 1.0, 1.0]", "inertia = [[-4.0, 1.0, 1.0]"),
        "plant.inertia",
        "positive definite",
    );
    refused(
        &with("inertia = [[4.0, 1.0, 1.0]", "inertia = [[4.0, 1.5, 1.0]"),
        "plant.inertia",
        "not symmetric",
    );
    refused(
        &with("[[1.0, 0.0, 0.0], [0.0, 1.2, 0.0]", "[[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]"),
        "reference.inertia",
        "positive definite",
    );
}

#[test]
fn rotor_inertia_not_positive_diagonal_is_refused() {
    refused(
        &with("rotor_inertia = [5.0, 6.0, 7.0]", "rotor_inertia = [5.0, 0.0, 7.0]"),
        "plant.rotor_inertia",
        "positive diagonal",
    );
    refused(
        &with("rotor_inertia = [4.0, 3.0, 2.0]", "rotor_inertia = [4.0, -3.0, 2.0]"),
        "reference.rotor_inertia",
        "positive diagonal",
    );
}

#[test]
fn initial_attitude_off_so3_is_refused() {
    // not orthonormal
    refused(&with("[[0.36, 0.48, -0.8]", "[[0.36, 0.48, -0.81]"), "plant.attitude", "det +1");
    // a reflection: orthonormal, det −1
    refused(&with("[[0.36, 0.48, -0.8]", "[[-0.36, -0.48, 0.8]"), "plant.attitude", "det +1");
    // within 1e-6: accepted and projected onto SO(3)
    let s = Scenario::from_toml(&with("[[0.36, 0.48, -0.8]", "[[0.3600000004, 0.48, -0.8]"), "t")
        .expect("within tolerance");
    let (o, d) = rotorloop_common::so3::orthonormality_error(&s.plant_init.r);
    assert!(o < 1e-14 && d < 1e-14);
}

#[test]
fn non_positive_or_non_finite_gains_are_refused() {
    refused(&with("kp = 1.0", "kp = 0.0"), "controller.kp", "> 0");
    refused(&with("kd = 3.0", "kd = -3.0"), "controller.kd", "> 0");
    refused(&with("ki = 1.0", "ki = -0.5"), "controller.ki", "≥ 0");
    refused(&with("kp = 1.0", "kp = nan"), "controller.kp", "finite");
    refused(&with("kd = 3.0", "kd = inf"), "controller.kd", "finite");
    // k_I = 0 is the PD law: allowed
    assert!(Scenario::from_toml(&with("ki = 1.0", "ki = 0.0"), "t").is_ok());
}

#[test]
fn p_not_symmetric_positive_definite_is_refused() {
    refused(
        &with("p = [[0.9, 0.0, 0.0]", "p = [[-0.9, 0.0, 0.0]"),
        "controller.p",
        "positive definite",
    );
    refused(&with("p = [[0.9, 0.0, 0.0]", "p = [[0.9, 0.2, 0.0]"), "controller.p", "symmetric");
}

#[test]
fn rate_or_duration_out_of_range_is_refused() {
    refused(&with("rate_hz = 1000.0", "rate_hz = 0.0"), "run.rate_hz", "from 1 to 100000");
    refused(&with("rate_hz = 1000.0", "rate_hz = 1e9"), "run.rate_hz", "from 1 to 100000");
    refused(
        &with("duration_s = 30.0", "duration_s = -1.0"),
        "run.duration_s",
        "from 0.001 to 86400",
    );
    refused(&with("duration_s = 30.0", "duration_s = nan"), "run.duration_s", "finite");
}

#[test]
fn unknown_scenario_profile_or_field_is_refused() {
    let err = Scenario::load("paper-zeroo").expect_err("unknown").to_string();
    assert!(err.contains("paper-zeroo") && err.contains("paper-sinusoid"), "{err}");
    refused(
        &with("profile = \"zero\"", "profile = \"square\""),
        "reference.torque.profile",
        "`sinusoid`",
    );
    // A misspelt key must not silently fall back to a default.
    let err =
        Scenario::from_toml(&with("kp = 1.0", "kpp = 1.0"), "t").expect_err("misspelt").to_string();
    assert!(err.contains("kpp"), "{err}");
    let err = Scenario::from_toml(&with("duration_s = 30.0", "duration = 30.0"), "t")
        .expect_err("misspelt")
        .to_string();
    assert!(err.contains("duration"), "{err}");
    let err = Scenario::from_toml(&format!("{PAPER}\n[plantt]\nx = 1\n"), "t")
        .expect_err("unknown table")
        .to_string();
    assert!(err.contains("plantt"), "{err}");
    // a profile field that does not belong to the profile
    refused(
        &with("profile = \"zero\"", "profile = \"zero\"\nvalue = [1.0, 2.0, 3.0]"),
        "reference.torque.value",
        "only with",
    );
    // a required profile field missing
    refused(
        &with("profile = \"zero\"", "profile = \"constant\""),
        "reference.torque.value",
        "required",
    );
    // both forms of the initial rate
    refused(
        &with(
            "rotor_rates = [0.5, 1.9, 1.5]",
            "rotor_rates = [0.5, 1.9, 1.5]\nomega = [0.0, 0.0, 0.0]",
        ),
        "plant.omega / plant.i_omega",
        "exactly one",
    );
}

#[test]
fn odd_but_valid_inputs_warn_and_run() {
    let paper = Scenario::from_toml(PAPER, "t").expect("valid");
    assert!(
        paper.warnings.iter().any(|w| w.contains("triangle inequality")),
        "{:?}",
        paper.warnings
    );
    let s = Scenario::from_toml(
        &with(
            "p = [[0.9, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.1]]",
            "p = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.1]]",
        ),
        "t",
    )
    .expect("valid");
    assert!(s.warnings.iter().any(|w| w.contains("repeated eigenvalues")), "{:?}", s.warnings);
    let s = Scenario::from_toml(&with("ki = 1.0", "ki = 5.0"), "t").expect("valid");
    assert!(s.warnings.iter().any(|w| w.contains("not Hurwitz")), "{:?}", s.warnings);
}

fn rotorloop(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_rotorloop")).args(args).output().expect("run rotorloop")
}

/// The CLI turns every refusal into exit code 2 with the message on stderr, and leaves
/// no summary.json that would make the directory look like a finished run.
#[test]
fn cli_refuses_bad_input_with_exit_code_2() {
    let dir = tempfile::tempdir().expect("tempdir");
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, with("kp = 1.0", "kp = -1.0")).expect("write");
    // The law's name is the controller crate's: refused before any process starts.
    let no_law = dir.path().join("no-law.toml");
    std::fs::write(&no_law, with("kp = 1.0", "law = \"bang-bang\"\nkp = 1.0")).expect("write");
    let no_law = no_law.to_str().expect("utf8");
    let out_dir = dir.path().join("out");
    let out_s = out_dir.to_str().expect("utf8");
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (vec!["sim", "--scenario", bad.to_str().expect("utf8"), "--out", out_s], "controller.kp"),
        (vec!["sim", "--scenario", "nope", "--out", out_s], "unknown scenario"),
        // The flags' ranges are clap's to check (they are the scenario's): named as flags.
        (vec!["sim", "--scenario", "paper-zero", "--rate", "0", "--out", out_s], "--rate"),
        (
            vec!["sim", "--scenario", "paper-zero", "--duration", "-5", "--out", out_s],
            "'--duration <DURATION>': allowed: a finite number from 0.001 to 86400 (seconds)",
        ),
        (
            vec!["sim", "--scenario", "paper-zero", "--open-loop", "1,2", "--out", out_s],
            "three finite numbers",
        ),
        (
            vec!["sim", "--scenario", "paper-zero", "--actuation", "jets", "--out", out_s],
            "actuation",
        ),
        (
            vec!["sim", "--scenario", "paper-zero", "--trace-every", "0", "--out", out_s],
            "trace-every",
        ),
        (vec!["montecarlo", "--runs", "0", "--out", out_s], "runs"),
        (vec!["sim", "--scenario", no_law, "--out", out_s], "controller.law: no law is named"),
        (vec!["run", "--scenario", no_law, "--out", out_s], "allowed: geometric-pid"),
        (vec!["gains", "--scenario", bad.to_str().expect("utf8")], "controller.kp"),
    ];
    for (args, needle) in cases {
        let o = rotorloop(&args);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(stderr.contains(needle), "{args:?}: stderr does not mention `{needle}`: {stderr}");
        assert!(!out_dir.join("summary.json").exists(), "{args:?} left a summary.json");
    }
}

/// The extensions' fields: limits must be positive, the initial rotor rates within the
/// speed limit, the disturbance finite, the inertia factor in range, the anti-windup rule
/// one of its names.
#[test]
fn actuator_disturbance_and_mismatch_values_out_of_range_are_refused() {
    let plant = "rotor_rates = [0.5, 1.9, 1.5]";
    for (line, field, hint) in [
        ("rotor_torque_limit = -1.0", "plant.rotor_torque_limit", "> 0"),
        ("rotor_torque_limit = nan", "plant.rotor_torque_limit", "> 0"),
        ("rotor_rate_limit = 0.0", "plant.rotor_rate_limit", "> 0"),
        ("rotor_rate_limit = 1.0", "plant.rotor_rates", "≤ plant.rotor_rate_limit"),
        ("disturbance_torque = [0.0, inf, 0.0]", "plant.disturbance_torque", "finite"),
    ] {
        refused(&with(plant, &format!("{plant}\n{line}")), field, hint);
    }
    refused(&with("kp = 1.0", "kp = 1.0\ninertia_factor = 20.0"), "inertia_factor", "0.1 to 10");
    refused(&with("kp = 1.0", "kp = 1.0\ninertia_factor = 0.0"), "inertia_factor", "0.1 to 10");
    let err = Scenario::from_toml(&with("kp = 1.0", "kp = 1.0\nanti_windup = \"clamp\""), "t")
        .expect_err("unknown rule")
        .to_string();
    assert!(err.contains("conditional") && err.contains("none"), "{err}");
    // And the valid ones load.
    let ok = with(plant, &format!("{plant}\nrotor_torque_limit = 2.0\nrotor_rate_limit = 5.0"));
    let s = Scenario::from_toml(&ok, "t").expect("valid limits");
    assert_eq!(s.limits.rotor_torque, Some(2.0));
    assert_eq!(s.limits.rotor_rate, Some(5.0));
}
