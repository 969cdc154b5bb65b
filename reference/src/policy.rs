//! What the reference process decides, without IPC or a clock: [`LeadWindow`] says which
//! ticks to publish next (up to [`REFERENCE_LEAD`] ahead of the newest state, never past
//! the last tick), builds their samples from the generator, and keeps the window of
//! recently published samples that a restart re-publishes (what the dead predecessor
//! published may be gone with its shared memory) and continues from, bit for bit.

use glam::DVec3;
use iceoryx2::prelude::ZeroCopySend;
use rotorloop_common::scenario::Scenario;
use rotorloop_common::so3::to_row_major;
use rotorloop_common::wire::REFERENCE_LEAD;
use rotorloop_common::wire::ReferenceSample;

use crate::Reference;

/// Samples a restarted reference can re-publish: its whole lead and history.
pub const RESUME_RING: usize = 2 * REFERENCE_LEAD as usize + 2;

/// The reference's resume slot: its last [`RESUME_RING`] published samples.
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("rotorloop::ReferenceResume_v5")]
#[repr(C)]
pub struct ReferenceResume {
    samples: [ReferenceSample; RESUME_RING],
    /// Newest tick stored + 1 (0: none).
    next: u64,
}

impl ReferenceResume {
    /// The next tick to publish (what a watcher reads as the reference's progress).
    pub fn next(&self) -> u64 {
        self.next
    }

    /// The stored sample of `tick`, if the window still holds it.
    pub fn sample(&self, tick: u64) -> Option<ReferenceSample> {
        Some(self.samples[tick as usize % RESUME_RING]).filter(|s| s.tick == tick)
    }
}

const EMPTY: ReferenceSample = ReferenceSample::zeroed(u64::MAX);

/// The lead rule (module docs).
#[derive(Debug, Clone)]
pub struct LeadWindow {
    generator: Reference,
    window: ReferenceResume,
    ticks: u64,
    dt: f64,
    newest_state: u64,
}

impl LeadWindow {
    /// A reference for `scenario` from tick 0.
    pub fn new(scenario: &Scenario) -> Self {
        Self {
            generator: Reference::for_scenario(scenario),
            window: ReferenceResume { samples: [EMPTY; RESUME_RING], next: 0 },
            ticks: scenario.ticks(),
            dt: scenario.dt(),
            newest_state: 0,
        }
    }

    /// Whether `r` (a resume slot's content) is of an unfinished run of this scenario.
    pub fn can_resume(&self, r: &ReferenceResume) -> bool {
        r.next > 0 && r.next <= self.ticks
    }

    /// Continues after the last sample of `r`, bit for bit, from the dummy body's
    /// integrator state that sample carries. Returns the stored samples to publish again,
    /// oldest first.
    pub fn resume(&mut self, scenario: &Scenario, r: &ReferenceResume) -> Vec<ReferenceSample> {
        let s = r.samples[((r.next - 1) as usize) % RESUME_RING];
        let x = s.body_state();
        let mut g = Reference::from_internal(
            scenario.reference,
            (x.r, DVec3::from_array(s.internal_h), DVec3::from_array(s.internal_p), x.theta),
            scenario.reference_torque,
        );
        g.step(s.tick as f64 * self.dt, self.dt);
        self.generator = g;
        self.window = *r;
        self.newest_state = r.next.saturating_sub(REFERENCE_LEAD + 1);
        let first = r.next.saturating_sub(RESUME_RING as u64);
        (first..r.next)
            .map(|tick| (tick, r.samples[tick as usize % RESUME_RING]))
            .filter_map(|(tick, again)| (again.tick == tick).then_some(again))
            .collect()
    }

    /// The next tick to publish (0 for a new run).
    pub fn next(&self) -> u64 {
        self.window.next
    }

    /// A state of tick `tick` was seen: the lead moves with it.
    pub fn saw_state(&mut self, tick: u64) {
        self.newest_state = self.newest_state.max(tick);
    }

    /// The next sample due (within the lead of the newest state, not past the last tick),
    /// or `None`. The generator steps past it and the window keeps it.
    pub fn next_due(&mut self) -> Option<ReferenceSample> {
        let next = self.window.next;
        if next > self.ticks.min(self.newest_state + REFERENCE_LEAD) {
            return None;
        }
        let t = next as f64 * self.dt;
        let rd = self.generator.sample(t);
        let body = self.generator.body_state();
        let (_, h, p, _) = self.generator.internal();
        let sample = ReferenceSample {
            tick: next,
            t_s: t,
            r_d_row_major: to_row_major(&rd.r_d),
            omega_d_rad_s: rd.omega_d.to_array(),
            omega_d_dot_rad_s2: rd.omega_d_dot.to_array(),
            omega_rotor_rad_s: body.omega_r.to_array(),
            theta_rotor_rad: body.theta.to_array(),
            publish_ns: 0,
            internal_h: h.to_array(),
            internal_p: p.to_array(),
        };
        self.window.samples[next as usize % RESUME_RING] = sample;
        self.window.next = next + 1;
        self.generator.step(t, self.dt);
        Some(sample)
    }

    /// What the resume slot stores (after each batch: the window is a few KiB).
    pub fn window(&self) -> &ReferenceResume {
        &self.window
    }
}

impl rotorloop_common::resume::Resumable for ReferenceResume {
    /// The next tick lies within the run, and every sample still in the window is a
    /// valid reference (as on the wire) of the tick its place says.
    fn resume_fault(&self, ticks: u64) -> Option<String> {
        if self.next > ticks + 1 {
            return Some(format!("next {} is beyond the run's last tick {ticks}", self.next));
        }
        let first = self.next.saturating_sub(RESUME_RING as u64);
        (first..self.next).find_map(|k| {
            let s = self.samples[k as usize % RESUME_RING];
            match s.validate() {
                _ if s.tick != k => {
                    Some(format!("the sample kept for tick {k} is of tick {}", s.tick))
                }
                Err(f) => Some(format!("tick {k}: {f}")),
                Ok(()) => None,
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scenario() -> Scenario {
        Scenario::load("paper-sinusoid").expect("built-in")
    }

    fn drain(w: &mut LeadWindow) -> Vec<u64> {
        std::iter::from_fn(|| w.next_due()).map(|s| s.tick).collect()
    }

    #[test]
    fn the_reference_leads_the_newest_state_by_the_lead_and_no_more() {
        let mut w = LeadWindow::new(&scenario());
        assert_eq!(drain(&mut w), (0..=REFERENCE_LEAD).collect::<Vec<_>>());
        w.saw_state(3);
        assert_eq!(drain(&mut w), (REFERENCE_LEAD + 1..=REFERENCE_LEAD + 3).collect::<Vec<_>>());
        w.saw_state(2);
        assert!(drain(&mut w).is_empty(), "an older state does not move the lead");
    }

    #[test]
    fn nothing_is_published_past_the_last_tick() {
        let s = scenario();
        let mut w = LeadWindow::new(&s);
        w.saw_state(s.ticks());
        assert_eq!(drain(&mut w).last(), Some(&s.ticks()));
        assert_eq!(w.next(), s.ticks() + 1);
    }

    #[test]
    fn a_restart_republishes_its_window_and_continues_bit_for_bit() {
        let s = scenario();
        let mut a = LeadWindow::new(&s);
        for k in 0..100 {
            a.saw_state(k);
            drain(&mut a);
        }
        let stored = *a.window();
        let mut b = LeadWindow::new(&s);
        assert!(b.can_resume(&stored));
        let again = b.resume(&s, &stored);
        assert_eq!(again.len(), RESUME_RING);
        assert_eq!(again.last().map(|r| r.tick), Some(stored.next - 1));
        for k in 100..150 {
            for w in [&mut a, &mut b] {
                w.saw_state(k);
            }
            let (ra, rb): (Vec<_>, Vec<_>) = (
                std::iter::from_fn(|| a.next_due()).collect(),
                std::iter::from_fn(|| b.next_due()).collect(),
            );
            assert_eq!(format!("{ra:?}"), format!("{rb:?}"));
        }
        assert!(
            !b.can_resume(&ReferenceResume { next: 0, ..stored }),
            "an empty slot is no restart"
        );
    }
}
