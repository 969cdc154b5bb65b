//! The `controller` process: a thin shell over [`TorqueAnswers`] and [`ReferencePairing`]
//! (the rules, in [`crate::policy`]). It answers the newest state sample with the law's
//! torques, paired with the reference sample of the same tick (waited for only in
//! lockstep), and stops after the plant's last tick (or, restarted after the end, when
//! the plant's resume slot says the run is over).

mod args;

use anyhow::Context;
use rotorloop_common::ipc::{Topic, now_ns, shutdown_requested};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::role::{Mode, PlantWatch, corrupted, linger, test_hook};
use rotorloop_common::wire::{FLAG_LAST, ReferenceSample, StateSample, TorqueSample};

pub use args::ControllerArgs;

use crate::policy::{Decision, DelayedSends, ReferencePairing, TorqueAnswers};

/// Runs the controller until the plant's last tick or a termination signal.
pub fn run(args: &ControllerArgs) -> anyhow::Result<()> {
    let (role, scenario) = (&args.role, args.role.scenario()?);
    role.setup("controller");
    let domain = role.open_domain()?;
    let node = domain.node("controller").context("controller")?;
    let out = domain.outbox::<TorqueSample>(&node, Topic::Torque).context("controller")?;
    // Subscribe to the state last: the plant starts when it sees its state subscribers.
    let refs = domain.inbox::<ReferenceSample>(&node, Topic::Reference, 128, false);
    let refs = refs.context("controller")?;
    let states = domain.inbox::<StateSample>(&node, Topic::State, 8, role.wait.listens());
    let states = states.context("controller")?;
    let slot = ResumeSlot::<TorqueSample>::open(&domain, "controller").context("controller")?;
    let mut plant = PlantWatch::open(&domain, "controller").context("controller")?;
    let dt = scenario.dt();
    let skip_at = test_hook("ROTORLOOP_TEST_SKIP_STATE_AT");
    let mut answers = TorqueAnswers::for_scenario(&scenario).leaving_unanswered(skip_at);
    let mut pairing = ReferencePairing::new(args.reference_hold_ticks, dt);
    if let Some(t) = slot.load().filter(|t| t.tick < scenario.ticks()) {
        answers.resume(&t);
        pairing.resume(&t);
        eprintln!("controller: resuming after tick {} with its last integral state", t.tick);
    }
    // Test hook: a first incarnation stalls holding a loan at this tick, to be killed so.
    let stall_at =
        test_hook("ROTORLOOP_TEST_STALL_WITH_LOAN_AT").filter(|_| answers.last().is_none());
    let mut sends = DelayedSends::new(args.inject_delay.clone());
    let send = |t: TorqueSample| out.send(corrupted(&args.corrupt, t), |s| s.publish_ns = now_ns());
    loop {
        while let Some(t) = sends.due(now_ns()) {
            send(t).context("controller: publishing a delayed torque")?;
        }
        let until = sends.next_due_ns().unwrap_or(u64::MAX).min(now_ns() + 100_000_000);
        let state = states.wait_for(role.wait, until, |inbox| {
            let mut newest: Option<(StateSample, u64)> = None;
            inbox.drain(|s| {
                answers.take(&s, newest.is_some());
                newest = Some((s, now_ns()));
            })?;
            Ok(newest)
        })?;
        let Some((state, recv_ns)) = state else {
            if shutdown_requested() || plant.run_over() {
                break;
            }
            continue;
        };
        let k = state.tick;
        plant.saw_state(k);
        if stall_at == Some(k) {
            out.stall_holding_a_loan()?;
            break;
        }
        let fault = match answers.decide(&state) {
            Decision::AnswerAgain(prev) => {
                out.send(prev, |s| s.publish_ns = now_ns()).context("controller: re-publishing")?;
                continue;
            }
            Decision::Ignore => continue,
            Decision::Answer { fault: Some(f), first_rejection: true } => {
                eprintln!("controller: rejected the state of tick {k}: {f} (skipping; counted)");
                Some(f)
            }
            Decision::Answer { fault, .. } => fault,
        };
        refs.drain(|r| pairing.take(r))?;
        let lockstep = role.mode == Mode::Lockstep;
        let rd = pairing.pair(k, fault.is_none(), lockstep, |p| {
            std::thread::sleep(std::time::Duration::from_micros(100));
            refs.drain(|r| p.take(r))?;
            Ok(!shutdown_requested())
        })?;
        if rd.is_none() && fault.is_none() && shutdown_requested() {
            break;
        }
        let sample = answers.answer(&state, recv_ns, rd.as_ref(), &pairing, dt);
        // Slot first: killed between the two, the restart re-sends this very answer when
        // the plant asks again; the other order would resume with a stale ξ_I.
        slot.store(&sample);
        if let Some(t) = sends.hold(sample, state.t_s, now_ns()) {
            send(t).context("controller: publishing torque")?;
        }
        if state.flags & FLAG_LAST != 0 {
            break;
        }
    }
    while let Some(due) = sends.next_due_ns() {
        // The last answers still held back go out when due.
        std::thread::sleep(std::time::Duration::from_nanos(due.saturating_sub(now_ns())));
        while let Some(t) = sends.due(now_ns()) {
            send(t).context("controller: publishing a delayed torque")?;
        }
    }
    drop((states, refs));
    linger(|| out.subscribers() == 0);
    Ok(())
}
