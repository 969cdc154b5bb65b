//! `rotorloop-link`: the link gateway of one host (see the crate docs).

use clap::Parser;

/// Carries a run domain's services between this host and another over Zenoh.
#[derive(Debug, Parser)]
#[command(name = "rotorloop-link", version)]
struct Cli {
    #[command(flatten)]
    link: rotorloop_link::config::LinkArgs,
}

fn main() {
    let cli = Cli::parse();
    // Output that nobody reads never stops the gateway (see `relay`).
    let relay = rotorloop_common::relay::Stdio::relay();
    let code = match rotorloop_link::gateway::run(&cli.link) {
        Ok(()) => 0,
        Err(e) => {
            eprintln!("link: error: {e:#}");
            let usage = e.downcast_ref::<rotorloop_link::config::ConfigError>().is_some();
            if usage { 2 } else { 1 }
        }
    };
    relay.finish();
    std::process::exit(code);
}
