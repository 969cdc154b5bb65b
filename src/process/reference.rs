//! The `reference` process: runs the dummy body and publishes `R_d, Ω_d, Ω̇_d` up to
//! [`REFERENCE_LEAD`] ticks ahead of the newest state, so the controller never waits for
//! it. The samples also carry the dummy's integrator state: a restarted reference
//! continues from the last sample it published, bit for bit, as if it had never died.
//!
//! It reads only the tick and the flags of state samples, so it needs no validation.

use anyhow::Context;
use clap::Args;
use glam::DVec3;
use iceoryx2::prelude::ZeroCopySend;
use rotorloop_common::ipc::{REFERENCE_LEAD, Topic, Wait, now_ns, shutdown_requested};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::so3::to_row_major;
use rotorloop_common::wire::{FLAG_LAST, ReferenceSample, StateSample};
use rotorloop_reference::Reference;

use super::{PlantEnd, RoleArgs, corrupted, linger};

/// Samples a restarted reference can re-publish: its whole lead and history.
const RESUME_RING: usize = 2 * REFERENCE_LEAD as usize + 2;

/// The reference's resume slot: its last [`RESUME_RING`] published samples.
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("rotorloop::ReferenceResume_v3")]
#[repr(C)]
struct ReferenceResume {
    samples: [ReferenceSample; RESUME_RING],
    /// Newest tick stored + 1 (0: none).
    next: u64,
}

/// `reference` arguments.
#[derive(Debug, Clone, Args)]
pub struct ReferenceArgs {
    #[command(flatten)]
    pub role: RoleArgs,
    /// Fault injection: publish this tick's sample corrupted (`nan@TICK`, `inf@TICK`,
    /// `huge@TICK`, `skew@TICK`). Repeatable. Set by `rotorloop run --corrupt`.
    #[arg(long)]
    pub corrupt: Vec<super::Corrupt>,
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
    let slot = ResumeSlot::<ReferenceResume>::open(&domain, "reference").context("reference")?;

    let ticks = scenario.ticks();
    let dt = scenario.dt();
    let mut ring = slot.load().filter(|r| r.next > 0 && r.next <= ticks);
    let (mut generator, mut next) = match &ring {
        Some(r) => {
            let s = r.samples[((r.next - 1) as usize) % RESUME_RING];
            let x = s.body_state();
            let mut g = Reference::from_internal(
                scenario.reference,
                (x.r, DVec3::from_array(s.internal_h), DVec3::from_array(s.internal_p), x.theta),
                scenario.reference_torque,
            );
            g.step(s.tick as f64 * dt, dt);
            // What the dead predecessor published may be gone with its shared memory:
            // publish the stored window again (subscribers take repeats as repeats).
            let first = r.next.saturating_sub(RESUME_RING as u64);
            for tick in first..r.next {
                let again = r.samples[tick as usize % RESUME_RING];
                if again.tick == tick {
                    out.send(again, |x| x.publish_ns = now_ns())
                        .context("reference: re-publishing")?;
                }
            }
            eprintln!(
                "reference: resuming after tick {} from the samples published before a restart",
                s.tick
            );
            (g, r.next)
        }
        None => (Reference::for_scenario(&scenario), 0),
    };
    let mut window = ring.take().unwrap_or(ReferenceResume {
        samples: [ReferenceSample {
            tick: u64::MAX,
            t_s: 0.0,
            r_d_row_major: [0.0; 9],
            omega_d_rad_s: [0.0; 3],
            omega_d_dot_rad_s2: [0.0; 3],
            omega_rotor_rad_s: [0.0; 3],
            theta_rotor_rad: [0.0; 3],
            publish_ns: 0,
            internal_h: [0.0; 3],
            internal_p: [0.0; 3],
        }; RESUME_RING],
        next: 0,
    });
    let mut newest_state = next.saturating_sub(REFERENCE_LEAD + 1);
    // Test hook: a first incarnation starts publishing this late, so that the first
    // states reach the controller before any reference does.
    if next == 0 {
        if let Some(ms) =
            std::env::var("ROTORLOOP_TEST_REFERENCE_LATE_MS").ok().and_then(|v| v.parse().ok())
        {
            std::thread::sleep(std::time::Duration::from_millis(ms));
        }
    }
    let mut saw_last = false;
    let plant_end = PlantEnd::open(&domain).context("reference")?;
    let mut last_state_ns = now_ns();
    let mut published_batch = false;
    loop {
        while next <= ticks.min(newest_state + REFERENCE_LEAD) {
            let t = next as f64 * dt;
            let rd = generator.sample(t);
            let body = generator.body_state();
            let (_, h, p, _) = generator.internal();
            let sample = ReferenceSample {
                tick: next,
                t_s: t,
                r_d_row_major: to_row_major(&rd.r_d),
                omega_d_rad_s: rd.omega_d.to_array(),
                omega_d_dot_rad_s2: rd.omega_d_dot.to_array(),
                omega_rotor_rad_s: body.omega_r.to_array(),
                theta_rotor_rad: body.theta.to_array(),
                publish_ns: 0,
                internal_h: h.to_array(),
                internal_p: p.to_array(),
            };
            out.send(corrupted(&args.corrupt, sample), |s| s.publish_ns = now_ns())
                .context("reference: publishing")?;
            window.samples[next as usize % RESUME_RING] = sample;
            window.next = next + 1;
            generator.step(t, dt);
            next += 1;
            published_batch = true;
        }
        if published_batch {
            slot.store(&window); // once per batch: the window is a few KiB
            published_batch = false;
        }
        if saw_last || shutdown_requested() {
            break;
        }
        let deadline = now_ns() + 100_000_000;
        let got = states.wait_for(Wait::Event, deadline, |inbox| {
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
        if got.is_some() {
            last_state_ns = now_ns();
        } else if now_ns() - last_state_ns > 1_000_000_000 && plant_end.ended() {
            eprintln!("reference: the plant has ended the run; nothing left to publish");
            break;
        }
    }
    drop(states);
    linger(|| out.subscribers() == 0);
    Ok(())
}
