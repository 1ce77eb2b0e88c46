//! Object and hand masks without learned weights: a depth model of the
//! scene (what stands above the calibrated floor), a colour model of the
//! hands, and OpenCV's GrabCut to settle the object's boundary.
//!
//! Per pixel: depth (3×3 median of valid values) lifted to the world gives
//! its height above the floor. Pixels clearly on the floor are background;
//! pixels above it are the object or a hand; hand-coloured ones (in
//! brightness-free chromaticity, so shading does not matter) start as
//! probable background, the rest as probable object, and GrabCut's colour
//! GMMs and smoothness term decide. Whatever stands above the floor and is
//! not the object is hand.

use dm_view::Camera;
use image::{GrayImage, Luma, RgbImage};
use opencv::core::{Mat, Rect, Scalar};
use opencv::prelude::{MatTraitConstManual, MatTraitManual};

/// Settings of the fallback segmentation.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SegmentOptions {
    /// Height above the floor (m) from which a pixel belongs to something.
    pub min_height_m: f64,
    /// Height below which a pixel is surely floor (m).
    pub floor_band_m: f64,
    /// Hand (skin or glove) albedo, RGB in [0, 1]. The default is the skin of
    /// dm-synth's scripted hands; real captures pass their own.
    pub hand_color: [f32; 3],
    /// Chromaticity distance under which a pixel looks like a hand.
    pub hand_chroma_tolerance: f32,
    /// GrabCut iterations (0: the depth/colour model alone).
    pub grabcut_iterations: i32,
}

impl Default for SegmentOptions {
    fn default() -> Self {
        Self {
            min_height_m: 0.005,
            floor_band_m: 0.0025,
            hand_color: [0.86, 0.66, 0.55],
            hand_chroma_tolerance: 0.03,
            grabcut_iterations: 2,
        }
    }
}

/// The two masks of one frame (0 or 255).
#[derive(Clone, Debug)]
pub struct FrameMasks {
    pub object: GrayImage,
    pub hand: GrayImage,
}

fn chromaticity(c: [f32; 3]) -> [f32; 2] {
    let s = (c[0] + c[1] + c[2]).max(1e-3);
    [c[0] / s, c[1] / s]
}

/// Median of the valid (finite, positive) values of a 3×3 window.
pub fn median_filter_depth(depth: &[f32], width: usize, height: usize) -> Vec<f32> {
    let mut out = vec![f32::NAN; depth.len()];
    let mut window = Vec::with_capacity(9);
    for y in 0..height {
        for x in 0..width {
            window.clear();
            for yy in y.saturating_sub(1)..(y + 2).min(height) {
                for xx in x.saturating_sub(1)..(x + 2).min(width) {
                    let d = depth[yy * width + xx];
                    if d.is_finite() && d > 0.0 {
                        window.push(d);
                    }
                }
            }
            if window.len() >= 3 {
                window.sort_by(f32::total_cmp);
                out[y * width + x] = window[window.len() / 2];
            }
        }
    }
    out
}

/// Height above the floor of every pixel (NaN where depth is missing).
pub fn heights_above_floor(
    camera: &Camera,
    depth_m: &[f32],
    up: [f64; 3],
    floor_height_m: f64,
) -> Vec<f32> {
    let width = camera.width as usize;
    depth_m
        .iter()
        .enumerate()
        .map(|(i, &d)| {
            if !d.is_finite() {
                return f32::NAN;
            }
            let (u, v) = ((i % width) as f64 + 0.5, (i / width) as f64 + 0.5);
            let p = camera.unproject(u, v, f64::from(d));
            (p.x * up[0] + p.y * up[1] + p.z * up[2] - floor_height_m) as f32
        })
        .collect()
}

/// Segments one frame of one camera. `depth_m` is the raw sensor depth.
pub fn segment_frame(
    camera: &Camera,
    rgb: &RgbImage,
    depth_m: &[f32],
    up: [f64; 3],
    floor_height_m: f64,
    options: &SegmentOptions,
) -> opencv::Result<FrameMasks> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let smooth = median_filter_depth(depth_m, w, h);
    let heights = heights_above_floor(camera, &smooth, up, floor_height_m);
    let hand_chroma = chromaticity(options.hand_color);
    let looks_like_hand = |x: u32, y: u32| {
        let p = rgb.get_pixel(x, y).0.map(|v| f32::from(v) / 255.0);
        let c = chromaticity(p);
        ((c[0] - hand_chroma[0]).powi(2) + (c[1] - hand_chroma[1]).powi(2)).sqrt()
            < options.hand_chroma_tolerance
    };
    // GrabCut labels: 0 background, 1 foreground, 2 probable bg, 3 probable fg.
    let mut labels = vec![opencv::imgproc::GC_PR_BGD as u8; w * h];
    let mut above = vec![false; w * h];
    let (mut x0, mut y0, mut x1, mut y1) = (w, h, 0usize, 0usize);
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let height = heights[i];
            if height.is_nan() {
                continue;
            }
            if f64::from(height) < options.floor_band_m {
                labels[i] = opencv::imgproc::GC_BGD as u8;
            } else if f64::from(height) >= options.min_height_m {
                above[i] = true;
                if !looks_like_hand(x as u32, y as u32) {
                    labels[i] = opencv::imgproc::GC_PR_FGD as u8;
                    x0 = x0.min(x);
                    y0 = y0.min(y);
                    x1 = x1.max(x);
                    y1 = y1.max(y);
                }
            }
        }
    }
    let mut object = GrayImage::new(w as u32, h as u32);
    let mut hand = GrayImage::new(w as u32, h as u32);
    if x1 < x0 {
        // Nothing but floor (or hands) in view.
        for (i, &a) in above.iter().enumerate() {
            if a {
                hand.put_pixel((i % w) as u32, (i / w) as u32, Luma([255]));
            }
        }
        return Ok(FrameMasks { object, hand });
    }
    let mut is_object: Vec<bool> = labels
        .iter()
        .map(|&l| l == opencv::imgproc::GC_PR_FGD as u8)
        .collect();
    if options.grabcut_iterations > 0 {
        // GrabCut on the object's box, widened so it sees some background.
        let margin = 12;
        let rx0 = x0.saturating_sub(margin);
        let ry0 = y0.saturating_sub(margin);
        let rx1 = (x1 + margin + 1).min(w);
        let ry1 = (y1 + margin + 1).min(h);
        let (rw, rh) = (rx1 - rx0, ry1 - ry0);
        let crop =
            image::imageops::crop_imm(rgb, rx0 as u32, ry0 as u32, rw as u32, rh as u32).to_image();
        let bgr = dm_capture::video::rgb_to_bgr_mat(&crop)?;
        let mut mask = Mat::new_rows_cols_with_default(
            rh as i32,
            rw as i32,
            opencv::core::CV_8UC1,
            Scalar::all(0.0),
        )?;
        let mut has = [false; 4];
        for y in 0..rh {
            let row = mask.at_row_mut::<u8>(y as i32)?;
            for x in 0..rw {
                let l = labels[(y + ry0) * w + x + rx0];
                row[x] = l;
                has[l as usize] = true;
            }
        }
        // GrabCut needs samples of both sides to fit its colour models.
        if (has[0] || has[2]) && (has[1] || has[3]) {
            let mut bgd = Mat::default();
            let mut fgd = Mat::default();
            opencv::imgproc::grab_cut(
                &bgr,
                &mut mask,
                Rect::new(0, 0, rw as i32, rh as i32),
                &mut bgd,
                &mut fgd,
                options.grabcut_iterations,
                opencv::imgproc::GC_INIT_WITH_MASK,
            )?;
            for y in 0..rh {
                let row = mask.at_row::<u8>(y as i32)?;
                for x in 0..rw {
                    let l = i32::from(row[x]);
                    let i = (y + ry0) * w + x + rx0;
                    // The object stands above the floor: GrabCut may only
                    // move the boundary within what depth left uncertain.
                    is_object[i] = (l == opencv::imgproc::GC_FGD
                        || l == opencv::imgproc::GC_PR_FGD)
                        && labels[i] != opencv::imgproc::GC_BGD as u8;
                }
            }
        }
    }
    for i in 0..w * h {
        let (x, y) = ((i % w) as u32, (i / w) as u32);
        if is_object[i] {
            object.put_pixel(x, y, Luma([255]));
        } else if above[i] {
            hand.put_pixel(x, y, Luma([255]));
        }
    }
    Ok(FrameMasks { object, hand })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Vector3};

    /// A camera looking down at a floor with a raised blue box and a
    /// skin-coloured box: the blue one is object, the skin one hand.
    #[test]
    fn separates_object_hand_and_floor() {
        let camera = Camera::look_at(
            Point3::new(0.0, 0.0, 0.6),
            Point3::origin(),
            Vector3::y(),
            64,
            48,
            50.0,
        );
        let (w, h) = (64usize, 48usize);
        let mut rgb = RgbImage::new(w as u32, h as u32);
        let mut depth = vec![0.6f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let floor = if (x / 8 + y / 8) % 2 == 0 {
                    [120, 120, 120]
                } else {
                    [60, 60, 60]
                };
                let (color, z) = if (10..26).contains(&x) && (12..36).contains(&y) {
                    ([40, 80, 200], 0.58)
                } else if (40..54).contains(&x) && (14..30).contains(&y) {
                    ([219, 168, 140], 0.55)
                } else {
                    (floor, 0.6)
                };
                rgb.put_pixel(x as u32, y as u32, image::Rgb(color));
                depth[y * w + x] = z;
            }
        }
        let masks = segment_frame(
            &camera,
            &rgb,
            &depth,
            [0.0, 0.0, 1.0],
            0.0,
            &SegmentOptions::default(),
        )
        .expect("segmentation runs");
        let at = |m: &GrayImage, x: u32, y: u32| m.get_pixel(x, y).0[0] == 255;
        assert!(at(&masks.object, 17, 24) && !at(&masks.hand, 17, 24));
        assert!(at(&masks.hand, 47, 22) && !at(&masks.object, 47, 22));
        assert!(!at(&masks.object, 32, 5) && !at(&masks.hand, 32, 5));
        let object_pixels = masks.object.pixels().filter(|p| p.0[0] == 255).count();
        // 16 × 24 = 384 pixels of box, give or take its boundary.
        assert!((340..=430).contains(&object_pixels), "{object_pixels}");
    }
}
