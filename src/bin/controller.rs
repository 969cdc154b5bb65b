//! The `controller` process of the loop: a thin shell over `rotorloop::process::controller`.

fn main() -> std::process::ExitCode {
    rotorloop::process::role_main::<rotorloop::process::controller::ControllerArgs>(
        "controller",
        rotorloop::process::controller::run,
    )
}
