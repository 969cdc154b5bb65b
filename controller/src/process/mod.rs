//! The `controller` process: a thin shell over [`TorqueAnswers`] and [`ReferencePairing`]
//! (the rules, in [`crate::policy`]). It answers the newest state sample with the law's
//! torques, paired with the reference sample of the same tick (waited for only in
//! lockstep), and stops after the plant's last tick (or, restarted after the end, when
//! the plant's resume slot says the run is over).

pub mod args;
mod ports;

use rotorloop_common::clock::now_ns;
use rotorloop_common::role::{UsageError, args::Mode, end::linger_publisher};
use rotorloop_common::signals::shutdown_requested;
use rotorloop_common::wire::{FLAG_LAST, StateSample};

use crate::ROLE;
use crate::law::AnyLaw;
use crate::policy::{DelayedSends, ReferencePairing, TorqueAnswers};
use ports::Ports;

/// Runs the controller until the plant's last tick or a termination signal.
pub fn run(args: &args::ControllerArgs) -> anyhow::Result<()> {
    let (role, scenario) = (&args.role, args.role.scenario()?);
    let law = AnyLaw::for_scenario(&scenario, scenario.actuation()).map_err(UsageError::from)?;
    role.setup(ROLE);
    let mut ports = Ports::open(role, scenario.ticks())?;
    let dt = scenario.dt();
    let mut answers = TorqueAnswers::new(law).leaving_unanswered(role.hooks.test_skip_state_at);
    let mut pairing = ReferencePairing::new(args.reference_hold_ticks, dt, scenario.ticks());
    if let Some(r) = ports.slot.load_for(ROLE, scenario.ticks()) {
        answers.resume(&r);
        pairing.resume(&r.last);
        eprintln!("controller: resuming after tick {} with its law's last state", r.last.tick);
    }
    let hooks = role.hooks.first_run(answers.last().is_none()); // the tests' hooks act once
    let mut sends = DelayedSends::new(args.inject_delay.clone());
    let mut state = StateSample::of(0, 0.0, &scenario.plant_init); // each wait overwrites it
    loop {
        ports.send_due(&mut sends, &args.corrupt, false)?;
        let until = sends.next_due_ns().unwrap_or(u64::MAX).min(now_ns() + 100_000_000);
        let warm = ports::warm(&pairing, &hooks, &sends, &args.corrupt);
        let Some(recv) = ports.newest_state(&mut answers, role.wait, until, &mut state, warm)?
        else {
            if shutdown_requested() || ports.plant.run_over() {
                break;
            }
            continue;
        };
        let k = state.tick;
        if hooks.test_stall_with_loan_at == Some(k) {
            ports.out.stall_holding_a_loan()?;
            break;
        }
        let Some(fault) = ports.act_on(answers.decide(&state), k)? else { continue };
        let validated = now_ns();
        let rd = ports.pair(&mut pairing, k, fault.is_none(), role.mode == Mode::Lockstep)?;
        if rd.is_none() && fault.is_none() && shutdown_requested() {
            break;
        }
        let stamps = (validated, now_ns(), now_ns as fn() -> u64); // paired, computed later
        // Into the resume slot, sent from there. Slot first: killed between the two, a
        // restart re-sends this answer (not a stale law)
        let (received, tracked) = ((&state, recv), (rd.as_ref(), &pairing));
        ports.slot.store_with(|r| answers.answer_into(r, received, tracked, dt, stamps));
        let sample = &ports.slot.stored().last;
        hooks.stop_before_send(k);
        if !sends.holds_back(sample, state.t_s, sample.computed_ns) {
            ports.publish(sample, &args.corrupt)?;
        }
        answers.gave(sample);
        ports.references_ahead(&mut pairing)?;
        if state.flags & FLAG_LAST != 0 {
            break;
        }
    }
    ports.send_due(&mut sends, &args.corrupt, true)?; // the last answers held back
    drop((ports.states, ports.refs)); // the publisher lingers alone
    linger_publisher(&ports.out, role);
    Ok(())
}
