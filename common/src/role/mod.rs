//! What every role process shares beyond the wire: how a process starts and reports its
//! errors ([`role_main`], [`UsageError`]), the arguments all four take ([`args`]), how it
//! ends without losing data and learns that the run is over ([`end`]), how it counts
//! what it received ([`count`]), and the faults a role injects into itself ([`inject`]).

pub mod args;
pub mod count;
pub mod end;
pub mod inject;

/// An error the user caused (bad argument or scenario value): exit code 2.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct UsageError(pub String);

impl From<crate::scenario::ScenarioError> for UsageError {
    fn from(e: crate::scenario::ScenarioError) -> Self {
        Self(e.to_string())
    }
}

/// Whether `e` is the user's to mend (exit code 2): a [`UsageError`], or a refusal of
/// something another user put where the run makes its own files ([`crate::private`]), or
/// an output directory another user can change ([`crate::outdir`]).
pub fn is_usage_error(e: &anyhow::Error) -> bool {
    use crate::private::{Foreign, PrivateError};
    e.downcast_ref::<UsageError>().is_some()
        || e.downcast_ref::<Foreign>().is_some()
        || matches!(e.downcast_ref::<PrivateError>(), Some(PrivateError::Foreign(_)))
        || e.downcast_ref::<crate::ipc::IpcError>().is_some_and(|i| i.is_foreign())
        || e.downcast_ref::<crate::outdir::OutError>().is_some_and(|o| o.is_refusal())
}

/// The error of a run whose state stopped being finite: a configuration the integrator
/// or the loop cannot handle (exit code 2, like any other bad scenario value).
pub fn diverged(tick: u64, t: f64) -> UsageError {
    UsageError(format!(
        "the run diverged at tick {tick} (t = {t} s): the plant's state is no longer finite. \
         The scenario is valid but unstable at this tick rate (gains, rates or torques too \
         large for dt?); no summary.json was written"
    ))
}

/// `main` of a role binary: parse arguments, install signal handlers, run, print the
/// error chain, and return the exit code (2 for bad arguments or scenario values).
pub fn role_main<A: clap::Args + clap::FromArgMatches>(
    name: &'static str,
    run: fn(&A) -> anyhow::Result<()>,
) -> std::process::ExitCode {
    let cmd = A::augment_args(clap::Command::new(name));
    let matches = cmd.get_matches();
    let args = match A::from_arg_matches(&matches) {
        Ok(a) => a,
        Err(e) => e.exit(),
    };
    let relay = crate::relay::Stdio::relay();
    let code = run_role(name, &args, run);
    relay.finish();
    code
}

/// Runs a role with signal handling and error reporting (shared by the role binaries
/// and `rotorloop role`).
pub fn run_role<A>(
    name: &str,
    args: &A,
    run: fn(&A) -> anyhow::Result<()>,
) -> std::process::ExitCode {
    crate::signals::install_signal_handlers();
    crate::ipc::quiet_iceoryx_logs();
    match run(args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("{name}: error: {e:#}");
            if is_usage_error(&e) {
                std::process::ExitCode::from(2)
            } else {
                std::process::ExitCode::FAILURE
            }
        }
    }
}
