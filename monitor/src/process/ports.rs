//! What the monitor's shell opens: three subscribers with the largest buffers (no
//! listener: it polls), its resume slot, and its view of the plant's end.

use anyhow::Context;
use rotorloop_common::graph::Topic;
use rotorloop_common::ipc::MAX_BUFFER;
use rotorloop_common::ipc::ports::{Inbox, RoleNode};
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::role::args::RoleArgs;
use rotorloop_common::role::end::PlantEnd;
use rotorloop_common::wire::{ReferenceSample, StateSample, TorqueSample};

use crate::ROLE;
use crate::policy::{MonitorResume, RowJoiner};

/// The monitor's subscribers, resume slot and plant-end view.
pub(super) struct Ports {
    refs: Inbox<ReferenceSample>,
    torques: Inbox<TorqueSample>,
    states: Inbox<StateSample>,
    pub slot: ResumeSlot<MonitorResume>,
    pub plant_end: PlantEnd,
    /// The domain's name (the fallback report directory is named after it).
    pub domain: String,
    _node: RoleNode,
}

impl Ports {
    pub fn open(role: &RoleArgs, out: &std::path::Path) -> anyhow::Result<Self> {
        let domain = role.open_domain()?;
        let node = domain.node(ROLE).context(ROLE)?;
        // Subscribe to the state last: the plant starts when it sees its state subscribers,
        // so everything else must already be connected by then.
        let refs = domain.inbox::<ReferenceSample>(&node, Topic::Reference, MAX_BUFFER, false)?;
        let torques = domain.inbox::<TorqueSample>(&node, Topic::Torque, MAX_BUFFER, false)?;
        let states = domain.inbox::<StateSample>(&node, Topic::State, MAX_BUFFER, false)?;
        let slot = ResumeSlot::<MonitorResume>::open(&domain, ROLE).context(ROLE)?;
        let plant_end = PlantEnd::open(&domain).context(ROLE)?;
        // iceoryx2's own CLI finds the domain from here: `cd OUT && iox2 service list`.
        let _ = domain.write_iox2_config(out);
        let domain_name = domain.name().to_owned();
        Ok(Self { refs, torques, states, slot, plant_end, domain: domain_name, _node: node })
    }

    /// Hands everything that arrived to the row joiner: states, references, torques.
    pub fn drain(&self, joiner: &mut RowJoiner) -> anyhow::Result<()> {
        self.states.drain(|s| joiner.take_state(s))?;
        self.refs.drain(|r| joiner.take_reference(r))?;
        self.torques.drain(|t| joiner.take_torque(t))?;
        Ok(())
    }
}
