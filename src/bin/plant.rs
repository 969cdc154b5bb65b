//! The `plant` process of the loop: a thin shell over `rotorloop::process::plant`.

fn main() -> std::process::ExitCode {
    rotorloop::process::role_main::<rotorloop::process::plant::PlantArgs>(
        "plant",
        rotorloop::process::plant::run,
    )
}
