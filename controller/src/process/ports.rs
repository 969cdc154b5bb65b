//! What the controller's shell opens, and its per-tick helpers: the wait for the newest
//! state, what a decision means for the ports, and sending the held-back answers.

use anyhow::Context;
use rotorloop_common::ipc::{Inbox, Outbox, RoleNode, Topic, Wait, now_ns};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::role::{Corrupt, PlantWatch, RoleArgs, corrupted};
use rotorloop_common::wire::{ReferenceSample, StateSample, TorqueSample, WireFault};

use crate::policy::{Decision, DelayedSends, TorqueAnswers};

/// What the controller opens: its torque publisher, reference and state subscribers,
/// resume slot, and its watch on the plant's end.
pub(super) struct Ports {
    pub out: Outbox<TorqueSample>,
    pub refs: Inbox<ReferenceSample>,
    pub states: Inbox<StateSample>,
    pub slot: ResumeSlot<TorqueSample>,
    pub plant: PlantWatch,
    _node: RoleNode,
}

impl Ports {
    pub fn open(role: &RoleArgs) -> anyhow::Result<Self> {
        let domain = role.open_domain()?;
        let node = domain.node("controller").context("controller")?;
        let out = domain.outbox::<TorqueSample>(&node, Topic::Torque).context("controller")?;
        // Subscribe to the state last: the plant starts when it sees its state subscribers.
        let refs = domain.inbox::<ReferenceSample>(&node, Topic::Reference, 128, false);
        let refs = refs.context("controller")?;
        let states = domain.inbox::<StateSample>(&node, Topic::State, 8, role.wait.listens());
        let states = states.context("controller")?;
        let slot = ResumeSlot::<TorqueSample>::open(&domain, "controller").context("controller")?;
        let plant = PlantWatch::open(&domain, "controller").context("controller")?;
        Ok(Self { out, refs, states, slot, plant, _node: node })
    }

    /// Waits until `until` for states; every one goes through `answers` (older ones are
    /// skipped, and counted), the newest comes back with its receive time.
    pub fn newest_state(
        &self,
        answers: &mut TorqueAnswers,
        wait: Wait,
        until: u64,
    ) -> anyhow::Result<Option<(StateSample, u64)>> {
        let newest = self.states.wait_for(wait, until, |inbox| {
            let mut newest: Option<(StateSample, u64)> = None;
            inbox.drain(|s| {
                answers.take(&s, newest.is_some());
                newest = Some((s, now_ns()));
            })?;
            Ok(newest)
        })?;
        Ok(newest)
    }

    /// Carries out what the answer rule decided for the state of tick `k`: `None` when
    /// nothing more is to be done for it, else the state's fault (if any) to answer with.
    pub fn act_on(&self, decision: Decision, k: u64) -> anyhow::Result<Option<Option<WireFault>>> {
        Ok(match decision {
            Decision::AnswerAgain(prev) => {
                self.out
                    .send(prev, |s| s.publish_ns = now_ns())
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

    /// Publishes a torque (corrupted where fault injection says so).
    pub fn publish(&self, t: TorqueSample, corrupt: &[Corrupt]) -> anyhow::Result<()> {
        let sent = self.out.send(corrupted(corrupt, t), |s| s.publish_ns = now_ns());
        sent.context("controller: publishing torque")
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
                self.publish(t, corrupt)?;
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
