//! `rotorloop-link`: the link gateway of one host (see the crate docs).

use clap::Parser;

/// Carries a run domain's services between this host and another over Zenoh.
#[derive(Debug, Parser)]
#[command(name = "rotorloop-link", version)]
struct Cli {
    #[command(flatten)]
    link: rotorloop_link::LinkArgs,
}

fn main() {
    let cli = Cli::parse();
    if let Err(e) = rotorloop_link::run(&cli.link) {
        eprintln!("link: error: {e:#}");
        let usage = e.downcast_ref::<rotorloop_link::ConfigError>().is_some();
        std::process::exit(if usage { 2 } else { 1 });
    }
}
