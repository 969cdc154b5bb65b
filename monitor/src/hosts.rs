//! Which roles share the plant's host, and so its clock. A monitor on any host computes
//! a hop only from two stamps taken on one host (the samples carry the stamps of the host
//! that took them); a hop between two hosts would subtract two clocks, so it is left out
//! and the summary says which and why.

use serde::Serialize;

use crate::latency::Hop;
use crate::stages::Stage;
use rotorloop_common::graph::Role;

/// The host of each role (`--hosts plant=a,controller=b,…`; none: one host).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Hosts {
    /// The plant's host.
    pub plant: Option<String>,
    /// The controller's host.
    pub controller: Option<String>,
    /// The reference's host.
    pub reference: Option<String>,
    /// The monitor's host.
    pub monitor: Option<String>,
}

/// What the summary says about a run over several hosts.
#[derive(Debug, Clone, Serialize)]
pub struct CrossHost {
    /// The host of each role.
    pub hosts: Hosts,
    /// Hops and stages not computed: they span two hosts.
    pub not_computed: Vec<&'static str>,
    /// Why.
    pub why: &'static str,
}

impl Hosts {
    /// Parses `ROLE=HOST,…`.
    pub fn parse(s: &str) -> Result<Self, String> {
        let mut h = Self::default();
        for part in s.split(',').filter(|p| !p.is_empty()) {
            let (role, host) = part
                .split_once('=')
                .ok_or_else(|| format!("--hosts `{part}` is not allowed: ROLE=HOST"))?;
            let slot = match role.parse::<Role>() {
                Ok(Role::Plant) => &mut h.plant,
                Ok(Role::Controller) => &mut h.controller,
                Ok(Role::Reference) => &mut h.reference,
                Ok(Role::Monitor) => &mut h.monitor,
                Err(e) => return Err(format!("--hosts: {e}")),
            };
            *slot = Some(host.to_owned());
        }
        Ok(h)
    }

    /// The controller stamps on another clock than the plant.
    pub fn controller_apart(&self) -> bool {
        self.plant != self.controller
    }

    /// Whether `hop` is computed from stamps of one host.
    pub fn computable(&self, hop: Hop) -> bool {
        match hop {
            Hop::StateTransport | Hop::TorqueTransport => !self.controller_apart(),
            Hop::ReferenceLead => self.plant == self.reference,
            _ => true,
        }
    }

    /// The summary's account, when the run spans hosts.
    pub fn cross_host(&self) -> Option<CrossHost> {
        if *self == Self::default() {
            return None;
        }
        let mut not_computed: Vec<&'static str> =
            Hop::ALL.iter().filter(|h| !self.computable(**h)).map(|h| h.name()).collect();
        if self.controller_apart() {
            // The stages `Stages::record_row` leaves out when the controller is apart.
            not_computed.extend([Stage::StateDelivery, Stage::TorqueDelivery].map(Stage::name));
        }
        Some(CrossHost {
            hosts: self.clone(),
            not_computed,
            why: "each would subtract a stamp of one host's CLOCK_MONOTONIC from another's; \
                  sense_to_actuate (both stamps the plant's) and controller_compute (both the \
                  controller's) are exact on any split, and their difference is the time the \
                  two transports took together",
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hops_between_two_hosts_are_never_computed() {
        let one = Hosts::default();
        assert!(Hop::ALL.iter().all(|h| one.computable(*h)) && one.cross_host().is_none());
        let split = Hosts::parse("plant=a,reference=a,monitor=a,controller=b").expect("valid");
        assert!(!split.computable(Hop::StateTransport) && !split.computable(Hop::TorqueTransport));
        assert!(split.computable(Hop::SenseToActuate) && split.computable(Hop::ReferenceLead));
        let c = split.cross_host().expect("split");
        assert_eq!(
            c.not_computed,
            ["state_transport", "torque_transport", "state_delivery", "torque_delivery"]
        );
        assert!(Hosts::parse("pilot=b").is_err() && Hosts::parse("plant").is_err());
    }
}
