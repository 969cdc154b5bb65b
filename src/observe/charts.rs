//! `watch`'s charts: the attitude error, the actuation delay (the loop's sense-to-actuate as
//! the plant applies it: p50 and p99) and the misses, over the last minute, one point per
//! second of watching. The points are the view's own one-second figures, so a chart never
//! shows what the numbers above it do not.

use std::collections::VecDeque;

use ratatui::Frame;
use ratatui::layout::{Constraint, Direction, Layout, Rect};
use ratatui::style::{Color, Style};
use ratatui::symbols::Marker;
use ratatui::widgets::{Axis, Block, Borders, Chart, Dataset, GraphType};
use serde::Serialize;

use super::watch::WatchView;

/// Points kept: a minute at one a second.
pub const SPAN: usize = 60;

/// One second of watching.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Point {
    /// Simulated time of the newest state then (s).
    pub t_s: f64,
    /// Attitude error (deg; NaN when not known).
    pub err_deg: f64,
    /// Actuation delay in that second (µs): median and 99th percentile of the sampled ticks.
    pub delay_p50_us: f64,
    /// See `delay_p50_us`.
    pub delay_p99_us: f64,
    /// Deadline misses in that second.
    pub misses: u64,
}

/// The last [`SPAN`] points.
#[derive(Debug, Default)]
pub struct History {
    points: VecDeque<Point>,
    last_ns: Option<u64>,
}

impl History {
    /// Adds the view's one-second figures when a second has passed since the last point.
    pub fn push_if_due(&mut self, now_ns: u64, v: &WatchView) {
        if self.last_ns.is_some_and(|t| now_ns < t + 1_000_000_000) {
            return;
        }
        self.last_ns = Some(now_ns);
        if self.points.len() == SPAN {
            self.points.pop_front();
        }
        self.points.push_back(Point {
            t_s: v.t_s,
            err_deg: v.err_deg.unwrap_or(f64::NAN),
            delay_p50_us: v.actuation_delay_1s.p50,
            delay_p99_us: v.actuation_delay_1s.p99,
            misses: v.misses_1s,
        });
    }

    /// The points, oldest first.
    pub fn points(&self) -> Vec<Point> {
        self.points.iter().copied().collect()
    }
}

/// `(t, y)` of the finite values of `y`.
fn series(points: &[Point], y: impl Fn(&Point) -> f64) -> Vec<(f64, f64)> {
    points.iter().map(|p| (p.t_s, y(p))).filter(|(t, v)| t.is_finite() && v.is_finite()).collect()
}

/// One line of a chart: its name, colour and `(t, y)` points.
type Series<'a> = (&'a str, Color, &'a [(f64, f64)]);

/// A chart of `sets` (name, colour, data) titled `title`, its y axis from 0 to the largest
/// value (the x axis: the simulated time the points span).
fn chart<'a>(title: &'a str, unit: &'a str, sets: Vec<Series<'a>>) -> Chart<'a> {
    let all = sets.iter().flat_map(|s| s.2.iter());
    let (t0, t1, top) = all
        .fold((f64::INFINITY, f64::NEG_INFINITY, 0.0f64), |(a, b, m), (t, v)| {
            (a.min(*t), b.max(*t), m.max(*v))
        });
    let (t0, t1) = if t0 < t1 { (t0, t1) } else { (0.0, 1.0) };
    let top = if top > 0.0 { top * 1.1 } else { 1.0 };
    let datasets = sets
        .into_iter()
        .map(|(name, colour, data)| {
            Dataset::default()
                .name(name)
                .marker(Marker::Braille)
                .graph_type(GraphType::Line)
                .style(Style::default().fg(colour))
                .data(data)
        })
        .collect();
    Chart::new(datasets)
        .block(Block::default().title(format!(" {title} ")).borders(Borders::ALL))
        .x_axis(
            Axis::default().bounds([t0, t1]).labels([format!("{t0:.0} s"), format!("{t1:.0} s")]),
        )
        .y_axis(
            Axis::default().bounds([0.0, top]).labels(["0".to_owned(), format!("{top:.3} {unit}")]),
        )
}

/// Draws the three charts side by side in `area`.
pub fn draw(f: &mut Frame, area: Rect, h: &History) {
    let points = h.points();
    let err = series(&points, |p| p.err_deg);
    let p50 = series(&points, |p| p.delay_p50_us);
    let p99 = series(&points, |p| p.delay_p99_us);
    let misses = series(&points, |p| p.misses as f64);
    let cells = Layout::default()
        .direction(Direction::Horizontal)
        .constraints([Constraint::Ratio(1, 3); 3])
        .split(area);
    f.render_widget(
        chart("attitude error", "deg", vec![("error", Color::Cyan, &err[..])]),
        cells[0],
    );
    let delay = vec![("p50", Color::Green, &p50[..]), ("p99", Color::Yellow, &p99[..])];
    f.render_widget(chart("actuation delay", "µs", delay), cells[1]);
    f.render_widget(
        chart("misses per second", "", vec![("misses", Color::Red, &misses[..])]),
        cells[2],
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view(t_s: f64, err: f64, misses_1s: u64) -> WatchView {
        WatchView { t_s, err_deg: Some(err), misses_1s, ..WatchView::default() }
    }

    /// A point a second, the last minute kept, oldest first.
    #[test]
    fn the_history_keeps_a_point_a_second_for_a_minute() {
        let mut h = History::default();
        for i in 0..400u64 {
            // Four looks a second: one point a second.
            h.push_if_due(i * 250_000_000, &view(i as f64 * 0.25, 1.0 / (i + 1) as f64, i % 3));
        }
        let p = h.points();
        assert_eq!(p.len(), SPAN);
        assert_eq!(p.last().map(|p| p.t_s), Some(99.0), "the newest second's view");
        assert_eq!(p.first().map(|p| p.t_s), Some(40.0), "a minute back");
    }

    /// NaN values are left out of a chart's series, not drawn as zero.
    #[test]
    fn unknown_values_are_not_drawn() {
        let p = [
            Point { t_s: 0.0, err_deg: f64::NAN, delay_p50_us: 1.0, delay_p99_us: 2.0, misses: 0 },
            Point { t_s: 1.0, err_deg: 3.0, delay_p50_us: 1.0, delay_p99_us: 2.0, misses: 0 },
        ];
        assert_eq!(series(&p, |p| p.err_deg), vec![(1.0, 3.0)]);
    }
}
