//! The `monitor` process of the loop: a thin shell over `rotorloop_monitor::process`.

fn main() -> std::process::ExitCode {
    rotorloop_common::role::role_main::<rotorloop_monitor::process::args::MonitorArgs>(
        rotorloop_monitor::ROLE,
        rotorloop_monitor::process::run,
    )
}
