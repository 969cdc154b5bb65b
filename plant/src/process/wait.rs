//! The shell's ports and its per-tick helpers: the torque wait (which also connects late
//! joiners and says when the controller seems gone), the messages a settled tick is
//! worth, and the plant's own sense-to-actuate histogram.

use anyhow::Context;
use hdrhistogram::Histogram;
use rotorloop_common::clock::now_ns;
use rotorloop_common::flight::{FlightRecorder, Stream, ring_wraps};
use rotorloop_common::graph::Topic;
use rotorloop_common::hgrm::write_hgrm_file;
use rotorloop_common::ipc::ports::{Inbox, Outbox, RoleNode};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::role::args::{Mode, RoleArgs};
use rotorloop_common::role::inject::{Corrupt, corrupted};
use rotorloop_common::wire::{Refusals, SendCost, StateSample, TorqueSample};

use crate::ROLE;
use crate::policy::{Answer, PlantTicker, Settled};

/// What the plant opens: its state publisher, torque subscriber and resume slot, and its
/// flight recorders (every state published, every torque received).
pub(super) struct Ports {
    pub states: Outbox<StateSample>,
    pub torques: Inbox<TorqueSample>,
    pub slot: ResumeSlot<StateSample>,
    /// The refusals by kind, stored as they happen ([`Refusals`]).
    pub refusals: ResumeSlot<Refusals>,
    pub states_flight: FlightRecorder<StateSample>,
    torques_flight: FlightRecorder<TorqueSample>,
    /// Lockstep with rings the launcher moves: wait for it before coming round (off once
    /// it gave up).
    mover_gate: std::cell::Cell<bool>,
    _node: RoleNode,
}

/// The longest lockstep waits for the launcher's mover before it goes on without it.
const MOVER_WAIT: std::time::Duration = std::time::Duration::from_secs(60);

impl Ports {
    pub fn open(role: &RoleArgs, ticks: u64) -> anyhow::Result<Self> {
        let domain = role.open_domain()?;
        let states_flight = role.flight(Stream::PlantState, ticks, ROLE);
        let torques_flight = role.flight(Stream::PlantTorque, ticks, ROLE);
        let node = domain.node(ROLE).context(ROLE)?;
        let states = domain.outbox::<StateSample>(&node, Topic::State).context(ROLE)?;
        let torques = domain.inbox::<TorqueSample>(&node, Topic::Torque, 16, role.wait.listens());
        let slot = ResumeSlot::<StateSample>::open(&domain, ROLE).context(ROLE)?;
        let refusals = ResumeSlot::<Refusals>::open(&domain, Refusals::SLOT).context(ROLE)?;
        let torques = torques.context(ROLE)?;
        let wraps = ring_wraps(ticks, states_flight.capacity());
        let mover_gate = (role.flight_moved && role.mode == Mode::Lockstep && wraps).into();
        Ok(Self {
            states,
            torques,
            slot,
            refusals,
            states_flight,
            torques_flight,
            mover_gate,
            _node: node,
        })
    }

    /// Lockstep, before publishing tick `k`: waits until the launcher has moved the
    /// flight records' half that `k` would let a writer come round to (`common::flight`).
    /// Lockstep is not about time, and a mover slowed by writeback (seen under the repeat
    /// harness) must not lose records; real time never waits.
    pub fn hold_for_mover(&self, k: u64) {
        if self.mover_gate.get() && self.states_flight.wait_for_mover(k, MOVER_WAIT) {
            self.mover_gate.set(false);
            eprintln!(
                "plant: the launcher moved no flight records for {} s before tick {k}; going \
                 on without waiting (records it did not move in time are lost, and counted)",
                MOVER_WAIT.as_secs()
            );
        }
    }
}

/// The state of tick `k` (due at `deadline`; 0 in lockstep), without its wake and
/// publish stamps: as the plant has it (for the resume slot) and as it is published
/// (corrupted where `--corrupt` says so), the latter written into a loaned sample.
pub(super) struct Made {
    state: StateSample,
    published: StateSample,
}

/// Makes the state of tick `k`: before the plant sleeps to the tick (the default), so
/// that only the resume slot, the stamps and the send are left between the wake and the
/// publish (`--plain-hot-path`: made after the wake, as before).
pub(super) fn made(
    ports: &Ports,
    plant: &PlantTicker,
    k: u64,
    deadline: u64,
    corrupt: &[Corrupt],
) -> anyhow::Result<Made> {
    let state = plant.state_sample(k, deadline, 0);
    let published = corrupted(corrupt, state);
    ports.states.prewrite(published).context("plant: loaning the state's sample")?;
    Ok(Made { state, published })
}

/// Publishes the state [`made`] for a tick with its stamps (due at `deadline`, woken at
/// `woke`, and what the previous publish cost), records it, and notes its publish time
/// for the plant's own sense-to-actuate. Returns what this publish cost.
pub(super) fn publish(
    ports: &Ports,
    made: Made,
    (deadline, woke, prev): (u64, u64, SendCost),
    s2a: &mut SenseToActuate,
) -> anyhow::Result<SendCost> {
    // Slot first: killed between the two, the restart publishes this very state, which
    // the controller answers (or answers again). The other order would let a restart
    // re-publish tick k−1 after the controller has moved past it: deadlock. Stored after
    // the wake, not when the state is made: the watchdog reads the slot as the plant's
    // progress (a state stored before a lockstep wait for the record mover made the
    // controller look hung).
    ports.slot.store(&StateSample { deadline_ns: deadline, wake_ns: woke, ..made.state });
    let stamps = |s: &mut StateSample, publish_ns| {
        (s.deadline_ns, s.wake_ns, s.publish_ns, s.prev_publish) =
            (deadline, woke, publish_ns, prev);
    };
    let record = |s: &StateSample| {
        s2a.publish_ns = s.publish_ns;
        ports.states_flight.record(s);
    };
    let sent = ports.states.send_prewritten(made.published, stamps, record);
    sent.context("plant: publishing state")
}

/// The wait for each tick's torque, and what the shell says about it.
pub(super) struct TorqueWait {
    realtime: bool,
    last_update: u64,
    waiting_logged: bool,
}

impl TorqueWait {
    pub fn new(realtime: bool) -> Self {
        Self { realtime, last_update: now_ns(), waiting_logged: false }
    }

    /// Waits for the answer to tick `k` (started at `deadline`; 0 in lockstep) until
    /// `until`, handing every torque that arrives to the plant's hold rule.
    pub fn answer(
        &mut self,
        ports: &Ports,
        plant: &mut PlantTicker,
        role: &RoleArgs,
        (k, deadline, until): (u64, u64, u64),
    ) -> anyhow::Result<Option<Answer>> {
        let since = now_ns();
        let answer = ports.torques.wait_for(role.wait, until, |inbox| {
            let mut answer: Option<Answer> = None;
            inbox.drain(|t| {
                let before = plant.hold.rejected();
                let took = plant.take(&t, k, deadline, now_ns());
                if plant.hold.rejected() != before {
                    ports.refusals.store(&plant.hold.refusals());
                }
                // The record is by tick: one for a tick not reached has no slot there (it
                // would take the one of a true tick).
                if !matches!(took, Some(Answer::Future(..))) {
                    ports.torques_flight.record(&t);
                }
                answer = took.filter(Answer::answers_the_tick).or(answer);
            })?;
            if answer.is_none() && now_ns() - self.last_update > 5_000_000 {
                // Late joiners (a controller started after us) get the state from history.
                (self.last_update, _) = (now_ns(), ports.states.update_connections());
                if !self.realtime && !self.waiting_logged && now_ns() - since > 1_000_000_000 {
                    eprintln!("plant: no torque for tick {k} for 1 s (controller gone?); waiting");
                    self.waiting_logged = true;
                }
            }
            Ok(answer)
        })?;
        Ok(answer)
    }

    /// Says what a settled tick changed: safe mode entered or left, control resumed.
    pub fn report(&mut self, settled: &Settled, k: u64, hold_ticks: u64) {
        let resumed =
            matches!(settled, Settled::Fresh { .. }) && std::mem::take(&mut self.waiting_logged);
        match settled.event(k, hold_ticks) {
            Some(event) => eprintln!("plant: {event}"),
            None if resumed => eprintln!("plant: fresh torque at tick {k}; control resumed"),
            None => {}
        }
    }
}

/// Sense-to-actuate as the plant itself sees it (`--latency-out`): from a state's
/// publish to the receipt of its fresh answer.
pub(super) struct SenseToActuate {
    hist: Histogram<u64>,
    /// When the state now being answered was published.
    pub publish_ns: u64,
}

impl SenseToActuate {
    pub fn new() -> anyhow::Result<Self> {
        Ok(Self { hist: Histogram::new_with_bounds(1, 3_600_000_000_000, 3)?, publish_ns: 0 })
    }

    pub fn record(&mut self, answer: Option<Answer>) {
        if let Some(Answer::Fresh(_, recv)) = answer {
            self.hist.saturating_record(recv.saturating_sub(self.publish_ns).max(1));
        }
    }

    /// Writes `DIR/plant_sense_to_actuate.hgrm`: an optional measurement, so a full disk
    /// is a warning, never a failed run.
    pub fn write(&self, dir: Option<&std::path::Path>) {
        let Some(dir) = dir else { return };
        if let Err(e) = write_hgrm_file(&dir.join("plant_sense_to_actuate.hgrm"), &self.hist) {
            eprintln!("plant: warning: {e}");
        }
    }
}
