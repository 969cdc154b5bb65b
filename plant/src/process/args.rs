//! `plant` arguments (the same for the `plant` binary and `rotorloop role plant`).

use clap::Args;
use rotorloop_common::role::args::RoleArgs;
use rotorloop_common::role::inject::Corrupt;

use crate::actuator::ActuationDelay;

/// What the world's clock does while the simulator is late (`--plant-stall`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum PlantStall {
    /// It goes on: a stall of the plant process enters the physics as a tick without
    /// control.
    #[default]
    Hold,
    /// It stands still: only the loop after the plant's publish shapes the physics.
    Pause,
}

impl std::fmt::Display for PlantStall {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Hold => "hold",
            Self::Pause => "pause",
        })
    }
}

/// `plant` arguments.
#[derive(Debug, Clone, Args)]
pub struct PlantArgs {
    /// What every role takes (scenario, mode, domain, wait, core, records).
    #[command(flatten)]
    pub role: RoleArgs,
    /// Fault injection: publish this tick's sample corrupted (`nan@TICK`, `inf@TICK`,
    /// `huge@TICK`, `skew@TICK`). Repeatable. Set by `rotorloop run --corrupt`.
    #[arg(long)]
    pub corrupt: Vec<Corrupt>,
    /// Wait for this many subscribers to the state before tick 0 (controller and
    /// reference; 3 with a monitor that must see every tick), 0 to 64.
    #[arg(long, allow_hyphen_values = true, default_value_t = 2,
          value_parser = rotorloop_common::input::whole_in(0usize, 64, "subscribers"))]
    pub subscribers: usize,
    /// In real time, sleep until this many µs before each grid time and spin the rest,
    /// 0 to 1000000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 0,
          value_parser = rotorloop_common::role::args::spin_us())]
    pub spin_before_tick_us: u64,
    /// Real time: ticks to hold the last torque without a fresh one before safe mode, 0 to
    /// 1000000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 50,
          value_parser = rotorloop_common::role::args::hold_ticks())]
    pub hold_ticks: u64,
    /// When a torque takes effect: `measured` (when it arrives; in lockstep at its own
    /// tick's time), `0` (at the start of the tick it arrives in: the plain zero-order
    /// hold), or SECONDS after its own tick's time (a fixed delay of any length, and never
    /// before it arrives).
    #[arg(long, default_value = "measured", allow_hyphen_values = true)]
    pub actuation_delay: ActuationDelay,
    /// Real time, when the simulator wakes more than a quarter tick late: `hold` (the
    /// world's clock went on: the torque in force acted on the body all that time) or
    /// `pause` (the world's clock stood still: the grid moves on from the wake).
    #[arg(long, default_value = "hold")]
    pub plant_stall: PlantStall,
    /// Lockstep: stop (SIGSTOP) right after publishing each of these ticks, until the
    /// launcher continues the plant, so that the faults due there land at that tick
    /// (`rotorloop run --fault`; `process::gate`). Comma-separated. Set by the launcher.
    #[arg(long, hide = true, value_delimiter = ',')]
    pub gate_ticks: Vec<u64>,
    /// The tick loop without the gate's check (as before the gate), to measure what the
    /// gate costs (`rotorloop bench --before-after gate`); refused with `--gate-ticks`.
    #[arg(long, hide = true, conflicts_with = "gate_ticks")]
    pub no_gate: bool,
    /// Also record sense-to-actuate in the plant itself and write
    /// `DIR/plant_sense_to_actuate.hgrm` at the end (works without a monitor).
    #[arg(long)]
    pub latency_out: Option<std::path::PathBuf>,
}
