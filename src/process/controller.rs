//! The `controller` process: answers each state sample with rotor and body torques from
//! the geometric PID law, pairing it with the reference sample of the same tick.
//!
//! **Missing reference.** The reference is published ahead, so it is normally there when
//! the state arrives. When it is not (counted as a reference miss): in lockstep the
//! controller waits for it, so the run stays deterministic; in real time it holds the
//! last reference sample and propagates it (`R_d ← R_d exp(Δt Ω_d)`, `Ω_d` and `Ω̇_d`
//! held) for at most `--reference-hold-ticks` ticks; after that (or with no reference
//! yet at all, as when the state of tick 0 comes first) it answers with a
//! [`TORQUE_SKIPPED`] sample, so the plant holds its torque and then enters safe mode.
//!
//! **Rejected input.** Every state and reference sample is validated
//! ([`StateSample::validate`]): NaN, infinity, absurd magnitudes and attitudes off SO(3)
//! are rejected and counted. A rejected state is not controlled: the tick is answered
//! with a [`TORQUE_SKIPPED`] sample (zero torque, `ξ_I` untouched), which the plant
//! treats as a missing torque (hold, then safe mode), so lockstep runs on. A rejected
//! reference counts as a missing one, but is not waited for, even in lockstep: the last
//! good reference is propagated as above (or, with none yet, the tick is skipped).
//!
//! **Restart.** A controller started while its resume slot holds an unfinished run
//! continues bumplessly: the integral state `ξ_I` and the counters come from the last
//! torque sample it published. A state it has already answered (a restarted plant
//! re-publishes its last state) gets the same answer again, not a second integration.

use anyhow::Context;
use clap::Args;
use glam::DVec3;
use rotorloop_common::ReferenceState;
use rotorloop_common::ipc::{Topic, now_ns, shutdown_requested};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::so3::exp;
use rotorloop_common::wire::{
    FLAG_LAST, ReferenceSample, StateSample, TORQUE_SKIPPED, TorqueSample,
};
use rotorloop_controller::GeometricPid;

use super::{Mode, PlantEnd, RoleArgs, SeqCounter, corrupted, linger};

/// `controller` arguments.
#[derive(Debug, Clone, Args)]
pub struct ControllerArgs {
    #[command(flatten)]
    pub role: RoleArgs,
    /// Fault injection: publish this tick's sample corrupted (`nan@TICK`, `inf@TICK`,
    /// `huge@TICK`, `skew@TICK`). Repeatable. Set by `rotorloop run --corrupt`.
    #[arg(long)]
    pub corrupt: Vec<super::Corrupt>,
    /// Real time: ticks to propagate the last reference when it is missing.
    #[arg(long, allow_negative_numbers = true, default_value_t = 1000)]
    pub reference_hold_ticks: u64,
}

const RING: usize = 256;

/// A reference ring entry. Unboxed on purpose: the ring is allocated once, and boxing the
/// sample would allocate on every receive.
#[derive(Debug, Clone, Copy)]
#[allow(clippy::large_enum_variant)]
enum RefEntry {
    Empty,
    Valid(ReferenceSample),
    /// A sample of this tick arrived and was rejected.
    Rejected(u64),
}

/// Runs the controller until the plant's last tick or a termination signal.
pub fn run(args: &ControllerArgs) -> anyhow::Result<()> {
    let role = &args.role;
    let scenario = role.scenario()?;
    role.setup("controller");
    let domain = role.open_domain()?;
    let node = domain.node("controller").context("controller")?;
    let out = domain.outbox::<TorqueSample>(&node, Topic::Torque).context("controller")?;
    // Subscribe to the state last: the plant starts when it sees its state subscribers.
    let refs = domain
        .inbox::<ReferenceSample>(&node, Topic::Reference, 128, false)
        .context("controller")?;
    let states = domain
        .inbox::<StateSample>(&node, Topic::State, 8, role.wait.listens())
        .context("controller")?;
    let slot = ResumeSlot::<TorqueSample>::open(&domain, "controller").context("controller")?;
    let plant_end = PlantEnd::open(&domain).context("controller")?;

    let actuation = scenario.actuation();
    let ticks = scenario.ticks();
    let mut pid = GeometricPid::new(scenario.gains, scenario.controller_params(actuation))
        .with_limits(scenario.limits_for(actuation), scenario.anti_windup);
    let dt = scenario.dt();
    let lockstep = role.mode == Mode::Lockstep;
    let mut ring: Vec<RefEntry> = vec![RefEntry::Empty; RING];
    let (mut states_rejected, mut references_rejected) = (0u64, 0u64);
    let mut first_rejection_logged = false;
    let mut state_seq = SeqCounter::default();
    let mut reference_misses = 0u64;
    let mut skipped = 0u64;
    let mut published = 0u64;
    let mut last: Option<TorqueSample> = None;
    let mut last_ref: Option<ReferenceSample> = None;
    let mut held_refs = 0u64;
    if let Some(t) = slot.load().filter(|t| t.tick < ticks) {
        pid = pid.with_integral_state(DVec3::from_array(t.xi_i));
        published = t.published;
        reference_misses = t.reference_misses;
        skipped = t.states_skipped;
        states_rejected = t.states_rejected;
        references_rejected = t.references_rejected;
        state_seq = SeqCounter::resume(t.states_received, t.states_lost, t.tick);
        last = Some(t);
        eprintln!(
            "controller: resuming after tick {} with the integral state it last published",
            t.tick
        );
    }

    let drain_refs = |ring: &mut Vec<RefEntry>, rejected: &mut u64| -> anyhow::Result<()> {
        while let Some(r) = refs.take()? {
            ring[r.tick as usize % RING] = match r.validate() {
                Ok(()) => RefEntry::Valid(r),
                Err(_) => {
                    *rejected += 1;
                    RefEntry::Rejected(r.tick)
                }
            };
        }
        Ok(())
    };
    let lookup = |ring: &Vec<RefEntry>, k: u64| match ring[k as usize % RING] {
        RefEntry::Valid(r) if r.tick == k => Some(r),
        _ => None,
    };
    let rejected_at = |ring: &Vec<RefEntry>, k: u64| matches!(ring[k as usize % RING], RefEntry::Rejected(t) if t == k);
    // Test hook: a first-incarnation controller loans a torque sample at this tick and
    // stalls holding it, so that a test can kill it with the loan outstanding.
    let stall_at: Option<u64> = std::env::var("ROTORLOOP_TEST_STALL_WITH_LOAN_AT")
        .ok()
        .and_then(|v| v.parse().ok())
        .filter(|_| last.is_none());
    // Test hook: never answer the state of this tick, as when a newer state superseded it
    // in the inbox (the newest-only policy under load).
    let skip_at: Option<u64> =
        std::env::var("ROTORLOOP_TEST_SKIP_STATE_AT").ok().and_then(|v| v.parse().ok());
    let mut last_state_ns = now_ns();
    let mut plant_gone = false;

    loop {
        let deadline = now_ns() + 100_000_000;
        let state = states.wait_for(role.wait, deadline, |inbox| {
            let mut newest: Option<(StateSample, u64)> = None;
            while let Some(s) = inbox.take()? {
                state_seq.see(s.tick);
                if newest.is_some() {
                    skipped += 1;
                }
                newest = Some((s, now_ns()));
            }
            Ok(newest)
        })?;
        let Some((state, recv_ns)) = state else {
            if shutdown_requested() {
                break;
            }
            if now_ns() - last_state_ns > 1_000_000_000 {
                if plant_end.ended() {
                    eprintln!("controller: the plant has ended the run; nothing left to answer");
                    break;
                }
                if !plant_gone {
                    eprintln!("controller: no state from the plant for 1 s (plant gone?)");
                    plant_gone = true;
                }
            }
            continue;
        };
        last_state_ns = now_ns();
        if plant_gone {
            eprintln!("controller: plant back at tick {}", state.tick);
            plant_gone = false;
        }
        let k = state.tick;
        if stall_at == Some(k) {
            out.stall_holding_a_loan()?;
            break;
        }
        if skip_at == Some(k) && state.flags & FLAG_LAST == 0 {
            skipped += 1;
            continue;
        }
        if let Some(prev) = last.filter(|t| t.tick >= k) {
            // Already answered (a restarted plant re-published it): same answer again.
            if prev.tick == k {
                out.send(prev, |s| s.publish_ns = now_ns()).context("controller: re-publishing")?;
            }
            continue;
        }
        let state_fault = state.validate().err();
        if let Some(f) = state_fault {
            states_rejected += 1;
            if !first_rejection_logged {
                eprintln!("controller: rejected the state of tick {k}: {f} (skipping; counted)");
                first_rejection_logged = true;
            }
        }
        drain_refs(&mut ring, &mut references_rejected)?;
        let mut rd = lookup(&ring, k).map(|r| r.reference_state());
        if rd.is_none() && state_fault.is_none() {
            reference_misses += 1;
            if lockstep {
                while rd.is_none() && !rejected_at(&ring, k) && !shutdown_requested() {
                    std::thread::sleep(std::time::Duration::from_micros(100));
                    drain_refs(&mut ring, &mut references_rejected)?;
                    rd = lookup(&ring, k).map(|r| r.reference_state());
                }
            }
            if let Some(r) = last_ref.filter(|r| rd.is_none() && r.tick < k) {
                held_refs += 1;
                if held_refs <= args.reference_hold_ticks {
                    // Hold and propagate the last reference sample.
                    let x = r.reference_state();
                    let gap = (k - r.tick) as f64 * dt;
                    rd = Some(ReferenceState { r_d: x.r_d * exp(gap * x.omega_d), ..x });
                }
            }
        } else {
            held_refs = 0;
        }
        if let Some(r) = lookup(&ring, k) {
            last_ref = Some(r);
        }
        let skip = match rd {
            _ if state_fault.is_some() => true,
            None if shutdown_requested() => break,
            // No reference to track (rejected, gone for longer than the hold, or not yet
            // arrived for the first tick): a skipped answer, which the plant treats as a
            // missing torque (hold, then safe mode). Answering keeps the count exact:
            // every state taken is answered or counted skipped.
            None => true,
            Some(_) => false,
        };
        let out_k = match rd {
            Some(rd) if !skip => pid.step(&state.body_state(), &rd, dt),
            _ => Default::default(),
        };
        published += 1;
        let sample = TorqueSample {
            tick: k,
            rotor_torque_nm: out_k.rotor_torque.to_array(),
            body_torque_nm: out_k.body_torque.to_array(),
            xi_i: pid.integral_state().to_array(),
            state_recv_ns: recv_ns,
            publish_ns: 0,
            states_received: state_seq.received,
            states_lost: state_seq.lost,
            states_skipped: skipped,
            reference_misses,
            published,
            states_rejected,
            references_rejected,
            flags: if skip { TORQUE_SKIPPED } else { 0 },
        };
        // Slot first: killed between the two, the restart re-sends this very answer when
        // the plant asks again; the other order would resume with a stale ξ_I.
        slot.store(&sample);
        out.send(corrupted(&args.corrupt, sample), |s| s.publish_ns = now_ns())
            .context("controller: publishing torque")?;
        last = Some(sample);
        if state.flags & FLAG_LAST != 0 {
            break;
        }
    }
    drop(states);
    drop(refs);
    linger(|| out.subscribers() == 0);
    Ok(())
}
