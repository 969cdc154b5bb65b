//! The `controller` process: a thin shell over [`TorqueAnswers`] and [`ReferencePairing`]
//! (the rules, in [`crate::policy`]). It answers the newest state sample with the law's
//! torques, pairing it with the reference sample of the same tick (waiting for it only in
//! lockstep), and stops after the plant's last tick (or, restarted after the end, when the
//! plant's resume slot says the run is over).

mod args;

use anyhow::Context;
use rotorloop_common::ipc::{Inbox, Topic, now_ns, shutdown_requested};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::role::{Mode, PlantEnd, corrupted, linger, test_hook};
use rotorloop_common::wire::{FLAG_LAST, ReferenceSample, StateSample, TorqueSample};

pub use args::ControllerArgs;

use crate::GeometricPid;
use crate::policy::{Decision, ReferencePairing, TorqueAnswers};

/// Runs the controller until the plant's last tick or a termination signal.
pub fn run(args: &ControllerArgs) -> anyhow::Result<()> {
    let (role, scenario) = (&args.role, args.role.scenario()?);
    role.setup("controller");
    let domain = role.open_domain()?;
    let node = domain.node("controller").context("controller")?;
    let out = domain.outbox::<TorqueSample>(&node, Topic::Torque).context("controller")?;
    // Subscribe to the state last: the plant starts when it sees its state subscribers.
    let refs = domain.inbox::<ReferenceSample>(&node, Topic::Reference, 128, false);
    let (refs, wait) = (refs.context("controller")?, role.wait);
    let states = domain
        .inbox::<StateSample>(&node, Topic::State, 8, wait.listens())
        .context("controller")?;
    let slot = ResumeSlot::<TorqueSample>::open(&domain, "controller").context("controller")?;
    let plant_end = PlantEnd::open(&domain).context("controller")?;
    let (a, dt) = (scenario.actuation(), scenario.dt());
    let pid = GeometricPid::new(scenario.gains, scenario.controller_params(a))
        .with_limits(scenario.limits_for(a), scenario.anti_windup);
    let (mut answers, mut pairing) =
        (TorqueAnswers::new(pid), ReferencePairing::new(args.reference_hold_ticks, dt));
    if let Some(t) = slot.load().filter(|t| t.tick < scenario.ticks()) {
        answers.resume(&t);
        pairing.resume(t.reference_misses, t.references_rejected);
        eprintln!(
            "controller: resuming after tick {} with the integral state it last published",
            t.tick
        );
    }
    // Test hooks: stall holding a loan at this tick (first incarnation only); never answer
    // the state of that tick, as when a newer state superseded it under load.
    let stall_at =
        test_hook("ROTORLOOP_TEST_STALL_WITH_LOAN_AT").filter(|_| answers.last().is_none());
    let skip_at = test_hook("ROTORLOOP_TEST_SKIP_STATE_AT");
    let (mut last_state_ns, mut plant_gone, mut rejection_logged) = (now_ns(), false, false);
    loop {
        let state = states.wait_for(wait, now_ns() + 100_000_000, |inbox| {
            let mut newest: Option<(StateSample, u64)> = None;
            while let Some(s) = inbox.take()? {
                answers.take(&s, newest.is_some());
                newest = Some((s, now_ns()));
            }
            Ok(newest)
        })?;
        let Some((state, recv_ns)) = state else {
            let silent = now_ns() - last_state_ns > 1_000_000_000;
            if shutdown_requested() {
                break;
            }
            if silent && plant_end.ended() {
                eprintln!("controller: the plant has ended the run; nothing left to answer");
                break;
            }
            if silent && !std::mem::replace(&mut plant_gone, true) {
                eprintln!("controller: no state from the plant for 1 s (plant gone?)");
            }
            continue;
        };
        last_state_ns = now_ns();
        if std::mem::take(&mut plant_gone) {
            eprintln!("controller: plant back at tick {}", state.tick);
        }
        let k = state.tick;
        if stall_at == Some(k) {
            out.stall_holding_a_loan()?;
            break;
        }
        if skip_at == Some(k) && state.flags & FLAG_LAST == 0 {
            answers.skip();
            continue;
        }
        let fault = match answers.decide(&state) {
            Decision::AnswerAgain(prev) => {
                out.send(prev, |s| s.publish_ns = now_ns()).context("controller: re-publishing")?;
                continue;
            }
            Decision::Ignore => continue,
            Decision::Answer { fault } => fault,
        };
        if let Some(f) = fault.filter(|_| !std::mem::replace(&mut rejection_logged, true)) {
            eprintln!("controller: rejected the state of tick {k}: {f} (skipping; counted)");
        }
        drain(&refs, &mut pairing)?;
        let mut found = pairing.begin(k, fault.is_none());
        let missed = found.is_none() && fault.is_none();
        while missed
            && role.mode == Mode::Lockstep
            && found.is_none()
            && !pairing.rejected_at(k)
            && !shutdown_requested()
        {
            std::thread::sleep(std::time::Duration::from_micros(100));
            drain(&refs, &mut pairing)?;
            found = pairing.lookup(k);
        }
        let rd = pairing.finish(k, found, missed).filter(|_| fault.is_none());
        if rd.is_none() && fault.is_none() && shutdown_requested() {
            break;
        }
        let sample = answers.answer(&state, recv_ns, rd.as_ref(), &pairing, dt);
        // Slot first: killed between the two, the restart re-sends this very answer when
        // the plant asks again; the other order would resume with a stale ξ_I.
        slot.store(&sample);
        out.send(corrupted(&args.corrupt, sample), |s| s.publish_ns = now_ns())
            .context("controller: publishing torque")?;
        if state.flags & FLAG_LAST != 0 {
            break;
        }
    }
    drop((states, refs));
    linger(|| out.subscribers() == 0);
    Ok(())
}

/// Takes every reference sample that arrived.
fn drain(refs: &Inbox<ReferenceSample>, pairing: &mut ReferencePairing) -> anyhow::Result<()> {
    while let Some(r) = refs.take()? {
        pairing.take(r);
    }
    Ok(())
}
