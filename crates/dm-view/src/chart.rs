//! Line charts as PNG-ready images, drawn with plotters and a bundled font
//! (DejaVu Sans, `assets/`), so every chart carries its title, axis labels
//! with tick values, and a legend without any system font. Used for
//! dm-fit's loss curve, dm-eval's per-frame metric plots and dm-diagnose's
//! error plots.

use crate::ViewError;
use image::RgbImage;
use plotters::prelude::*;
use std::sync::OnceLock;

/// The font every chart's text uses, registered with plotters once.
const FONT_BYTES: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");
/// The family name under which [`register_font`] registers it.
pub const FONT_FAMILY: &str = "sans-serif";

/// How values map to the vertical axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ValueScale {
    Linear,
    /// log10; values ≤ 0 are not drawn.
    Log,
}

/// One line: `values[i]` is drawn at x = i; non-finite values leave gaps.
#[derive(Clone, Debug, PartialEq)]
pub struct ChartSeries<'a> {
    pub values: &'a [f64],
    pub color: [u8; 3],
    /// Legend entry (empty: none).
    pub label: &'a str,
}

/// Chart size, text and decorations.
#[derive(Clone, Debug, PartialEq)]
pub struct ChartOptions {
    pub width: u32,
    pub height: u32,
    pub scale: ValueScale,
    /// x positions marked by dashed dark grey vertical lines (e.g. where a
    /// stage or a split starts).
    pub markers: Vec<usize>,
    pub title: String,
    pub x_label: String,
    pub y_label: String,
}

impl Default for ChartOptions {
    fn default() -> Self {
        Self {
            width: 640,
            height: 360,
            scale: ValueScale::Linear,
            markers: Vec::new(),
            title: String::new(),
            x_label: String::new(),
            y_label: String::new(),
        }
    }
}

/// Registers the bundled font with plotters (once per process); every
/// plotters drawing in the workspace calls it before drawing text.
pub fn register_font() -> Result<(), ViewError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font(FONT_FAMILY, FontStyle::Normal, FONT_BYTES).is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err(ViewError::Chart(
            "the bundled font DejaVuSans.ttf does not parse".into(),
        ))
    }
}

/// A value as drawn on the vertical axis: itself, or its log10 (`None`
/// where it cannot be drawn: non-finite, or ≤ 0 on a log scale).
fn scaled(value: f64, scale: ValueScale) -> Option<f64> {
    match scale {
        ValueScale::Linear => value.is_finite().then_some(value),
        ValueScale::Log => (value.is_finite() && value > 0.0).then(|| value.log10()),
    }
}

/// The drawn range of every series' scaled values, padded so a flat
/// series gets a visible span (`None` when nothing can be drawn).
fn scaled_range(series: &[ChartSeries<'_>], scale: ValueScale) -> Option<(f64, f64)> {
    let (lo, hi) = series
        .iter()
        .flat_map(|s| s.values.iter())
        .filter_map(|&v| scaled(v, scale))
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !lo.is_finite() {
        return None;
    }
    let pad = if hi > lo {
        0.05 * (hi - lo)
    } else {
        0.5 * lo.abs().max(1e-9)
    };
    Some((lo - pad, hi + pad))
}

/// Runs of consecutive drawable values as (x, scaled value) points.
fn segments(values: &[f64], scale: ValueScale) -> Vec<Vec<(f64, f64)>> {
    let mut runs: Vec<Vec<(f64, f64)>> = Vec::new();
    let mut current = Vec::new();
    for (i, &v) in values.iter().enumerate() {
        if let Some(y) = scaled(v, scale) {
            current.push((i as f64, y));
        } else if !current.is_empty() {
            runs.push(std::mem::take(&mut current));
        }
    }
    if !current.is_empty() {
        runs.push(current);
    }
    runs
}

fn chart_error<E: std::fmt::Display>(e: E) -> ViewError {
    ViewError::Chart(e.to_string())
}

/// Draws the series on a white canvas with labelled axes, ticks, the
/// markers and a legend of the labelled series; the vertical range spans
/// every drawable value. A log scale draws log10 of the values on a linear
/// axis whose ticks read as the values themselves (plotters' own log axis
/// labels only powers of ten, so a loss falling within one decade had no
/// tick). With nothing drawable (no series, fewer than two points, all
/// non-finite) the frame and labels are drawn alone.
pub fn line_chart(
    series: &[ChartSeries<'_>],
    options: &ChartOptions,
) -> Result<RgbImage, ViewError> {
    register_font()?;
    let (w, h) = (options.width.max(160), options.height.max(120));
    let mut buffer = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(chart_error)?;
        let points = series.iter().map(|s| s.values.len()).max().unwrap_or(0);
        let x_max = points.saturating_sub(1).max(1) as f64;
        let range = scaled_range(series, options.scale).filter(|_| points >= 2);
        let (lo, hi) = range.unwrap_or((0.0, 1.0));
        let mut builder = ChartBuilder::on(&root);
        builder
            .margin(12)
            .x_label_area_size(if options.x_label.is_empty() { 24 } else { 40 })
            .y_label_area_size(if options.y_label.is_empty() { 52 } else { 70 });
        if !options.title.is_empty() {
            builder.caption(&options.title, (FONT_FAMILY, 17));
        }
        let mut chart = builder
            .build_cartesian_2d(0.0..x_max, lo..hi)
            .map_err(chart_error)?;
        let style = (FONT_FAMILY, 13);
        let scale = options.scale;
        chart
            .configure_mesh()
            .light_line_style(RGBColor(238, 238, 238))
            .x_desc(options.x_label.as_str())
            .y_desc(options.y_label.as_str())
            .label_style(style)
            .axis_desc_style(style)
            .x_labels(points.clamp(2, 11))
            // x is an index (frame, iteration): whole numbers only.
            .x_label_formatter(&|v| {
                if v.fract() == 0.0 {
                    format!("{v:.0}")
                } else {
                    String::new()
                }
            })
            .y_label_formatter(&|v| match scale {
                ValueScale::Linear => format_tick(*v),
                ValueScale::Log => format_tick(10f64.powf(*v)),
            })
            .draw()
            .map_err(chart_error)?;
        // Darker and wider than the mesh, which often has a line at the
        // same x (a split starting at frame 25).
        let marker_color = RGBColor(70, 70, 70);
        for &m in &options.markers {
            if m > 0 && m < points {
                chart
                    .draw_series(DashedLineSeries::new(
                        [(m as f64, lo), (m as f64, hi)],
                        8,
                        5,
                        marker_color.stroke_width(2),
                    ))
                    .map_err(chart_error)?;
            }
        }
        if range.is_some() {
            let mut any_label = false;
            for s in series {
                let color = RGBColor(s.color[0], s.color[1], s.color[2]);
                for (k, run) in segments(s.values, scale).into_iter().enumerate() {
                    let drawn = if run.len() == 1 {
                        chart.draw_series(std::iter::once(Circle::new(run[0], 4, color.filled())))
                    } else {
                        chart.draw_series(LineSeries::new(run, color.stroke_width(2)))
                    }
                    .map_err(chart_error)?;
                    if k == 0 && !s.label.is_empty() {
                        any_label = true;
                        drawn.label(s.label).legend(move |(x, y)| {
                            PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
                        });
                    }
                }
            }
            if any_label {
                chart
                    .configure_series_labels()
                    .label_font(style)
                    .background_style(WHITE.mix(0.85))
                    .border_style(RGBColor(180, 180, 180))
                    // Errors grow with time in most of our charts.
                    .position(SeriesLabelPosition::UpperLeft)
                    .draw()
                    .map_err(chart_error)?;
            }
        }
        root.present().map_err(chart_error)?;
    }
    RgbImage::from_raw(w, h, buffer)
        .ok_or_else(|| ViewError::Chart("chart buffer has the wrong size".into()))
}

/// The x positions (pixel columns, ascending, once each) where `image` has
/// a pixel of exactly `color`: what a chart drew in a series' colour, for
/// checks of a chart's content.
pub fn colour_columns(image: &RgbImage, color: [u8; 3]) -> Vec<u32> {
    let mut columns: Vec<u32> = image
        .enumerate_pixels()
        .filter(|(_, _, p)| p.0 == color)
        .map(|(x, _, _)| x)
        .collect();
    columns.sort_unstable();
    columns.dedup();
    columns
}

/// A tick value in at most 4 decimals (3 significant digits in
/// scientific notation outside 1e-3..1e4, so close log ticks differ),
/// never "-0". Below 1e-12 a tick is the rounding of a linear axis's
/// `lo + i·step` at zero (plotters drew "-2.78e-17" on a score axis), not
/// a value any of our charts plots, so it reads "0".
pub fn format_tick(v: f64) -> String {
    const ROUNDING_ZERO: f64 = 1e-12;
    let a = v.abs();
    if a < ROUNDING_ZERO {
        "0".into()
    } else if !(1e-3..1e4).contains(&a) {
        format!("{v:.2e}")
    } else {
        let text = format!("{v:.4}");
        let text = text.trim_end_matches('0').trim_end_matches('.');
        if text == "-0" {
            "0".into()
        } else {
            text.into()
        }
    }
}

#[cfg(test)]
mod format_tick_tests {
    use super::format_tick;

    #[test]
    fn axis_rounding_at_zero_reads_zero() {
        assert_eq!(format_tick(-2.7755575615628914e-17), "0");
        assert_eq!(format_tick(-0.0), "0");
        assert_eq!(format_tick(0.05), "0.05");
        assert_eq!(format_tick(-0.15), "-0.15");
        assert_eq!(format_tick(2.5e-5), "2.50e-5");
        assert_eq!(format_tick(12345.0), "1.23e4");
    }
}
