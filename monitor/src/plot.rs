//! PNG figures rendered with plotters' bitmap backend. The font is compiled in (Ubuntu
//! Light from `epaint_default_fonts`), so rendering needs nothing installed on the
//! machine: no fontconfig, no system fonts.

use std::path::Path;
use std::sync::Once;

use plotters::prelude::*;
use plotters::style::FontStyle;

/// A failed figure: which file and why.
#[derive(Debug, thiserror::Error)]
#[error("cannot render {path}: {message}")]
pub struct PlotError {
    /// The PNG being written.
    pub path: String,
    /// What plotters said.
    pub message: String,
}

/// One line of a chart.
#[derive(Debug, Clone, Copy)]
pub struct Series<'a> {
    /// Legend text.
    pub label: &'a str,
    /// `(x, y)` points.
    pub points: &'a [(f64, f64)],
    /// Dashed lines for references.
    pub dashed: bool,
}

/// The y axis scale of a chart.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum YScale {
    /// Linear.
    Linear,
    /// Logarithmic; values at or below `floor` are drawn at `floor`.
    Log {
        /// The smallest value drawn.
        floor: f64,
    },
}

/// Chart size in pixels.
pub const SIZE: (u32, u32) = (1000, 600);

/// A figure of `size` drawn into memory by `draw`, then encoded as PNG and written to `path`
/// whole, never through a link ([`rotorloop_common::outdir`]).
fn render(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>) -> Result<(), PlotError>,
) -> Result<(), PlotError> {
    use image::ImageEncoder;
    let mut rgb = vec![0u8; size.0 as usize * size.1 as usize * 3];
    draw(BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area())?;
    let mut png = Vec::new();
    image::codecs::png::PngEncoder::new(&mut png)
        .write_image(&rgb, size.0, size.1, image::ColorType::Rgb8)
        .map_err(|e| err(path, e))?;
    rotorloop_common::outdir::write_file(path, png).map_err(|e| err(path, e))
}

const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The bytes are a valid TTF shipped by the crate; a failure here would show as a
        // rendering error on the first chart, which names the file.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            epaint_default_fonts::UBUNTU_LIGHT,
        );
    });
}

fn err(path: &Path, e: impl std::fmt::Display) -> PlotError {
    PlotError { path: path.display().to_string(), message: e.to_string() }
}

fn bounds(series: &[Series<'_>], scale: YScale) -> ((f64, f64), (f64, f64)) {
    let mut x = (f64::INFINITY, f64::NEG_INFINITY);
    let mut y = (f64::INFINITY, f64::NEG_INFINITY);
    for s in series {
        for &(px, py) in s.points {
            if !px.is_finite() || !py.is_finite() {
                continue;
            }
            let py = match scale {
                YScale::Log { floor } => py.max(floor),
                YScale::Linear => py,
            };
            x = (x.0.min(px), x.1.max(px));
            y = (y.0.min(py), y.1.max(py));
        }
    }
    if !x.0.is_finite() {
        x = (0.0, 1.0);
    }
    if !y.0.is_finite() {
        y = (0.0, 1.0);
    }
    if x.1 <= x.0 {
        x.1 = x.0 + 1.0;
    }
    match scale {
        YScale::Linear => {
            // 5 % headroom; a flat series still gets a visible band.
            let pad = ((y.1 - y.0) * 0.05).max(y.1.abs().max(y.0.abs()) * 1e-3).max(1e-300);
            y = (y.0 - pad, y.1 + pad);
        }
        YScale::Log { .. } => {
            y = (y.0 / 2.0, y.1 * 2.0);
        }
    }
    (x, y)
}

/// A line chart of several series sharing axes.
pub fn line_chart(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series<'_>],
    scale: YScale,
) -> Result<(), PlotError> {
    register_font();
    render(path, SIZE, |root| {
        root.fill(&WHITE).map_err(|e| err(path, e))?;
        draw_lines(&root, path, title, x_label, y_label, series, scale)?;
        root.present().map_err(|e| err(path, e))
    })
}

fn draw_lines<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series<'_>],
    scale: YScale,
) -> Result<(), PlotError>
where
    DB::ErrorType: 'static,
{
    let ((x0, x1), (y0, y1)) = bounds(series, scale);
    let mut builder = ChartBuilder::on(area);
    builder
        .caption(title, ("sans-serif", 22))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(80);
    macro_rules! finish {
        ($chart:expr, $map:expr) => {{
            let mut chart = $chart;
            chart
                .configure_mesh()
                .x_desc(x_label)
                .y_desc(y_label)
                .label_style(("sans-serif", 15))
                .draw()
                .map_err(|e| err(path, e))?;
            for (i, s) in series.iter().enumerate() {
                let color = PALETTE[i % PALETTE.len()];
                let pts = s.points.iter().filter(|p| p.0.is_finite() && p.1.is_finite()).map($map);
                let style = color.stroke_width(2);
                if s.dashed {
                    chart
                        .draw_series(DashedLineSeries::new(pts, 8, 5, style))
                        .map_err(|e| err(path, e))?
                        .label(s.label)
                        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color));
                } else {
                    chart
                        .draw_series(LineSeries::new(pts, style))
                        .map_err(|e| err(path, e))?
                        .label(s.label)
                        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color));
                }
            }
            if series.len() > 1 || !series.first().map(|s| s.label.is_empty()).unwrap_or(true) {
                chart
                    .configure_series_labels()
                    .background_style(WHITE.mix(0.85))
                    .border_style(BLACK)
                    .label_font(("sans-serif", 15))
                    .draw()
                    .map_err(|e| err(path, e))?;
            }
        }};
    }
    match scale {
        YScale::Linear => {
            finish!(builder.build_cartesian_2d(x0..x1, y0..y1).map_err(|e| err(path, e))?, |&p| p)
        }
        YScale::Log { floor } => finish!(
            builder.build_cartesian_2d(x0..x1, (y0..y1).log_scale()).map_err(|e| err(path, e))?,
            move |&(x, y): &(f64, f64)| (x, y.max(floor))
        ),
    }
    Ok(())
}

/// A grid of line charts (row-major panels), each with its own axes.
pub fn panel_grid(
    path: &Path,
    title: &str,
    (rows, cols): (usize, usize),
    panels: &[(&str, &str, &[Series<'_>])],
) -> Result<(), PlotError> {
    register_font();
    render(path, (1200, 900), |root| {
        root.fill(&WHITE).map_err(|e| err(path, e))?;
        let root = root.titled(title, ("sans-serif", 26)).map_err(|e| err(path, e))?;
        for (area, (panel_title, y_label, series)) in
            root.split_evenly((rows, cols)).iter().zip(panels)
        {
            draw_lines(area, path, panel_title, "t (s)", y_label, series, YScale::Linear)?;
        }
        root.present().map_err(|e| err(path, e))
    })
}

/// A histogram of `values` in `bins` equal bins over their range.
pub fn histogram(
    path: &Path,
    title: &str,
    x_label: &str,
    values: &[f64],
    bins: usize,
) -> Result<(), PlotError> {
    register_font();
    let finite: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    let lo = finite.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = finite.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let (lo, hi) =
        if lo.is_finite() && hi > lo { (lo, hi) } else { (lo.min(0.0), lo.max(0.0) + 1.0) };
    let bins = bins.max(1);
    let width = (hi - lo) / bins as f64;
    let mut counts = vec![0u32; bins];
    for v in &finite {
        let i = (((v - lo) / width) as usize).min(bins - 1);
        counts[i] += 1;
    }
    let top = counts.iter().copied().max().unwrap_or(1).max(1);
    render(path, SIZE, |root| {
        root.fill(&WHITE).map_err(|e| err(path, e))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 22))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(lo..hi, 0u32..top + top / 10 + 1)
            .map_err(|e| err(path, e))?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc("runs")
            .label_style(("sans-serif", 15))
            .draw()
            .map_err(|e| err(path, e))?;
        chart
            .draw_series(counts.iter().enumerate().map(|(i, &c)| {
                let x0 = lo + i as f64 * width;
                Rectangle::new([(x0, 0), (x0 + width, c)], PALETTE[0].filled())
            }))
            .map_err(|e| err(path, e))?;
        root.present().map_err(|e| err(path, e))
    })
}
