//! The stage breakdown of sense-to-actuate: where the microseconds of one loop tick go,
//! from the stamps the plant and the controller carry in their samples (each taken on
//! the process that did the work, never a difference of two processes' clocks beyond
//! what the hops already use: one monotonic clock per host).
//!
//! In order, the in-loop stages add up to sense-to-actuate exactly, tick by tick:
//! state send (publish stamp → `send` returned), state delivery (→ the controller has
//! it: its wake-up, the notify it waited for, and the receive that found no newer
//! state), validation (the answer rule and the state's checks), pairing (with the
//! reference), the law, publish preparation (resume slot, delay queue, loan), torque
//! send, torque delivery (→ the plant has it). The
//! notifies and loans are shown beside them: a notify runs after the send, in parallel
//! with the delivery (a spinning receiver does not wait for it); a loan is taken before
//! the publish stamp, ahead of time by default (the plant's before it sleeps to the tick,
//! the controller's after its previous publish). The plant's state preparation (its
//! wake-up → the state's publish stamp) comes before sense-to-actuate starts.
//!
//! A sample cannot carry the cost of its own send, so each publisher carries the cost of
//! its previous publish in the next sample: a state's send cost comes with the next
//! state, a torque's with the next torque (rows whose next torque the monitor does not
//! have yet when the row settles are not counted for the torque stages).

use hdrhistogram::Histogram;
use serde::Serialize;

use crate::latency::{HopStats, histogram};
use crate::policy::JoinedRow;

/// One stage of a loop tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Plant: publish stamp → `send` returned.
    StateSend,
    /// `send` returned → the controller has the state.
    StateDelivery,
    /// Controller: the answer rule and the state's validation.
    Validate,
    /// Controller: pairing with the reference sample.
    Pair,
    /// Controller: the geometric PID law.
    Law,
    /// Controller: resume slot, delay queue, loan, up to the publish stamp.
    PublishPrep,
    /// Controller: publish stamp → `send` returned.
    TorqueSend,
    /// `send` returned → the plant has the torque.
    TorqueDelivery,
    /// Plant: notifying the state's listeners (after the send).
    StateNotify,
    /// Controller: notifying the torque's listener (after the send).
    TorqueNotify,
    /// Plant: loaning the state sample (before the publish stamp).
    StateLoan,
    /// Controller: loaning the torque sample (inside publish preparation, or after the
    /// previous publish when loaned ahead).
    TorqueLoan,
    /// Plant: its wake-up → the state's publish stamp (the state made and its sample
    /// loaned, unless both were done before the sleep).
    StatePrep,
}

impl Stage {
    /// Every stage, the in-loop ones first, in the order a tick goes through them.
    pub const ALL: [Stage; 13] = [
        Stage::StateSend,
        Stage::StateDelivery,
        Stage::Validate,
        Stage::Pair,
        Stage::Law,
        Stage::PublishPrep,
        Stage::TorqueSend,
        Stage::TorqueDelivery,
        Stage::StateNotify,
        Stage::TorqueNotify,
        Stage::StateLoan,
        Stage::TorqueLoan,
        Stage::StatePrep,
    ];

    /// JSON name.
    pub fn name(self) -> &'static str {
        match self {
            Stage::StateSend => "state_send",
            Stage::StateDelivery => "state_delivery",
            Stage::Validate => "controller_validate",
            Stage::Pair => "controller_pair",
            Stage::Law => "controller_law",
            Stage::PublishPrep => "controller_publish_prep",
            Stage::TorqueSend => "torque_send",
            Stage::TorqueDelivery => "torque_delivery",
            Stage::StateNotify => "state_notify",
            Stage::TorqueNotify => "torque_notify",
            Stage::StateLoan => "state_loan",
            Stage::TorqueLoan => "torque_loan",
            Stage::StatePrep => "state_prep",
        }
    }

    /// Whether the stage is one of those that add up to sense-to-actuate.
    pub fn in_loop(self) -> bool {
        (self as usize) < 8
    }
}

/// One stage's statistics, as `summary.json` lists them (in [`Stage::ALL`] order).
#[derive(Debug, Clone, Serialize)]
pub struct StageStats {
    /// [`Stage::name`].
    pub stage: &'static str,
    /// [`Stage::in_loop`].
    pub in_loop: bool,
    /// ns.
    #[serde(flatten)]
    pub stats: HopStats,
}

/// The whole-run histogram of every stage.
#[derive(Debug, Clone)]
pub struct Stages {
    hists: Vec<Histogram<u64>>,
}

impl Default for Stages {
    fn default() -> Self {
        Self { hists: Stage::ALL.iter().map(|_| histogram()).collect() }
    }
}

impl Stages {
    fn record(&mut self, stage: Stage, ns: u64) {
        self.hists[stage as usize].saturating_record(ns.max(1));
    }

    /// Records the stages of one settled row (those its samples allow); with the
    /// controller on another host (`apart`), not the two deliveries (two clocks).
    pub fn record_row(&mut self, j: &JoinedRow, apart: bool) {
        let Some(t) = j.torque.filter(|t| t.computed()) else { return };
        let s = &j.state;
        if s.wake_ns > 0 && s.publish_ns >= s.wake_ns {
            self.record(Stage::StatePrep, s.publish_ns - s.wake_ns);
        }
        // A restarted plant's first state carries no cost (zero).
        if let Some(c) = j.following.map(|f| f.prev_publish).filter(|c| c.send_ns > 0) {
            self.record(Stage::StateLoan, c.loan_ns);
            self.record(Stage::StateSend, c.send_ns);
            self.record(Stage::StateNotify, c.notify_ns);
            let sent = s.publish_ns + c.send_ns;
            if !apart {
                self.record(Stage::StateDelivery, t.state_recv_ns.saturating_sub(sent));
            }
        }
        // Stamps in order (an answer sent again carries its first stamps: not counted).
        let stamps = [t.state_recv_ns, t.validated_ns, t.paired_ns, t.computed_ns, t.publish_ns];
        if stamps[0] > 0 && stamps.windows(2).all(|w| w[0] <= w[1]) {
            self.record(Stage::Validate, stamps[1] - stamps[0]);
            self.record(Stage::Pair, stamps[2] - stamps[1]);
            self.record(Stage::Law, stamps[3] - stamps[2]);
            self.record(Stage::PublishPrep, stamps[4] - stamps[3]);
        }
        let Some(c) = j.next_torque.filter(|n| n.prev_tick == j.tick).map(|n| n.prev_publish)
        else {
            return;
        };
        self.record(Stage::TorqueLoan, c.loan_ns);
        self.record(Stage::TorqueSend, c.send_ns);
        self.record(Stage::TorqueNotify, c.notify_ns);
        if let Some(f) = j.following.filter(|f| f.applied_torque_tick == j.tick && !apart) {
            let sent = t.publish_ns + c.send_ns;
            self.record(Stage::TorqueDelivery, f.applied_torque_recv_ns.saturating_sub(sent));
        }
    }

    /// Statistics of every stage, in [`Stage::ALL`] order.
    pub fn stats(&self) -> Vec<StageStats> {
        Stage::ALL
            .iter()
            .zip(&self.hists)
            .map(|(s, h)| StageStats {
                stage: s.name(),
                in_loop: s.in_loop(),
                stats: HopStats::of(h),
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use rotorloop_common::wire::{ReferenceSample, SendCost, StateSample, TorqueSample};

    use super::*;

    fn state(tick: u64, publish_ns: u64, prev: SendCost) -> StateSample {
        let x = rotorloop_common::params::RotorBodyState {
            r: glam::DMat3::IDENTITY,
            omega: glam::DVec3::ZERO,
            omega_r: glam::DVec3::ZERO,
            theta: glam::DVec3::ZERO,
        };
        StateSample { publish_ns, prev_publish: prev, ..StateSample::of(tick, 0.0, &x) }
    }

    #[test]
    fn in_loop_stages_add_up_to_sense_to_actuate() {
        let cost = |send_ns| SendCost { loan_ns: 300, send_ns, notify_ns: 900 };
        // State 7 published at 1000 (its send took 400), received by the controller at
        // 2000, validated 2100, paired 2300, computed 2600, torque published at 2900
        // (its send took 500), received by the plant at 4000.
        let torque = TorqueSample {
            tick: 7,
            state_recv_ns: 2000,
            validated_ns: 2100,
            paired_ns: 2300,
            computed_ns: 2600,
            publish_ns: 2900,
            ..TorqueSample::default()
        };
        let next_torque = TorqueSample { tick: 8, prev_tick: 7, prev_publish: cost(500), ..torque };
        let mut following = state(8, 10_000, cost(400));
        (following.applied_torque_tick, following.applied_torque_recv_ns) = (7, 4000);
        let row = JoinedRow {
            tick: 7,
            // Woken at 950: 50 ns from the wake-up to the publish stamp.
            state: StateSample { wake_ns: 950, ..state(7, 1000, SendCost::default()) },
            reference: ReferenceSample::zeroed(7),
            torque: Some(torque),
            following: Some(following),
            next_torque: Some(next_torque),
            first: false,
        };
        let mut stages = Stages::default();
        stages.record_row(&row, false);
        let stats = stages.stats();
        let p50 = |name: &str| stats.iter().find(|s| s.stage == name).map(|s| s.stats.p50);
        let in_loop: u64 = stats.iter().filter(|s| s.in_loop).map(|s| s.stats.p50).sum();
        assert_eq!(in_loop, 4000 - 1000, "the in-loop stages are the whole sense-to-actuate");
        assert_eq!(p50("state_delivery"), Some(2000 - 1400));
        assert_eq!(p50("controller_pair"), Some(200));
        assert_eq!(p50("torque_delivery"), Some(4000 - 3400));
        assert_eq!(p50("state_notify"), Some(900));
        assert_eq!(p50("state_prep"), Some(50));
        // Without the next torque the torque's send cost is unknown: not counted.
        let mut partial = Stages::default();
        partial.record_row(&JoinedRow { next_torque: None, ..row }, false);
        let counts: Vec<u64> = partial.stats().iter().map(|s| s.stats.count).collect();
        assert_eq!(counts, [1, 1, 1, 1, 1, 1, 0, 0, 1, 0, 1, 0, 1]);
    }
}
