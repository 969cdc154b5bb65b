//! The `plant` process of the loop: a thin shell over `rotorloop_plant::process`.

fn main() -> std::process::ExitCode {
    rotorloop_common::role::role_main::<rotorloop_plant::process::args::PlantArgs>(
        rotorloop_plant::ROLE,
        rotorloop_plant::process::run,
    )
}
