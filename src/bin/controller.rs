//! The `controller` process of the loop: a thin shell over `rotorloop_controller::process`.

fn main() -> std::process::ExitCode {
    rotorloop_common::role::role_main::<rotorloop_controller::process::args::ControllerArgs>(
        rotorloop_controller::ROLE,
        rotorloop_controller::process::run,
    )
}
