//! The one reader of the four roles' resume slots: where each role stands. `ps` and
//! `watch` open them read-only (they create nothing); the launcher opens or creates them
//! before the roles start, each on its role's host, and its watchdog reads their marks.

use std::collections::BTreeMap;

use rotorloop_common::graph::Role;
use rotorloop_common::ipc::IpcError;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::wire::{FLAG_LAST, Refusals, StateSample};
use rotorloop_controller::policy::ControllerResume;
use rotorloop_monitor::policy::MonitorResume;
use rotorloop_reference::policy::ReferenceResume;

/// The resume slots of a loop's four roles (a slot not there yet is `None`).
#[derive(Debug)]
pub struct Slots {
    plant: Option<ResumeSlot<StateSample>>,
    /// The plant's torque refusals by kind ([`Refusals`]).
    refusals: Option<ResumeSlot<Refusals>>,
    controller: Option<ResumeSlot<ControllerResume>>,
    /// The reference's slot (its window of samples).
    pub reference: Option<ResumeSlot<ReferenceResume>>,
    monitor: Option<ResumeSlot<MonitorResume>>,
}

/// One slot of `role` in its domain: opened or created (`create`), or opened read-only
/// if it exists.
fn one<T: Copy + iceoryx2::prelude::ZeroCopySend>(
    domain: &Domain,
    role: Role,
    create: bool,
) -> Result<Option<ResumeSlot<T>>, IpcError> {
    match create {
        true => ResumeSlot::open(domain, role.name()).map(Some),
        false => ResumeSlot::open_existing(domain, role.name()),
    }
}

impl Slots {
    /// Each role's slot in `domain_of(role)`: read-only where it exists (an observer), or
    /// opened and created (`create`: the launcher, before the roles start).
    pub fn open<'a>(
        domain_of: impl Fn(Role) -> &'a Domain,
        create: bool,
    ) -> Result<Self, IpcError> {
        Ok(Self {
            plant: one(domain_of(Role::Plant), Role::Plant, create)?,
            refusals: match create {
                true => Some(ResumeSlot::open(domain_of(Role::Plant), Refusals::SLOT)?),
                false => ResumeSlot::open_existing(domain_of(Role::Plant), Refusals::SLOT)?,
            },
            controller: one(domain_of(Role::Controller), Role::Controller, create)?,
            reference: one(domain_of(Role::Reference), Role::Reference, create)?,
            monitor: one(domain_of(Role::Monitor), Role::Monitor, create)?,
        })
    }

    /// An observer's slots of `domain`: those that exist, read-only.
    pub fn observe(domain: &Domain) -> Self {
        Self {
            plant: one(domain, Role::Plant, false).ok().flatten(),
            refusals: ResumeSlot::open_existing(domain, Refusals::SLOT).ok().flatten(),
            controller: one(domain, Role::Controller, false).ok().flatten(),
            reference: one(domain, Role::Reference, false).ok().flatten(),
            monitor: one(domain, Role::Monitor, false).ok().flatten(),
        }
    }

    /// Opens the slots that were not there yet (roles started since).
    pub fn reopen_missing(&mut self, domain: &Domain) {
        if self.plant.is_none()
            || self.refusals.is_none()
            || self.controller.is_none()
            || self.reference.is_none()
            || self.monitor.is_none()
        {
            let fresh = Self::observe(domain);
            self.plant = self.plant.take().or(fresh.plant);
            self.refusals = self.refusals.take().or(fresh.refusals);
            self.controller = self.controller.take().or(fresh.controller);
            self.reference = self.reference.take().or(fresh.reference);
            self.monitor = self.monitor.take().or(fresh.monitor);
        }
    }

    /// The plant's last state sample.
    pub fn plant(&self) -> Option<StateSample> {
        self.plant.as_ref().and_then(ResumeSlot::load)
    }

    /// The plant's torque refusals by kind, as of its last refusal.
    pub fn refusals(&self) -> Option<Refusals> {
        self.refusals.as_ref().and_then(ResumeSlot::load)
    }

    /// The tick of the controller's last answer.
    pub fn controller_tick(&self) -> Option<u64> {
        self.controller.as_ref().and_then(ResumeSlot::load).map(|r| r.last.tick)
    }

    /// The next tick the reference publishes.
    pub fn reference_next(&self) -> Option<u64> {
        self.reference.as_ref().and_then(ResumeSlot::load).map(|r| r.next())
    }

    /// The monitor's next row to take (its progress; the rows before it may still be on
    /// their way to its files).
    pub fn monitor_next(&self) -> Option<u64> {
        self.monitor.as_ref().and_then(ResumeSlot::load).map(|m| m.taken_row)
    }

    /// The plant has published its last tick: the control loop is complete.
    pub fn loop_complete(&self) -> bool {
        self.plant().is_some_and(|s| s.flags & FLAG_LAST != 0)
    }

    /// Each role's newest tick (the reference's and the monitor's next), by role name.
    pub fn ticks(&self) -> BTreeMap<String, u64> {
        let marks = [
            (Role::Plant, self.plant().map(|s| s.tick)),
            (Role::Controller, self.controller_tick()),
            (Role::Reference, self.reference_next()),
            (Role::Monitor, self.monitor_next()),
        ];
        marks.into_iter().filter_map(|(r, t)| Some((r.name().to_owned(), t?))).collect()
    }
}
