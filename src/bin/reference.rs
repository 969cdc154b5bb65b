//! The `reference` process of the loop: a thin shell over `rotorloop::process::reference`.

fn main() -> std::process::ExitCode {
    rotorloop::process::role_main::<rotorloop::process::reference::ReferenceArgs>(
        "reference",
        rotorloop::process::reference::run,
    )
}
