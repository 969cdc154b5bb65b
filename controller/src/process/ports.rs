//! What the controller's shell opens, and its per-tick helpers: the wait for the newest
//! state, what a decision means for the ports, and sending the held-back answers.

use std::cell::Cell;

use anyhow::Context;
use rotorloop_common::clock::now_ns;
use rotorloop_common::flight::{FlightRecorder, Stream};
use rotorloop_common::graph::{Role, Topic};
use rotorloop_common::ipc::ports::{Inbox, Outbox, RoleNode};
use rotorloop_common::ipc::wait::Wait;
use rotorloop_common::params::ReferenceState;
use rotorloop_common::prefetch;
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::role::args::RoleArgs;
use rotorloop_common::role::end::PlantWatch;
use rotorloop_common::role::inject::{Corrupt, TestHooks, corrupt_in_place};
use rotorloop_common::signals::shutdown_requested;
use rotorloop_common::wire::SendCost;
use rotorloop_common::wire::{NO_TICK, ReferenceSample, StateSample, TorqueSample, WireFault};

use crate::ROLE;
use crate::policy::{ControllerResume, Decision, DelayedSends, ReferencePairing, TorqueAnswers};

/// What the first state of a tick asks for besides the rule's state, the resume slot and
/// the loaned torque ([`Ports::newest_state`]): the pairing and tick `k`'s reference
/// entry, the test hooks, the delay queue and the corruption list.
pub fn warm<'a>(
    pairing: &'a ReferencePairing,
    hooks: &'a TestHooks,
    sends: &'a DelayedSends,
    corrupt: &'a [Corrupt],
) -> impl Fn(u64) + 'a {
    move |k| {
        pairing.prefetch(k);
        prefetch::lines(hooks);
        prefetch::lines(sends);
        prefetch::lines(corrupt);
    }
}

/// What the controller opens: its torque publisher, reference and state subscribers,
/// resume slot, and its watch on the plant's end.
pub(super) struct Ports {
    pub out: Outbox<TorqueSample>,
    pub refs: Inbox<ReferenceSample>,
    pub states: Inbox<StateSample>,
    pub slot: ResumeSlot<ControllerResume>,
    pub plant: PlantWatch,
    /// The plant's resume slot: the newest state it has published, which a reference
    /// beyond the newest state taken (and its lead) is checked against (the tick rule).
    plant_published: ResumeSlot<StateSample>,
    /// Every torque published, in the run's flight record.
    flight: FlightRecorder<TorqueSample>,
    /// The hot path with its overhead cut (not `--plain-hot-path`): the reference topic
    /// drained after each publish and at a pairing only when the reference of the tick
    /// is not in hand, and each torque's sample loaned after the previous publish.
    cut: bool,
    /// The tick and cost of the last torque published (carried in the next one).
    last_publish: Cell<(u64, SendCost)>,
    _node: RoleNode,
}

impl Ports {
    pub fn open(role: &RoleArgs, ticks: u64) -> anyhow::Result<Self> {
        let domain = role.open_domain()?;
        let flight = role.flight(Stream::ControllerTorque, ticks, ROLE);
        let node = domain.node(ROLE).context(ROLE)?;
        let out = domain.outbox::<TorqueSample>(&node, Topic::Torque).context(ROLE)?;
        // Subscribe to the state last: the plant starts when it sees its state subscribers.
        let refs = domain.inbox::<ReferenceSample>(&node, Topic::Reference, 128, false);
        let refs = refs.context(ROLE)?;
        let states = domain.inbox::<StateSample>(&node, Topic::State, 8, role.wait.listens());
        let states = states.context(ROLE)?;
        let slot = ResumeSlot::<ControllerResume>::open(&domain, ROLE).context(ROLE)?;
        let plant = PlantWatch::open(&domain, ROLE).context(ROLE)?;
        let plant_published = ResumeSlot::open(&domain, Role::Plant.name()).context(ROLE)?;
        let last_publish = Cell::new((NO_TICK, SendCost::default()));
        let cut = !role.plain_hot_path;
        Ok(Self {
            out,
            refs,
            states,
            slot,
            plant,
            plant_published,
            flight,
            cut,
            last_publish,
            _node: node,
        })
    }

    /// Waits until `until` for states; every one goes through `answers` (older ones are
    /// skipped, and counted), the newest is left in `newest` and its receive time comes
    /// back: when the controller has it and knows it is the newest (the receive that finds
    /// no more samples is iceoryx2's delivery, not the controller's validation). The
    /// sample is in place before that stamp: nothing is moved after it. The plant watch
    /// sees it.
    ///
    /// On the cut hot path, the first state taken asks for the cache lines its answer
    /// will touch ([`rotorloop_common::prefetch`]): the rule's and the law's state and
    /// the validation's bounds, the resume slot's next copy and the torque sample loaned
    /// ahead (both for writing: the launcher and the plant read them last, from their
    /// cores), and what `warm` asks for (given the tick); they come while the inbox is
    /// read to its end, instead of one miss after another as the answer reaches them.
    pub fn newest_state(
        &mut self,
        answers: &mut TorqueAnswers,
        wait: Wait,
        until: u64,
        newest: &mut StateSample,
        warm: impl Fn(u64),
    ) -> anyhow::Result<Option<u64>> {
        let (slot, out, cut) = (&self.slot, &self.out, self.cut);
        let recv_ns = self.states.wait_for(wait, until, |inbox| {
            let mut any = false;
            inbox.drain(|s| {
                if cut && !any {
                    answers.prefetch();
                    slot.prefetch_store();
                    out.prefetch_loaned();
                    warm(s.tick);
                }
                answers.take(&s, any);
                (*newest, any) = (s, true);
            })?;
            Ok(any.then(now_ns))
        })?;
        if let Some(t) = recv_ns {
            self.plant.saw_state(newest.tick, t);
        }
        Ok(recv_ns)
    }

    /// Carries out what the answer rule decided for the state of tick `k`: `None` when
    /// nothing more is to be done for it, else the state's fault (if any) to answer with.
    pub fn act_on(&self, decision: Decision, k: u64) -> anyhow::Result<Option<Option<WireFault>>> {
        Ok(match decision {
            Decision::AnswerAgain(prev) => {
                self.out
                    .send_stamped(prev, |s, t1| s.publish_ns = t1, |s| self.flight.record(s))
                    .context("controller: re-publishing")?;
                None
            }
            Decision::Ignore => None,
            Decision::Answer { fault: Some(f), first_rejection: true } => {
                eprintln!("controller: rejected the state of tick {k}: {f} (skipping; counted)");
                Some(Some(f))
            }
            Decision::Answer { fault, .. } => Some(fault),
        })
    }

    /// Pairs the state of tick `k` with its reference (in lockstep waiting for it, polling
    /// every 100 µs), under the pairing rule. The reference works ahead and publishes in
    /// batches: the topic is read only when tick `k`'s is not in hand yet (each empty
    /// read of a subscriber costs about 0.2–0.7 µs here). A reference beyond `k` and the
    /// lead is checked against the plant's resume slot (the tick rule), read only then.
    pub fn pair(
        &self,
        pairing: &mut ReferencePairing,
        k: u64,
        state_ok: bool,
        lockstep: bool,
    ) -> anyhow::Result<Option<ReferenceState>> {
        pairing.saw_state(k);
        if !self.cut || pairing.lookup(k).is_none() {
            self.take_references(pairing)?;
        }
        pairing.pair(k, state_ok, lockstep, |p| {
            std::thread::sleep(std::time::Duration::from_micros(100));
            self.take_references(p)?;
            Ok(!shutdown_requested())
        })
    }

    /// Takes every reference sample that came into `pairing` (each checked as it is
    /// taken: the tick rule, then the wire contract's checks).
    fn take_references(&self, pairing: &mut ReferencePairing) -> anyhow::Result<()> {
        let published = || self.plant_published.load().map(|s| s.tick);
        Ok(self.refs.drain(|r| pairing.take(r, published))?)
    }

    /// After an answer is on its way: the reference just paired is settled (copied out
    /// of the ring: [`ReferencePairing::settle`]); on the hot path cut, the references
    /// that came are taken, so that the next tick's is in hand when its state arrives,
    /// and its pairing is a lookup. The reference works ahead, so the drain and each
    /// sample's checks are done here, off the path from a state to its answer, rather
    /// than at the next tick's pairing.
    pub fn references_ahead(&self, pairing: &mut ReferencePairing) -> anyhow::Result<()> {
        pairing.settle(); // before a sample taken can reuse the entry of the one just paired
        if self.cut {
            self.take_references(pairing)?;
        }
        Ok(())
    }

    /// Publishes a torque (corrupted where fault injection says so), carrying what the
    /// previous publish cost. Taken by reference, and filled in after the publish stamp
    /// ([`Outbox::send_patched`]): nothing of it is copied before that stamp.
    pub fn publish(&self, t: &TorqueSample, corrupt: &[Corrupt]) -> anyhow::Result<()> {
        let prev = self.last_publish.get();
        let patch = |s: &mut TorqueSample, t1: u64| {
            (s.prev_tick, s.prev_publish, s.publish_ns) = (prev.0, prev.1, t1);
            corrupt_in_place(corrupt, s);
        };
        let sent = self.out.send_patched(t, patch, |s| self.flight.record(s));
        self.last_publish.set((t.tick, sent.context("controller: publishing torque")?));
        if self.cut {
            // The next answer's sample, loaned now (after this one is on its way) rather
            // than between its state's arrival and its publish.
            self.out.preloan().context("controller: loaning the next torque's sample")?;
        }
        Ok(())
    }

    /// Publishes the held-back answers that are due; with `all`, waits for every one.
    pub fn send_due(
        &self,
        sends: &mut DelayedSends,
        corrupt: &[Corrupt],
        all: bool,
    ) -> anyhow::Result<()> {
        loop {
            while let Some(t) = sends.due(now_ns()) {
                self.publish(&t, corrupt)?;
            }
            match sends.next_due_ns() {
                Some(due) if all => std::thread::sleep(std::time::Duration::from_nanos(
                    due.saturating_sub(now_ns()),
                )),
                _ => return Ok(()),
            }
        }
    }
}
