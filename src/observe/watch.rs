//! `rotorloop watch`: one loop live, from the roles' resume slots sampled a few hundred
//! times a second (a sample of the ticks, which it says), without a node of its own.

use std::collections::{BTreeMap, VecDeque};
use std::io::IsTerminal;
use std::time::Duration;

use hdrhistogram::Histogram;
use rotorloop_common::clock::now_ns;
use rotorloop_common::ipc::domain::Domain;
use rotorloop_common::resume::ResumeSlot;
use rotorloop_common::role::UsageError;
use rotorloop_common::signals::shutdown_requested;
use rotorloop_common::so3::rotation_angle;
use rotorloop_common::wire::{FLAG_SAFE_MODE, StateSample, effect_delay_s};
use serde::Serialize;

use super::slots::Slots;
use super::{RoleView, charts, out, refuse_unreachable, roles};

/// `rotorloop watch` arguments.
#[derive(Debug, Clone, clap::Args)]
pub struct WatchArgs {
    /// The domain to watch.
    #[arg(long)]
    pub domain: String,
    /// Print one JSON snapshot after `--seconds` of watching and exit (for scripts and tests).
    #[arg(long)]
    pub once: bool,
    /// With `--once`: JSON (the default for `--once`).
    #[arg(long)]
    pub json: bool,
    /// How long to watch before the snapshot of `--once` (s), 0 to 86400 (a day, the
    /// longest run).
    #[arg(long, allow_hyphen_values = true, default_value_t = 2.0,
          value_parser = rotorloop_common::input::number_in(0.0, 86_400.0, "seconds"))]
    pub seconds: f64,
    /// Slot samples per second, 1 to 2000.
    #[arg(long, allow_hyphen_values = true, default_value_t = 250,
          value_parser = rotorloop_common::input::whole_in(1u64, 2000, "samples a second"))]
    pub sample_hz: u64,
}

/// p50, p99 and max of a set of values (µs), and how many.
#[derive(Debug, Clone, Copy, Serialize, Default, PartialEq)]
pub struct Spread {
    /// Values.
    pub count: usize,
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Largest.
    pub max: f64,
}

impl Spread {
    fn of(values: impl Iterator<Item = f64>) -> Self {
        let mut v: Vec<f64> = values.filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return Self::default();
        }
        v.sort_by(f64::total_cmp);
        let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        Self { count: v.len(), p50: q(0.5), p99: q(0.99), max: v[v.len() - 1] }
    }
}

/// The spread of every value since watching began, in memory that does not grow with the
/// watch: an HdrHistogram of nanoseconds (3 significant digits, 1 ns to an hour; a longer
/// value counts as an hour), its largest value exact. A day of watching at 2000 samples a
/// second is 173 M values; a list of them would be 1.4 GB, and sorting it four times a
/// second would stall the screen long before.
struct SinceStart {
    ns: Histogram<u64>,
    max_us: f64,
}

impl SinceStart {
    const MAX_NS: u64 = 3_600_000_000_000;

    fn new() -> Self {
        let ns = Histogram::new_with_bounds(1, Self::MAX_NS, 3).expect("1 ns to an hour, 3 digits");
        Self { ns, max_us: f64::NEG_INFINITY }
    }

    /// One value (µs); NaN (no value this tick) is not counted, as in [`Spread::of`].
    fn record(&mut self, us: f64) {
        if !us.is_finite() {
            return;
        }
        self.max_us = self.max_us.max(us);
        // Below 0 (`as` saturates) counts as 0, above an hour as an hour.
        self.ns.saturating_record((us * 1e3).round() as u64);
    }

    fn spread(&self) -> Spread {
        if self.ns.is_empty() {
            return Spread::default();
        }
        // A bucket's highest value can lie above the largest value recorded in it.
        let q = |p: f64| (self.ns.value_at_quantile(p) as f64 / 1e3).min(self.max_us);
        Spread { count: self.ns.len() as usize, p50: q(0.5), p99: q(0.99), max: self.max_us }
    }
}

/// The events `watch` shows (the newest); older ones are let go.
const EVENTS_SHOWN: usize = 12;

/// One sampled tick.
#[derive(Debug, Clone, Copy)]
struct Seen {
    at_ns: u64,
    tick: u64,
    lateness_us: f64,
    delay_us: f64,
    err_deg: f64,
}

/// What `watch` shows.
#[derive(Debug, Clone, Default, Serialize)]
pub struct WatchView {
    /// The domain.
    pub domain: String,
    /// Simulated time of the newest state (s).
    pub t_s: f64,
    /// The plant's newest tick.
    pub tick: u64,
    /// Ticks per second over the last second.
    pub rate_hz: f64,
    /// Tick lateness (wake-up − grid time), last second (µs), of the sampled ticks.
    pub tick_lateness_1s: Spread,
    /// The same since watching began.
    pub tick_lateness_all: Spread,
    /// Actuation delay of the torques that took effect (µs): the loop's sense-to-actuate
    /// seen by the plant, last second, of the sampled ticks.
    pub actuation_delay_1s: Spread,
    /// The same since watching began.
    pub actuation_delay_all: Spread,
    /// Deadline misses: total, and in the last second.
    pub misses: u64,
    /// Misses in the last second.
    pub misses_1s: u64,
    /// Ticks in safe mode, total.
    pub safe_mode_ticks: u64,
    /// The plant is in safe mode now.
    pub safe_mode: bool,
    /// Attitude error now (deg), if the reference sample of the tick is in its window.
    pub err_deg: Option<f64>,
    /// Attitude error one second ago (deg): the trend.
    pub err_deg_1s_ago: Option<f64>,
    /// Roles and their state.
    pub roles: Vec<RoleView>,
    /// What happened while watching (a role died or restarted, safe mode, control back).
    pub events: Vec<String>,
    /// The charts' points: one a second of watching, the last minute.
    pub history: Vec<charts::Point>,
}

/// The watcher's state between refreshes.
struct Watcher {
    domain: Domain,
    slots: Slots,
    seen: VecDeque<Seen>,
    all_lateness: SinceStart,
    all_delay: SinceStart,
    last_tick: Option<u64>,
    misses_at: VecDeque<(u64, u64, u64)>,
    pids: BTreeMap<String, (u32, String)>,
    safe: bool,
    events: VecDeque<String>,
    started_ns: u64,
    dt: f64,
    history: charts::History,
}

impl Watcher {
    fn new(name: &str) -> Result<Self, UsageError> {
        let domain = Domain::new(name).map_err(|e| UsageError(e.to_string()))?;
        refuse_unreachable(&domain)?;
        let slots = Slots::observe(&domain);
        Ok(Self {
            domain,
            slots,
            seen: VecDeque::new(),
            all_lateness: SinceStart::new(),
            all_delay: SinceStart::new(),
            last_tick: None,
            misses_at: VecDeque::new(),
            pids: BTreeMap::new(),
            safe: false,
            events: VecDeque::new(),
            started_ns: now_ns(),
            dt: 1e-3,
            history: Default::default(),
        })
    }

    fn event(&mut self, what: String) {
        let at = (now_ns() - self.started_ns) as f64 / 1e9;
        if self.events.len() == EVENTS_SHOWN {
            self.events.pop_front();
        }
        self.events.push_back(format!("{at:7.2} s  {what}"));
    }

    /// One look at the plant's slot (and the reference's, for the error).
    fn sample(&mut self) {
        self.slots.reopen_missing(&self.domain);
        let Some(s) = self.slots.plant() else { return };
        if self.last_tick == Some(s.tick) {
            return;
        }
        if s.tick > 0 {
            self.dt = s.t_s / s.tick as f64;
        }
        self.last_tick = Some(s.tick);
        let lateness_us = if s.deadline_ns > 0 {
            s.wake_ns.saturating_sub(s.deadline_ns) as f64 / 1e3
        } else {
            f64::NAN
        };
        let delay_us = match s.effects {
            0 => f64::NAN,
            _ => {
                effect_delay_s(
                    s.tick.saturating_sub(1),
                    s.effect_ticks[0],
                    s.effect_offsets_s[0],
                    self.dt,
                ) * 1e6
            }
        };
        let err_deg = self.error(&s);
        self.seen.push_back(Seen { at_ns: now_ns(), tick: s.tick, lateness_us, delay_us, err_deg });
        self.all_lateness.record(lateness_us);
        self.all_delay.record(delay_us);
        self.misses_at.push_back((now_ns(), s.misses, s.safe_mode_ticks));
        let safe = s.flags & FLAG_SAFE_MODE != 0;
        if safe != self.safe {
            self.safe = safe;
            self.event(if safe {
                format!("plant in safe mode at tick {}", s.tick)
            } else {
                format!("control resumed at tick {}", s.tick)
            });
        }
        let horizon = now_ns().saturating_sub(2_000_000_000);
        while self.seen.front().is_some_and(|x| x.at_ns < horizon) {
            self.seen.pop_front();
        }
        while self.misses_at.front().is_some_and(|x| x.0 < horizon) {
            self.misses_at.pop_front();
        }
    }

    fn error(&self, s: &StateSample) -> f64 {
        let r = self.slots.reference.as_ref().and_then(ResumeSlot::load);
        let Some(rd) = r.and_then(|w| w.sample(s.tick)) else { return f64::NAN };
        rotation_angle(&(rd.reference_state().r_d * s.body_state().r.transpose())).to_degrees()
    }

    /// Roles: note deaths and restarts (a new pid for a role).
    fn roles(&mut self) -> Vec<RoleView> {
        let roles: Vec<RoleView> = roles(&self.domain)
            .unwrap_or_default()
            .into_iter()
            .filter(|r| !r.role.starts_with('('))
            .collect();
        for r in &roles {
            match self.pids.get(&r.role) {
                Some((pid, _)) if *pid != r.pid && r.state == "alive" => {
                    let what = format!("{} restarted (pid {} → {})", r.role, pid, r.pid);
                    self.event(what);
                }
                Some((pid, st)) if *pid == r.pid && st != &r.state => {
                    let what = format!("{} {} (pid {})", r.role, r.state, r.pid);
                    self.event(what);
                }
                None if !self.pids.is_empty() => {
                    self.event(format!("{} started (pid {})", r.role, r.pid))
                }
                _ => {}
            }
        }
        for (role, (pid, _)) in self.pids.clone() {
            if !roles.iter().any(|r| r.role == role) {
                self.event(format!("{role} gone (pid {pid})"));
            }
        }
        self.pids = roles.iter().map(|r| (r.role.clone(), (r.pid, r.state.clone()))).collect();
        roles
    }

    fn view(&mut self) -> WatchView {
        let roles = self.roles();
        let now = now_ns();
        let last_s: Vec<&Seen> =
            self.seen.iter().filter(|x| x.at_ns + 1_000_000_000 >= now).collect();
        let ago = self.seen.iter().find(|x| x.at_ns + 1_000_000_000 >= now).map(|x| x.err_deg);
        let s = self.slots.plant();
        let first_1s = self.misses_at.iter().find(|x| x.0 + 1_000_000_000 >= now).copied();
        let rate_hz = match (last_s.first(), last_s.last()) {
            (Some(a), Some(b)) if b.at_ns > a.at_ns => {
                (b.tick - a.tick) as f64 / ((b.at_ns - a.at_ns) as f64 / 1e9)
            }
            _ => 0.0,
        };
        let v = WatchView {
            domain: self.domain.name().to_owned(),
            t_s: s.map_or(0.0, |s| s.t_s),
            tick: s.map_or(0, |s| s.tick),
            rate_hz,
            tick_lateness_1s: Spread::of(last_s.iter().map(|x| x.lateness_us)),
            tick_lateness_all: self.all_lateness.spread(),
            actuation_delay_1s: Spread::of(last_s.iter().map(|x| x.delay_us)),
            actuation_delay_all: self.all_delay.spread(),
            misses: s.map_or(0, |s| s.misses),
            misses_1s: match (first_1s, s) {
                (Some(f), Some(s)) => s.misses.saturating_sub(f.1),
                _ => 0,
            },
            safe_mode_ticks: s.map_or(0, |s| s.safe_mode_ticks),
            safe_mode: self.safe,
            err_deg: last_s.last().map(|x| x.err_deg).filter(|e| e.is_finite()),
            err_deg_1s_ago: ago.filter(|e| e.is_finite()),
            roles,
            events: self.events.iter().cloned().collect(),
            history: Vec::new(),
        };
        self.history.push_if_due(now, &v);
        WatchView { history: self.history.points(), ..v }
    }
}

/// Samples for `seconds` (or until a signal), at `hz`.
fn sample_for(w: &mut Watcher, seconds: f64, hz: u64) {
    let until = now_ns() + (seconds * 1e9) as u64;
    while now_ns() < until && !shutdown_requested() {
        w.sample();
        std::thread::sleep(Duration::from_nanos(1_000_000_000 / hz));
    }
}

fn spread_line(name: &str, one: &Spread, all: &Spread) -> String {
    format!(
        "{name:<18} last 1 s: p50 {:>8.1}  p99 {:>8.1}  max {:>8.1} µs ({:>3} seen)   since start: p50 {:>8.1}  p99 {:>8.1}  max {:>8.1} µs",
        one.p50, one.p99, one.max, one.count, all.p50, all.p99, all.max
    )
}

/// The view as text lines (the screen, or plain lines when stdout is not a terminal).
pub fn render(v: &WatchView) -> Vec<String> {
    let trend = match (v.err_deg, v.err_deg_1s_ago) {
        (Some(e), Some(a)) if e < a => "falling",
        (Some(e), Some(a)) if e > a => "rising",
        (Some(_), Some(_)) => "steady",
        _ => "",
    };
    let mut l = vec![
        format!(
            "domain {}   t = {:.3} s   tick {}   {:.1} Hz   {}",
            v.domain,
            v.t_s,
            v.tick,
            v.rate_hz,
            if v.safe_mode { "SAFE MODE" } else { "controlling" }
        ),
        spread_line("tick lateness", &v.tick_lateness_1s, &v.tick_lateness_all),
        spread_line("actuation delay", &v.actuation_delay_1s, &v.actuation_delay_all),
        format!(
            "misses {} ({} in the last second)   safe-mode ticks {}   attitude error {} ({trend})",
            v.misses,
            v.misses_1s,
            v.safe_mode_ticks,
            v.err_deg.map_or("-".to_owned(), |e| format!("{e:.4}°"))
        ),
        String::new(),
    ];
    for r in &v.roles {
        l.push(format!(
            "  {:<11} pid {:>8}  {:<12} core {:>2}  {}",
            r.role,
            r.pid,
            r.state,
            r.core.map_or("-".into(), |c| c.to_string()),
            r.policy.as_deref().unwrap_or("")
        ));
    }
    l.push(String::new());
    l.push("events:".into());
    l.extend(v.events.iter().map(|e| format!("  {e}")));
    l
}

/// `rotorloop watch`.
pub fn watch(a: &WatchArgs) -> anyhow::Result<()> {
    rotorloop_common::signals::install_signal_handlers();
    let mut w = Watcher::new(&a.domain)?;
    w.roles();
    if a.once {
        sample_for(&mut w, a.seconds, a.sample_hz);
        // A loop that appeared while watching may be another user's.
        refuse_unreachable(&w.domain)?;
        return out(&(serde_json::to_string_pretty(&w.view())? + "\n"));
    }
    if !std::io::stdout().is_terminal() {
        // Plain lines, one block a second, for a pipe or a log.
        while !shutdown_requested() {
            sample_for(&mut w, 1.0, a.sample_hz);
            out(&(render(&w.view()).join("\n") + "\n\n"))?;
        }
        return Ok(());
    }
    let mut terminal = ratatui::init();
    let result = (|| -> anyhow::Result<()> {
        while !shutdown_requested() {
            sample_for(&mut w, 0.25, a.sample_hz);
            let lines = render(&w.view());
            terminal.draw(|f| {
                use ratatui::layout::{Constraint, Layout};
                use ratatui::widgets::{Block, Borders, Paragraph};
                let text: Vec<ratatui::text::Line> =
                    lines.iter().map(|l| ratatui::text::Line::from(l.as_str())).collect();
                let title = " rotorloop watch (q or Ctrl-C quits) ";
                let rows = u16::try_from(lines.len() + 2).unwrap_or(u16::MAX);
                let [top, bottom] =
                    Layout::vertical([Constraint::Length(rows), Constraint::Min(8)])
                        .areas(f.area());
                f.render_widget(
                    Paragraph::new(text).block(Block::default().title(title).borders(Borders::ALL)),
                    top,
                );
                charts::draw(f, bottom, &w.history);
            })?;
            if ratatui::crossterm::event::poll(Duration::ZERO)? {
                if let ratatui::crossterm::event::Event::Key(k) = ratatui::crossterm::event::read()?
                {
                    let ctrl_c = k.code == ratatui::crossterm::event::KeyCode::Char('c')
                        && k.modifiers.contains(ratatui::crossterm::event::KeyModifiers::CONTROL);
                    if k.code == ratatui::crossterm::event::KeyCode::Char('q') || ctrl_c {
                        break;
                    }
                }
            }
        }
        Ok(())
    })();
    ratatui::restore();
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic values from 0.5 µs to about 5 ms, skewed like lateness (many small,
    /// a long tail), with NaNs (ticks without a value) among them.
    fn values(n: usize, seed: u64) -> Vec<f64> {
        let mut x = seed;
        (0..n)
            .map(|i| {
                x = x
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                let u = (x >> 11) as f64 / (1u64 << 53) as f64;
                if i % 97 == 0 { f64::NAN } else { 0.5 + 5000.0 * u.powi(6) }
            })
            .collect()
    }

    #[test]
    fn the_spread_since_start_follows_the_values_in_memory_that_does_not_grow() {
        let mut since = SinceStart::new();
        assert_eq!(since.spread(), Spread::default());
        let first = values(100_000, 1);
        first.iter().for_each(|&v| since.record(v));
        let (exact, kept) = (Spread::of(first.iter().copied()), since.spread());
        assert_eq!(kept.count, exact.count);
        assert_eq!(kept.max, exact.max);
        for (k, e) in [(kept.p50, exact.p50), (kept.p99, exact.p99)] {
            // 3 significant digits, and a rank apart at most.
            assert!((k - e).abs() <= 2e-3 * e + 1e-3, "{k} against {e}");
        }
        let buckets = since.ns.distinct_values();
        // Ten times as many values, the same memory.
        values(1_000_000, 2).iter().for_each(|&v| since.record(v));
        assert_eq!(since.ns.distinct_values(), buckets);
        assert_eq!(since.spread().count, exact.count + 1_000_000 - 1_000_000 / 97 - 1);
        // Out of range: counted at the ends, the max still exact.
        since.record(-3.0);
        since.record(7.2e9);
        assert_eq!(since.spread().max, 7.2e9);
        assert_eq!(since.ns.distinct_values(), buckets);
    }

    #[test]
    fn watch_keeps_only_the_events_it_shows() {
        let mut w = Watcher::new("events-test").expect("a domain name");
        for i in 0..100 {
            w.event(format!("event {i}"));
        }
        assert_eq!(w.events.len(), EVENTS_SHOWN);
        assert!(
            w.events.iter().zip(88..100).all(|(kept, i)| kept.ends_with(&format!("event {i}")))
        );
    }
}
