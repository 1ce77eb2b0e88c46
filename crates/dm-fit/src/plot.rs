//! A loss curve as a PNG: log-scale loss per iteration, with the stage
//! boundary marked (drawn with plain pixels: no font needed).

use image::{Rgb, RgbImage};

/// Plots `losses` (one per iteration); a grey line marks where stage 2
/// starts (after `stage1_iterations`).
pub fn loss_curve(losses: &[f64], stage1_iterations: usize) -> RgbImage {
    let (w, h, margin) = (640u32, 360u32, 30i64);
    let mut img = RgbImage::from_pixel(w, h, Rgb([255, 255, 255]));
    let finite: Vec<f64> = losses
        .iter()
        .copied()
        .filter(|v| v.is_finite() && *v > 0.0)
        .collect();
    let axis = Rgb([60, 60, 60]);
    let (x0, y0, x1, y1) = (margin, margin, w as i64 - margin, h as i64 - margin);
    let put = |img: &mut RgbImage, x: i64, y: i64, c: Rgb<u8>| {
        if x >= 0 && y >= 0 && x < w as i64 && y < h as i64 {
            img.put_pixel(x as u32, y as u32, c);
        }
    };
    for x in x0..=x1 {
        put(&mut img, x, y1, axis);
    }
    for y in y0..=y1 {
        put(&mut img, x0, y, axis);
    }
    if finite.len() < 2 {
        return img;
    }
    let (lo, hi) = finite
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v.log10()), b.max(v.log10()))
        });
    let span = (hi - lo).max(1e-9);
    let n = losses.len().max(2) - 1;
    let px = |i: usize| x0 + ((x1 - x0) as f64 * i as f64 / n as f64) as i64;
    let py = |v: f64| y1 - ((y1 - y0) as f64 * (v.log10() - lo) / span) as i64;
    if stage1_iterations > 0 && stage1_iterations < losses.len() {
        let x = px(stage1_iterations);
        for y in (y0..=y1).step_by(3) {
            put(&mut img, x, y, Rgb([170, 170, 170]));
        }
    }
    let line = Rgb([200, 40, 40]);
    for i in 1..losses.len() {
        let (a, b) = (losses[i - 1], losses[i]);
        if !(a.is_finite() && b.is_finite() && a > 0.0 && b > 0.0) {
            continue;
        }
        let (xa, ya, xb, yb) = (px(i - 1), py(a), px(i), py(b));
        let steps = (xb - xa).abs().max((yb - ya).abs()).max(1);
        for s in 0..=steps {
            let x = xa + (xb - xa) * s / steps;
            let y = ya + (yb - ya) * s / steps;
            for d in -1..=1 {
                put(&mut img, x, y + d, line);
            }
        }
    }
    img
}
