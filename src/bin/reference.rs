//! The `reference` process of the loop: a thin shell over `rotorloop_reference::process`.

fn main() -> std::process::ExitCode {
    rotorloop_common::role::role_main::<rotorloop_reference::process::args::ReferenceArgs>(
        rotorloop_reference::ROLE,
        rotorloop_reference::process::run,
    )
}
