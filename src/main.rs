//! The `rotorloop` binary: a thin shell over the library (see `rotorloop::cli`).

fn main() -> std::process::ExitCode {
    rotorloop::cli::main()
}
