//! The report's PNGs: charts with titles, labelled axes and legends
//! (plotters with dm-view's bundled font); the error map is drawn pixel by
//! pixel, its axes and colour range given in report.md's caption.

use crate::analysis::{AccelSample, dot, norm};
use crate::{DiagnoseError, Diagnosis};
use dm_bundle::{Bundle, Split, write_file_atomic};
use dm_view::ViewError;
use dm_view::chart::{ChartOptions, ChartSeries, FONT_FAMILY, ValueScale, line_chart};
use image::{Rgb, RgbImage};
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::path::Path;

pub(crate) struct PlotInputs<'a> {
    pub bundle: &'a Bundle,
    pub split: Split,
    pub base_track: &'a [f64],
    pub extended_track: Option<&'a [f64]>,
    pub per_track_test: &'a [f64],
    pub samples: &'a [AccelSample],
    pub residual_dv: &'a [f64],
    pub diagnosis: &'a Diagnosis,
    pub up: [f64; 3],
    pub axis: [f64; 3],
}

/// A written plot and the ranges its axes span (for the report).
#[derive(Clone, Debug)]
pub(crate) struct PlotFile {
    pub file: String,
    pub caption: String,
}

const RED: [u8; 3] = [200, 40, 40];
const BLUE: [u8; 3] = [40, 90, 200];
const GREY: [u8; 3] = [150, 150, 150];

fn save(image: &RgbImage, out: &Path, name: &str) -> Result<(), DiagnoseError> {
    let path = out.join(name);
    write_file_atomic(&path, |tmp| {
        image
            .save_with_format(tmp, image::ImageFormat::Png)
            .map_err(std::io::Error::other)
    })?;
    Ok(())
}

/// Blue (low) → red (high).
fn heat(t: f64) -> [u8; 3] {
    let t = t.clamp(0.0, 1.0);
    [
        (40.0 + 200.0 * t) as u8,
        (60.0 + 120.0 * (1.0 - (2.0 * t - 1.0).abs())) as u8,
        (220.0 - 190.0 * t) as u8,
    ]
}

fn dot_at(img: &mut RgbImage, x: f64, y: f64, r: i64, color: [u8; 3]) {
    let (cx, cy) = (x.round() as i64, y.round() as i64);
    for dy in -r..=r {
        for dx in -r..=r {
            if dx * dx + dy * dy > r * r {
                continue;
            }
            let (px, py) = (cx + dx, cy + dy);
            if px >= 0 && py >= 0 && (px as u32) < img.width() && (py as u32) < img.height() {
                img.put_pixel(px as u32, py as u32, Rgb(color));
            }
        }
    }
}

/// Maps data ranges onto a canvas with a 30 px margin.
struct Frame {
    w: f64,
    h: f64,
    x: (f64, f64),
    y: (f64, f64),
}

impl Frame {
    fn new(w: u32, h: u32, xs: impl Iterator<Item = f64>, ys: impl Iterator<Item = f64>) -> Self {
        let span = |it: &mut dyn Iterator<Item = f64>| {
            let (lo, hi) = it
                .filter(|v| v.is_finite())
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
                    (l.min(v), h.max(v))
                });
            if !lo.is_finite() {
                (0.0, 1.0)
            } else if hi - lo < 1e-12 {
                (lo - 0.5, hi + 0.5)
            } else {
                (lo, hi)
            }
        };
        let mut xs = xs;
        let mut ys = ys;
        Self {
            w: w as f64,
            h: h as f64,
            x: span(&mut xs),
            y: span(&mut ys),
        }
    }

    fn px(&self, x: f64, y: f64) -> (f64, f64) {
        let m = 30.0;
        (
            m + (x - self.x.0) / (self.x.1 - self.x.0) * (self.w - 2.0 * m),
            self.h - m - (y - self.y.0) / (self.y.1 - self.y.0) * (self.h - 2.0 * m),
        )
    }
}

fn rgb(c: [u8; 3]) -> RGBColor {
    RGBColor(c[0], c[1], c[2])
}

type PlotResult = Result<(), Box<dyn std::error::Error>>;

/// A `w` × `h` white picture drawn by `draw` with plotters (the bundled
/// font registered first).
fn draw_with_plotters(
    w: u32,
    h: u32,
    draw: impl FnOnce(&DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>) -> PlotResult,
) -> Result<RgbImage, ViewError> {
    dm_view::chart::register_font()?;
    let mut buffer = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (w, h)).into_drawing_area();
        draw(&root).map_err(|e| ViewError::Chart(e.to_string()))?;
        root.present()
            .map_err(|e| ViewError::Chart(e.to_string()))?;
    }
    RgbImage::from_raw(w, h, buffer)
        .ok_or_else(|| ViewError::Chart("chart buffer has the wrong size".into()))
}

type PanelChart<'a, 'b> = ChartContext<
    'a,
    BitMapBackend<'b>,
    plotters::coord::cartesian::Cartesian2d<
        plotters::coord::types::RangedCoordf64,
        plotters::coord::types::RangedCoordf64,
    >,
>;

/// A scatter panel: `[title, x label, y label]`, the ranges, the points
/// as small blue dots.
fn scatter_panel<'a, 'b>(
    area: &'a DrawingArea<BitMapBackend<'b>, plotters::coord::Shift>,
    [title, x_desc, y_desc]: [&str; 3],
    x: std::ops::Range<f64>,
    y: std::ops::Range<f64>,
    points: impl Iterator<Item = (f64, f64)>,
) -> Result<PanelChart<'a, 'b>, Box<dyn std::error::Error>> {
    let mut chart = ChartBuilder::on(area)
        .caption(title, (FONT_FAMILY, 16))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(x, y)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .y_label_formatter(&|v| dm_view::chart::format_tick(*v))
        .label_style((FONT_FAMILY, 12))
        .axis_desc_style((FONT_FAMILY, 13))
        .draw()?;
    chart.draw_series(points.map(|p| Circle::new(p, 1, rgb(BLUE).filled())))?;
    Ok(chart)
}

/// The legend of a panel's labelled series, top right.
fn draw_legend<'a, 'b: 'a>(chart: &mut PanelChart<'a, 'b>) -> PlotResult {
    chart
        .configure_series_labels()
        .label_font((FONT_FAMILY, 12))
        .background_style(WHITE.mix(0.85))
        .border_style(rgb(GREY))
        .position(SeriesLabelPosition::UpperRight)
        .draw()?;
    Ok(())
}

fn canvas(w: u32, h: u32) -> RgbImage {
    RgbImage::from_pixel(w, h, Rgb([255, 255, 255]))
}

/// Robust symmetric range: the 98th percentile of |values|.
fn robust_abs_max(values: &[f64]) -> f64 {
    let mut a: Vec<f64> = values
        .iter()
        .filter(|v| v.is_finite())
        .map(|v| v.abs())
        .collect();
    if a.is_empty() {
        return 1.0;
    }
    a.sort_by(f64::total_cmp);
    a[(a.len() * 98 / 100).min(a.len() - 1)].max(1e-9)
}

pub(crate) fn write_plots(p: &PlotInputs<'_>, out: &Path) -> Result<Vec<PlotFile>, DiagnoseError> {
    let mut files = Vec::new();

    // 1. Track error per frame, before (red) and after (blue) the extension.
    let base_mm: Vec<f64> = p.base_track.iter().map(|v| 1e3 * v).collect();
    let after_mm: Option<Vec<f64>> = p
        .extended_track
        .map(|a| a.iter().map(|v| 1e3 * v).collect());
    let extended_label = format!("extended with {}", p.diagnosis.cause);
    let mut series = vec![ChartSeries {
        values: &base_mm,
        color: RED,
        label: "fitted model",
    }];
    if let Some(after) = &after_mm {
        series.push(ChartSeries {
            values: after,
            color: BLUE,
            label: &extended_label,
        });
    }
    let validation_start = crate::selection_frames(p.split.train).validation[0];
    let chart = line_chart(
        &series,
        &ChartOptions {
            width: 640,
            height: 320,
            scale: ValueScale::Linear,
            markers: vec![validation_start, p.split.test[0]],
            title: "Track error per frame (dashed: validation frames, then test split, start)"
                .into(),
            x_label: "frame".into(),
            y_label: "track error (mm)".into(),
        },
    )?;
    save(&chart, out, "error_vs_time.png")?;
    let max_err = p
        .base_track
        .iter()
        .chain(p.extended_track.unwrap_or(&[]))
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max);
    files.push(PlotFile {
        file: "error_vs_time.png".into(),
        caption: format!(
            "Track error per frame (x: frame 0–{}, y: 0–{:.1} mm). Red: fitted model; blue: \
             extended model. Dashed lines: start of the validation frames that chose the \
             cause (frame {}) and of the held-out test split (frame {}).",
            p.base_track.len().saturating_sub(1),
            1e3 * max_err,
            validation_start,
            p.split.test[0]
        ),
    });

    // 2. Error map on the object: tracked points at frame 0 projected on
    // (main axis, up) — or (main axis, second axis) for flat objects —
    // coloured by their test-split error.
    let tracks = &p.bundle.tracks.object_points;
    let first: Vec<[f64; 3]> = (0..tracks.shape()[1])
        .map(|k| [0, 1, 2].map(|a| tracks[[0, k, a]] as f64))
        .collect();
    let heights: Vec<f64> = first.iter().map(|q| dot(*q, p.up)).collect();
    let extent = |v: &[f64]| {
        v.iter().copied().fold(f64::NEG_INFINITY, f64::max)
            - v.iter().copied().fold(f64::INFINITY, f64::min)
    };
    let along: Vec<f64> = first.iter().map(|q| dot(*q, p.axis)).collect();
    let cross_axis = {
        let c = [
            p.up[1] * p.axis[2] - p.up[2] * p.axis[1],
            p.up[2] * p.axis[0] - p.up[0] * p.axis[2],
            p.up[0] * p.axis[1] - p.up[1] * p.axis[0],
        ];
        let n = norm(c).max(1e-12);
        c.map(|x| x / n)
    };
    let across: Vec<f64> = first.iter().map(|q| dot(*q, cross_axis)).collect();
    let flat = extent(&heights) < 0.3 * extent(&across);
    let vertical = if flat { &across } else { &heights };
    let mut frame = Frame::new(560, 420, along.iter().copied(), vertical.iter().copied());
    // Equal scale on both axes (a rope stays a rope): widen the narrower
    // range about its centre to the canvas's aspect.
    let (sx, sy) = (frame.x.1 - frame.x.0, frame.y.1 - frame.y.0);
    let per_px = (sx / 500.0).max(sy / 360.0);
    let (cx, cy) = (0.5 * (frame.x.0 + frame.x.1), 0.5 * (frame.y.0 + frame.y.1));
    frame.x = (cx - 250.0 * per_px, cx + 250.0 * per_px);
    frame.y = (cy - 180.0 * per_px, cy + 180.0 * per_px);
    let mut img = canvas(560, 420);
    let errs: Vec<f64> = p.per_track_test.to_vec();
    let emax = robust_abs_max(&errs);
    let mut order: Vec<usize> = (0..first.len()).collect();
    order.sort_by(|&a, &b| errs[a].total_cmp(&errs[b]));
    for k in order {
        if !errs[k].is_finite() {
            continue;
        }
        let (x, y) = frame.px(along[k], vertical[k]);
        dot_at(&mut img, x, y, 4, heat(errs[k] / emax));
    }
    for h in dm_model::hand_anchors(p.bundle, 0) {
        let v = if flat {
            dot(h, cross_axis)
        } else {
            dot(h, p.up)
        };
        let (x, y) = frame.px(dot(h, p.axis), v);
        dot_at(&mut img, x, y, 6, [20, 20, 20]);
    }
    save(&img, out, "error_map.png")?;
    files.push(PlotFile {
        file: "error_map.png".into(),
        caption: format!(
            "Error map: each tracked point at frame 0, seen {} (x: main axis, {:.0} mm wide), \
             coloured by its mean test-split track error (blue 0 → red ≥ {:.1} mm). Black \
             dots: hand anchors at frame 0.",
            if flat { "from above" } else { "from the side" },
            1e3 * extent(&along),
            1e3 * emax
        ),
    });

    // 3. Residual acceleration against velocity: the component along the
    // velocity direction against the speed (drag / friction make a
    // negative slope through the origin), and the horizontal residual
    // (tilt makes an off-centre cloud).
    let speeds: Vec<f64> = p.samples.iter().map(|s| norm(s.velocity)).collect();
    let along_v: Vec<f64> = p
        .samples
        .iter()
        .zip(&speeds)
        .map(|(s, v)| {
            if *v > 0.0 {
                dot(s.residual, s.velocity) / v
            } else {
                0.0
            }
        })
        .collect();
    let amax = robust_abs_max(&along_v);
    let vmax = robust_abs_max(&speeds);
    let (east, north) = crate::candidates::horizontal_basis(p.up);
    let hx: Vec<f64> = p.samples.iter().map(|s| dot(s.residual, east)).collect();
    let hy: Vec<f64> = p.samples.iter().map(|s| dot(s.residual, north)).collect();
    let hmax = robust_abs_max(&hx).max(robust_abs_max(&hy));
    let k = p.diagnosis.signatures.drag_rate_per_s;
    let mean = p.diagnosis.signatures.horizontal_accel;
    let img = draw_with_plotters(900, 420, |root| {
        let (left, right) = root.split_horizontally(450);
        let in_range = |x: f64, y: f64, xr: &std::ops::Range<f64>, yr: &std::ops::Range<f64>| {
            (xr.start..=xr.end).contains(&x) && (yr.start..=yr.end).contains(&y)
        };
        let (xr, yr) = (0.0..vmax, -amax..amax);
        let mut chart = scatter_panel(
            &left,
            [
                "Residual along the velocity",
                "speed (m/s)",
                "residual · v̂ (m/s²)",
            ],
            xr.clone(),
            yr.clone(),
            speeds
                .iter()
                .zip(&along_v)
                .map(|(v, a)| (*v, *a))
                .filter(|(v, a)| in_range(*v, *a, &xr, &yr)),
        )?;
        chart
            .draw_series(LineSeries::new(
                [(0.0, 0.0), (vmax, (-k * vmax).clamp(-amax, amax))],
                rgb(RED).stroke_width(2),
            ))?
            .label(format!("fit r = −k v, k = {k:.2} /s"))
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], rgb(RED).stroke_width(2)));
        draw_legend(&mut chart)?;
        let (xr, yr) = (-hmax..hmax, -hmax..hmax);
        let mut chart = scatter_panel(
            &right,
            ["Horizontal residual", "east (m/s²)", "north (m/s²)"],
            xr.clone(),
            yr.clone(),
            hx.iter()
                .zip(&hy)
                .map(|(x, y)| (*x, *y))
                .filter(|(x, y)| in_range(*x, *y, &xr, &yr)),
        )?;
        chart
            .draw_series(std::iter::once(Circle::new(
                (dot(mean, east), dot(mean, north)),
                6,
                rgb(RED).filled(),
            )))?
            .label("mean (a tilted gravity moves it off 0)")
            .legend(|(x, y)| Circle::new((x + 9, y), 4, rgb(RED).filled()));
        draw_legend(&mut chart)?;
        Ok(())
    })?;
    save(&img, out, "residual_vs_velocity.png")?;
    files.push(PlotFile {
        file: "residual_vs_velocity.png".into(),
        caption: format!(
            "Residual accelerations (observed − simulated, second differences over ±{} frames). \
             Left: component along the velocity (y: ±{:.2} m/s²) against speed (x: 0–{:.2} m/s); \
             red: least-squares r = −k v (k = {:.2} /s) — drag or friction tilt the cloud \
             downwards. Right: horizontal residual (x: world +x, y: world +y for +z up; \
             ±{:.2} m/s²); red dot: its mean — a tilted gravity moves it off the centre.",
            crate::analysis::ACCEL_STRIDE,
            amax,
            vmax,
            p.diagnosis.signatures.drag_rate_per_s,
            hmax
        ),
    });

    // 4. Candidate scores (bars) with the threshold (grey line).
    let cands = &p.diagnosis.candidates;
    // The top and bottom leave room for the value written beyond each bar
    // (a bar ending at the axis looked cut off); a bar past a cap is drawn
    // to the cap and its value says how far it goes.
    let top = cands
        .iter()
        .map(|c| c.score)
        .fold(p.diagnosis.threshold * 1.5, f64::max)
        .min(1.0);
    let bottom = cands.iter().map(|c| c.score).fold(0.0, f64::min).max(-0.3);
    let room = 0.15 * (top - bottom);
    let (smin, smax) = (bottom - room, top + room);
    let n = cands.len().max(1);
    let threshold = p.diagnosis.threshold;
    let img = draw_with_plotters(960, 340, |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(
                "Score per candidate (red: the named cause; dashed: `none` threshold)",
                (FONT_FAMILY, 15),
            )
            .margin(10)
            .x_label_area_size(50)
            .y_label_area_size(60)
            // An integer range's end is a key point of its own: 0..n−1
            // makes exactly n segments.
            .build_cartesian_2d((0..n - 1).into_segmented(), smin..smax)?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(n)
            .x_label_formatter(&|v| match v {
                SegmentValue::CenterOf(i) => {
                    cands.get(*i).map_or(String::new(), |c| c.name.clone())
                }
                _ => String::new(),
            })
            .y_desc("score")
            .y_label_formatter(&|v| dm_view::chart::format_tick(*v))
            .label_style((FONT_FAMILY, 11))
            .axis_desc_style((FONT_FAMILY, 13))
            .draw()?;
        chart.draw_series(cands.iter().enumerate().map(|(i, c)| {
            let color = if c.name == p.diagnosis.cause {
                RED
            } else {
                BLUE
            };
            let mut bar = Rectangle::new(
                [
                    (SegmentValue::Exact(i), 0.0),
                    (SegmentValue::Exact(i + 1), c.score.clamp(bottom, top)),
                ],
                rgb(color).filled(),
            );
            bar.set_margin(0, 0, 8, 8);
            bar
        }))?;
        chart.draw_series(cands.iter().enumerate().map(|(i, c)| {
            let end = c.score.clamp(bottom, top);
            let (y, v) = if c.score >= 0.0 {
                (end + 0.02 * (smax - smin), VPos::Bottom)
            } else {
                (end - 0.02 * (smax - smin), VPos::Top)
            };
            Text::new(
                format!("{:.3}", c.score),
                (SegmentValue::CenterOf(i), y),
                (FONT_FAMILY, 12)
                    .into_font()
                    .color(&BLACK)
                    .pos(Pos::new(HPos::Center, v)),
            )
        }))?;
        chart.draw_series(DashedLineSeries::new(
            [
                (SegmentValue::Exact(0), threshold),
                (SegmentValue::Last, threshold),
            ],
            6,
            4,
            rgb(GREY).stroke_width(1),
        ))?;
        Ok(())
    })?;
    save(&img, out, "candidates.png")?;
    files.push(PlotFile {
        file: "candidates.png".into(),
        caption: format!(
            "Score per candidate, named under its bar, in the table's order (red: the named cause; \
             y: {:.2} to {:.2}, each bar's score written at its end); dashed grey: the `none` threshold {:.2}.",
            smin,
            smax,
            p.diagnosis.threshold
        ),
    });

    // 5. The learned residual's mean |Δv| per frame, if the model has one.
    if !p.residual_dv.is_empty() {
        let chart = line_chart(
            &[ChartSeries {
                values: p.residual_dv,
                color: BLUE,
                label: "",
            }],
            &ChartOptions {
                width: 640,
                height: 260,
                scale: ValueScale::Linear,
                markers: vec![p.split.test[0]],
                title: "The learned residual's mean |Δv| per frame".into(),
                x_label: "frame".into(),
                y_label: "|Δv| (m/s)".into(),
            },
        )?;
        save(&chart, out, "residual_dv.png")?;
        files.push(PlotFile {
            file: "residual_dv.png".into(),
            caption: format!(
                "The learned residual's mean |Δv| per frame (y: up to {:.4} m/s).",
                p.residual_dv.iter().copied().fold(0.0, f64::max)
            ),
        });
    }
    Ok(files)
}
