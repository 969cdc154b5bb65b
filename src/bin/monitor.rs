//! The `monitor` process of the loop: a thin shell over `rotorloop::process::monitor`.

fn main() -> std::process::ExitCode {
    rotorloop::process::role_main::<rotorloop::process::monitor::MonitorArgs>(
        "monitor",
        rotorloop::process::monitor::run,
    )
}
