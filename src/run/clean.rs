//! `rotorloop clean`: what dead processes of a domain left in shared memory removed, and
//! the flight records of a launcher that did not end normally named (kept: they are that
//! run's record, for `rotorloop recover`).

use rotorloop_common::role::UsageError;

/// `rotorloop clean` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct CleanArgs {
    /// The run domain.
    #[arg(long, default_value = "default")]
    pub domain: String,
    /// The host whose space to clean (`--host` of the roles), if any.
    #[arg(long)]
    pub host: Option<String>,
}

/// Cleans the domain's dead nodes (and, when none of its processes is alive, its last
/// iceoryx2 file), and names its staged flight records if a launcher left them.
pub fn run(a: &CleanArgs) -> anyhow::Result<()> {
    let (domain, host) = (&a.domain, a.host.as_deref());
    let d = rotorloop_common::ipc::domain::Domain::on_host(domain, host)
        .map_err(|e| UsageError(e.to_string()))?;
    let (cleaned, alive) = d.cleanup()?;
    let on = host.map(|h| format!(" on host {h}")).unwrap_or_default();
    println!("domain {domain}{on}: {cleaned} dead node(s) cleaned, {alive} alive");
    // A launcher that did not end normally left its run's flight records on tmpfs: they
    // are the record of that run, so they are kept, and named.
    let staged = rotorloop_common::flight::staging_dir(domain);
    if let Some(staged) = staged.filter(|d| alive == 0 && mine(d)) {
        let how = match crate::run::recover::run_dir_of(&staged) {
            Some(out) => format!("`rotorloop recover {}` makes its report", out.display()),
            None => "move them into OUT/flight by hand".to_owned(),
        };
        println!(
            "flight records of domain {domain} kept in {} (its launcher did not move them \
             into the run directory): {how}",
            staged.display()
        );
    }
    Ok(())
}

/// Whether `d` is this user's own private directory: only that is a run's record; another
/// user's (or a link) is named, never trusted for where to recover.
fn mine(d: &std::path::Path) -> bool {
    let meta = std::fs::symlink_metadata(d);
    match meta.map(|m| rotorloop_common::private::check(d, &m, true)) {
        Ok(Err(f)) => {
            eprintln!("warning: not this user's records, left alone: {f}");
            false
        }
        Ok(Ok(())) => true,
        Err(_) => false,
    }
}
