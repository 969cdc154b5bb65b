//! What the monitor's shell opens: three subscribers with the largest buffers (no
//! listener: it polls), its resume slot, and its view of the plant's end.

use anyhow::Context;
use rotorloop_common::graph::{Role, Topic};
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
    /// The plant's resume slot: the newest state it has published, which a torque or a
    /// reference beyond the newest state taken is checked against (the tick rule).
    plant_published: ResumeSlot<StateSample>,
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
        let plant_published = ResumeSlot::open(&domain, Role::Plant.name()).context(ROLE)?;
        // iceoryx2's own CLI finds the domain from here: `cd OUT && iox2 service list`.
        let _ = domain.write_iox2_config(out);
        let domain_name = domain.name().to_owned();
        Ok(Self {
            refs,
            torques,
            states,
            slot,
            plant_end,
            plant_published,
            domain: domain_name,
            _node: node,
        })
    }

    /// Hands everything that arrived to the row joiner: states, references, torques. A
    /// torque or reference beyond the newest state taken (it arrived before its state) is
    /// checked against the plant's resume slot (the tick rule), read only then: it was
    /// received, so the state it follows was stored there before.
    pub fn drain(&self, joiner: &mut RowJoiner) -> anyhow::Result<()> {
        let published = || self.plant_published.load().map(|s| s.tick);
        self.states.drain(|s| joiner.take_state(s))?;
        self.refs.drain(|r| joiner.take_reference(r, published))?;
        self.torques.drain(|t| joiner.take_torque(t, published))?;
        Ok(())
    }
}
