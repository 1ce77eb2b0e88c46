//! Line charts as PNG-ready images, drawn with plain pixels (no font is
//! bundled, so there are no labels: callers state axes and ranges in the
//! text that accompanies the picture). Used for dm-fit's loss curve and
//! dm-eval's per-frame metric plots.

use image::{Rgb, RgbImage};

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
}

/// Chart size and decorations.
#[derive(Clone, Debug, PartialEq)]
pub struct ChartOptions {
    pub width: u32,
    pub height: u32,
    pub scale: ValueScale,
    /// x positions marked by dotted grey vertical lines (e.g. where a
    /// stage or a split starts).
    pub markers: Vec<usize>,
}

impl Default for ChartOptions {
    fn default() -> Self {
        Self {
            width: 640,
            height: 360,
            scale: ValueScale::Linear,
            markers: Vec::new(),
        }
    }
}

const MARGIN: i64 = 30;

/// The range drawn on the vertical axis, in scaled units (`None` when no
/// value can be drawn). A flat series gets a small span around its value.
fn scaled_range<'a>(series: &[ChartSeries<'a>], scale: ValueScale) -> Option<(f64, f64)> {
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
        0.0
    } else {
        0.5 * lo.abs().max(1e-9)
    };
    Some((lo - pad, hi + pad))
}

fn scaled(value: f64, scale: ValueScale) -> Option<f64> {
    match scale {
        ValueScale::Linear => value.is_finite().then_some(value),
        ValueScale::Log => (value.is_finite() && value > 0.0).then(|| value.log10()),
    }
}

/// Draws the series over a white canvas with left and bottom axes; the
/// vertical range spans every drawable value of every series.
pub fn line_chart(series: &[ChartSeries<'_>], options: &ChartOptions) -> RgbImage {
    let (w, h) = (
        options.width.max(2 * MARGIN as u32 + 2),
        options.height.max(2 * MARGIN as u32 + 2),
    );
    let mut img = RgbImage::from_pixel(w, h, Rgb([255, 255, 255]));
    let put = |img: &mut RgbImage, x: i64, y: i64, c: Rgb<u8>| {
        if x >= 0 && y >= 0 && x < i64::from(w) && y < i64::from(h) {
            img.put_pixel(x as u32, y as u32, c);
        }
    };
    let (x0, y0, x1, y1) = (MARGIN, MARGIN, i64::from(w) - MARGIN, i64::from(h) - MARGIN);
    let axis = Rgb([60, 60, 60]);
    for x in x0..=x1 {
        put(&mut img, x, y1, axis);
    }
    for y in y0..=y1 {
        put(&mut img, x0, y, axis);
    }
    let points = series.iter().map(|s| s.values.len()).max().unwrap_or(0);
    let Some((lo, hi)) = scaled_range(series, options.scale) else {
        return img;
    };
    if points < 2 {
        return img;
    }
    let span = hi - lo;
    let last = (points - 1) as f64;
    let px = |i: usize| x0 + ((x1 - x0) as f64 * i as f64 / last) as i64;
    let py = |v: f64| y1 - ((y1 - y0) as f64 * (v - lo) / span) as i64;
    for &marker in &options.markers {
        if marker > 0 && marker < points {
            let x = px(marker);
            for y in (y0..=y1).step_by(3) {
                put(&mut img, x, y, Rgb([170, 170, 170]));
            }
        }
    }
    for s in series {
        let color = Rgb(s.color);
        for i in 1..s.values.len() {
            let (Some(a), Some(b)) = (
                scaled(s.values[i - 1], options.scale),
                scaled(s.values[i], options.scale),
            ) else {
                continue;
            };
            let (xa, ya, xb, yb) = (px(i - 1), py(a), px(i), py(b));
            let steps = (xb - xa).abs().max((yb - ya).abs()).max(1);
            for step in 0..=steps {
                let x = xa + (xb - xa) * step / steps;
                let y = ya + (yb - ya) * step / steps;
                for d in -1..=1 {
                    put(&mut img, x, y + d, color);
                }
            }
        }
    }
    img
}
