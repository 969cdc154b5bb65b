//! `rotorloop run --controller-cmd "COMMAND …"`: a controller of the user's own, in any
//! language, in the built-in controller's place and under the same supervision (restart
//! policy, watchdog, `kill`/`stop` faults, pinning and priority, `ps`/`watch`, the report).
//!
//! The command is split into words (`'…'` and `"…"` group words; no shell runs it) and
//! started as a plain process with the built-in controller's arguments appended
//! (`--domain D --scenario OUT/scenario.toml --mode M --wait W …`, which a program may
//! ignore; the scenario is the file as run, never a built-in name), and with
//! the run described in its environment:
//!
//! | variable | what |
//! |---|---|
//! | `ROTORLOOP_DOMAIN` | the run's domain |
//! | `ROTORLOOP_IOX2_CONFIG` | `OUT/config/iceoryx2.toml`: the domain's iceoryx2 config |
//! | `ROTORLOOP_MODE` | `lockstep` or `realtime` |
//! | `ROTORLOOP_WAIT` | `event`, `spin` or `hybrid` |
//! | `ROTORLOOP_RATE_HZ`, `ROTORLOOP_DT_S`, `ROTORLOOP_TICKS` | the grid as run |
//! | `ROTORLOOP_SCENARIO` | `OUT/scenario.toml`: the scenario as run (overrides applied) |
//! | `ROTORLOOP_CONTROLLER_JSON` | `OUT/controller.json`: what the law needs, resolved (gains, `P`, the controller's model of `I` and `K`, actuation, limits) |
//! | `ROTORLOOP_STATE_DIR` | a directory that survives the controller's restarts (for its own resume state) |
//!
//! The program is pinned and given its priority by the launcher before it starts
//! (`--pin controller=N`, `--rt-priority`), since it cannot be trusted to do it. A
//! program that cannot be started is a usage error (exit 2) before the run starts. Its
//! progress, for the watchdog, is the newest of its torques the plant has taken (it keeps
//! no rotorloop resume slot).

use std::path::{Path, PathBuf};
use std::process::Command;

use rotorloop_common::controller_json::{
    CONTROLLER_JSON_VERSION, ControllerJson, JsonGains, JsonLimits, JsonModel,
};
use rotorloop_common::role::UsageError;
use rotorloop_common::role::args::RoleArgs;
use rotorloop_common::scenario::Scenario;

/// A user's controller command, checked.
#[derive(Debug, Clone)]
pub struct ExternalController {
    /// The program, as found.
    pub program: PathBuf,
    /// Its arguments from the command.
    pub args: Vec<String>,
}

/// Splits `s` into words: whitespace separates, `'…'` and `"…"` group (no escapes, no
/// variables: no shell).
pub fn split_words(s: &str) -> Result<Vec<String>, UsageError> {
    let mut words = Vec::new();
    let mut word: Option<String> = None;
    let mut quote: Option<char> = None;
    for c in s.chars() {
        match (quote, c) {
            (Some(q), c) if c == q => quote = None,
            (Some(_), c) => word.get_or_insert_with(String::new).push(c),
            (None, '\'' | '"') => {
                quote = Some(c);
                word.get_or_insert_with(String::new);
            }
            (None, c) if c.is_whitespace() => words.extend(word.take()),
            (None, c) => word.get_or_insert_with(String::new).push(c),
        }
    }
    if quote.is_some() {
        return Err(UsageError(format!(
            "--controller-cmd `{s}` is not allowed: a quote is not closed"
        )));
    }
    words.extend(word);
    Ok(words)
}

/// Whether `p` is a file this process may execute.
fn executable(p: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(p).is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
}

impl ExternalController {
    /// Checks `cmd`: words, and a program that exists and may be executed (a name without
    /// `/` is looked up in `PATH`).
    pub fn parse(cmd: &str) -> Result<Self, UsageError> {
        let mut words = split_words(cmd)?.into_iter();
        let first = words.next().ok_or_else(|| {
            UsageError(
                "--controller-cmd is empty: give a command, e.g. \"python3 controller.py\"".into(),
            )
        })?;
        let program = if first.contains('/') {
            Some(PathBuf::from(&first)).filter(|p| executable(p))
        } else {
            std::env::var_os("PATH").and_then(|paths| {
                std::env::split_paths(&paths).map(|d| d.join(&first)).find(|p| executable(p))
            })
        };
        let program = program.ok_or_else(|| {
            UsageError(format!(
                "--controller-cmd: cannot start `{first}`: no such executable file{}",
                if first.contains('/') { "" } else { " in PATH" }
            ))
        })?;
        Ok(Self { program, args: words.collect() })
    }

    /// The command that starts it for `role_args` (the built-in controller's arguments
    /// are appended), with the run in its environment, pinned to `core` and given
    /// SCHED_FIFO `priority` before it runs.
    pub fn command(&self, role_args: &RoleArgs, out: &Path, scenario: &Scenario) -> Command {
        let mut cmd = Command::new(&self.program);
        // `--scenario` names the scenario as run, a file any program can read: a built-in
        // name would mean nothing outside rotorloop.
        let mut appended = role_args.clone();
        appended.scenario = out.join(SCENARIO_FILE).display().to_string();
        cmd.args(&self.args).args(appended.to_args());
        let mode = match role_args.mode {
            rotorloop_common::role::args::Mode::Lockstep => "lockstep",
            rotorloop_common::role::args::Mode::Realtime => "realtime",
        };
        cmd.env("ROTORLOOP_DOMAIN", role_args.domain())
            .env("ROTORLOOP_IOX2_CONFIG", out.join("config/iceoryx2.toml"))
            .env("ROTORLOOP_MODE", mode)
            .env("ROTORLOOP_WAIT", role_args.wait.to_string())
            .env("ROTORLOOP_RATE_HZ", scenario.file.run.rate_hz.to_string())
            .env("ROTORLOOP_DT_S", scenario.dt().to_string())
            .env("ROTORLOOP_TICKS", scenario.ticks().to_string())
            .env("ROTORLOOP_SCENARIO", out.join(SCENARIO_FILE))
            .env("ROTORLOOP_CONTROLLER_JSON", out.join(CONTROLLER_FILE))
            .env("ROTORLOOP_STATE_DIR", state_dir(out));
        let (core, priority) = (role_args.core, role_args.rt_priority);
        use std::os::unix::process::CommandExt;
        // SAFETY: runs in the child between fork and exec, calling only async-signal-safe
        // system calls on itself; a refusal leaves the child as it was (the built-in
        // roles warn about the same refusals; here the program runs on regardless).
        unsafe {
            cmd.pre_exec(move || {
                if let Some(c) = core {
                    let mut set: libc::cpu_set_t = std::mem::zeroed();
                    libc::CPU_SET(c, &mut set);
                    libc::sched_setaffinity(0, size_of::<libc::cpu_set_t>(), &set);
                }
                if let Some(p) = priority {
                    let param = libc::sched_param { sched_priority: p };
                    libc::sched_setscheduler(0, libc::SCHED_FIFO, &param);
                }
                libc::prctl(libc::PR_SET_TIMERSLACK, 1 as libc::c_ulong, 0, 0, 0);
                Ok(())
            });
        }
        cmd
    }
}

/// `--controller-cmd` checked against the rest of the command line, before anything
/// starts: the program, and no fault or corruption the built-in controller would have
/// to apply itself, and no split run (its hosts start the built-in roles).
pub fn check(
    args: &crate::run::args::RunArgs,
    faults: &[crate::run::fault::Fault],
) -> Result<Option<ExternalController>, UsageError> {
    let Some(cmd) = &args.controller_cmd else { return Ok(None) };
    let ext = ExternalController::parse(cmd)?;
    let refuse = |what: &str| {
        UsageError(format!(
            "--controller-cmd is not allowed with {what}: the built-in controller applies it itself"
        ))
    };
    if args.corrupt.iter().any(|c| c.starts_with("controller:")) {
        return Err(refuse("--corrupt controller:…"));
    }
    if faults
        .iter()
        .any(|f| f.role.is(rotorloop_common::graph::Role::Controller) && f.role_arg().is_some())
    {
        return Err(refuse("--fault controller:delay…"));
    }
    if args.split.is_some() {
        return Err(UsageError("--controller-cmd is not allowed with --split".into()));
    }
    Ok(Some(ext))
}

/// `OUT/scenario.toml`: the scenario as run.
pub const SCENARIO_FILE: &str = "scenario.toml";
/// `OUT/controller.json`: what a law needs, resolved.
pub const CONTROLLER_FILE: &str = "controller.json";

/// The directory a user's controller keeps its own resume state in.
pub fn state_dir(out: &Path) -> PathBuf {
    out.join("controller-state")
}

/// Writes the files the environment points at: the scenario as run, and what the law
/// needs (gains, `P`, the controller's model, actuation, limits, `dt`, ticks).
pub fn write_run_files(out: &Path, scenario: &Scenario) -> anyhow::Result<()> {
    use anyhow::Context;
    let dir = rotorloop_common::outdir::OutDir::open(out)?;
    dir.write(SCENARIO_FILE, scenario.file.to_toml().as_bytes())
        .with_context(|| format!("cannot write {}", out.join(SCENARIO_FILE).display()))?;
    let actuation = scenario.actuation();
    let model = scenario.controller_params(actuation);
    let limits = scenario.limits_for(actuation);
    let rows = |m: glam::DMat3| m.transpose().to_cols_array_2d();
    let g = &scenario.gains;
    let law_params = match serde_json::to_value(&scenario.law_params)? {
        serde_json::Value::Object(m) => m,
        _ => serde_json::Map::new(),
    };
    let j = ControllerJson {
        layout_version: CONTROLLER_JSON_VERSION,
        law: scenario.law.as_deref().unwrap_or("geometric-pid").to_owned(),
        actuation: actuation.to_string(),
        dt_s: scenario.dt(),
        rate_hz: scenario.file.run.rate_hz,
        ticks: scenario.ticks(),
        gains: JsonGains { kp: g.kp, kd: g.kd, ki: g.ki, p: rows(g.p) },
        model: JsonModel {
            inertia: rows(model.inertia),
            rotor_inertia: model.rotor_inertia.to_array(),
        },
        limits: JsonLimits {
            rotor_torque_nm: limits.rotor_torque,
            rotor_rate_rad_s: limits.rotor_rate,
        },
        anti_windup: format!("{:?}", scenario.anti_windup).to_lowercase(),
        law_params,
    };
    let path = out.join(CONTROLLER_FILE);
    dir.write(CONTROLLER_FILE, (serde_json::to_string_pretty(&j)? + "\n").as_bytes())
        .with_context(|| format!("cannot write {}", path.display()))?;
    // A new run starts with an empty state directory: a controller must never resume
    // the state of an earlier run written into the same `--out` (its restarts within
    // this run keep it: this runs once, before the first start).
    // (`remove_dir_all` never follows a link: it works relative to each directory.)
    let state = state_dir(out);
    match std::fs::remove_dir_all(&state) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            return Err(e).with_context(|| format!("cannot clear {}", state.display()));
        }
        _ => {}
    }
    dir.subdir("controller-state")?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn words_split_on_whitespace_and_group_in_quotes() {
        let w = split_words("python3  'my dir/c.py' --gain \"1 2\" x").expect("words");
        assert_eq!(w, ["python3", "my dir/c.py", "--gain", "1 2", "x"]);
        assert_eq!(split_words("a ''").expect("an empty word"), ["a", ""]);
        assert!(split_words("a 'b").is_err());
    }

    /// A program that is not there is refused with the name and where it was looked for.
    #[test]
    fn a_program_that_cannot_be_started_is_refused() {
        let e = ExternalController::parse("no-such-controller-xyz --x").expect_err("absent");
        assert!(e.0.contains("no-such-controller-xyz") && e.0.contains("PATH"), "{e}");
        let e = ExternalController::parse("/nonexistent/ctl").expect_err("absent");
        assert!(e.0.contains("/nonexistent/ctl"), "{e}");
        assert!(ExternalController::parse("   ").is_err());
        let ok = ExternalController::parse("sh -c true").expect("sh is in PATH");
        assert_eq!(ok.args, ["-c", "true"]);
    }
}
