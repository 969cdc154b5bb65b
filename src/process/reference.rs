//! The `reference` process: runs the dummy body and publishes `R_d, Ω_d, Ω̇_d` up to
//! [`REFERENCE_LEAD`] ticks ahead of the newest state, so the controller never waits for
//! it. The samples also carry the dummy's rotor state, enough to resume it.

use anyhow::Context;
use clap::Args;
use rotorloop_common::ipc::{REFERENCE_LEAD, Topic, Wait, now_ns, shutdown_requested};
use rotorloop_common::so3::to_row_major;
use rotorloop_common::wire::{FLAG_LAST, ReferenceSample, StateSample};
use rotorloop_reference::Reference;

use super::{RoleArgs, linger};

/// `reference` arguments.
#[derive(Debug, Clone, Args)]
pub struct ReferenceArgs {
    #[command(flatten)]
    pub role: RoleArgs,
}

/// Runs the reference generator until the plant's last tick or a termination signal.
pub fn run(args: &ReferenceArgs) -> anyhow::Result<()> {
    let role = &args.role;
    let scenario = role.scenario()?;
    role.setup("reference");
    let domain = role.open_domain()?;
    let node = domain.node("reference").context("reference")?;
    let out = domain.outbox::<ReferenceSample>(&node, Topic::Reference).context("reference")?;
    // Off the hot path: always block on events, whatever --wait says, so a spinning
    // loop does not get a third busy process.
    let states = domain.inbox::<StateSample>(&node, Topic::State, 8, true).context("reference")?;

    let h = scenario.plant_init.spatial_momentum(&scenario.plant);
    let mut generator = Reference::matched(
        scenario.reference,
        scenario.reference_attitude,
        scenario.reference_omega,
        scenario.reference_torque,
        h,
    );
    let ticks = scenario.ticks();
    let dt = scenario.dt();
    let mut next = 0u64;
    let mut newest_state = 0u64;
    let mut saw_last = false;
    loop {
        while next <= ticks.min(newest_state + REFERENCE_LEAD) {
            let t = next as f64 * dt;
            let rd = generator.sample(t);
            let body = generator.body_state();
            let sample = ReferenceSample {
                tick: next,
                t_s: t,
                r_d_row_major: to_row_major(&rd.r_d),
                omega_d_rad_s: rd.omega_d.to_array(),
                omega_d_dot_rad_s2: rd.omega_d_dot.to_array(),
                omega_rotor_rad_s: body.omega_r.to_array(),
                theta_rotor_rad: body.theta.to_array(),
                publish_ns: 0,
            };
            out.send(sample, |s| s.publish_ns = now_ns()).context("reference: publishing")?;
            generator.step(t, dt);
            next += 1;
        }
        if saw_last || shutdown_requested() {
            break;
        }
        let deadline = now_ns() + 100_000_000;
        states.wait_for(Wait::Event, deadline, |inbox| {
            let mut any = None;
            while let Some(s) = inbox.take()? {
                newest_state = newest_state.max(s.tick);
                saw_last |= s.flags & FLAG_LAST != 0;
                any = Some(());
            }
            if any.is_none() {
                out.update_connections();
            }
            Ok(any)
        })?;
    }
    drop(states);
    linger(|| out.subscribers() == 0);
    Ok(())
}
