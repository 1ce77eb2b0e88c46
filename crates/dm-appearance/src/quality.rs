//! Image quality of a splat render against a bundle view, by the
//! benchmark's masking rule (docs/metrics.md, the same rule as dm-eval's
//! `benchmark_pair`): ground truth = observed RGB × object mask on black,
//! prediction = the render on black, hand pixels black in both; images
//! quantised to 8 bits as a saved PNG would be.

use image::{GrayImage, RgbImage};

/// A render (row-major RGB, any range) as an 8-bit image (clamped,
/// rounded).
pub fn to_rgb8(image: &[[f32; 3]], width: u32, height: u32) -> RgbImage {
    let raw: Vec<u8> = image
        .iter()
        .flat_map(|p| p.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8))
        .collect();
    RgbImage::from_raw(width, height, raw).unwrap_or_else(|| RgbImage::new(width, height))
}

/// Rendered coverage at or above which a pixel belongs to the silhouette.
/// Half: Gaussian tails reach 3σ beyond the surface, so "any coverage"
/// (the particle renderer's rule, whose spheres have hard edges) would
/// grow the splat silhouette by a footprint all around (toy, seed 7,
/// frame 0: IoU 0.87 with `> 0` against 0.97 for the spheres).
pub const SILHOUETTE_ALPHA: f32 = 0.5;

/// The rendered silhouette (coverage `1 − T ≥` [`SILHOUETTE_ALPHA`]) as a
/// 0/255 mask.
pub fn alpha_mask(alpha: &[f32], width: u32, height: u32) -> GrayImage {
    let raw: Vec<u8> = alpha
        .iter()
        .map(|&a| if a >= SILHOUETTE_ALPHA { 255 } else { 0 })
        .collect();
    GrayImage::from_raw(width, height, raw).unwrap_or_else(|| GrayImage::new(width, height))
}

/// PSNR (dB, data range 1) of the masked pair; +∞ when identical. Sizes
/// must agree (the caller renders at the camera's size).
pub fn masked_psnr(
    observed: &RgbImage,
    object_mask: &GrayImage,
    hand_mask: &GrayImage,
    rendered: &RgbImage,
) -> f64 {
    let mut squared = 0.0;
    let mut count = 0usize;
    for (x, y, obs) in observed.enumerate_pixels() {
        let hand = hand_mask.get_pixel(x, y).0[0] > 0;
        let object = object_mask.get_pixel(x, y).0[0] > 0;
        let pred = rendered.get_pixel(x, y);
        for c in 0..3 {
            let t = if hand || !object {
                0.0
            } else {
                f64::from(obs.0[c]) / 255.0
            };
            let p = if hand {
                0.0
            } else {
                f64::from(pred.0[c]) / 255.0
            };
            squared += (t - p) * (t - p);
            count += 1;
        }
    }
    let mse = squared / count.max(1) as f64;
    if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (1.0 / mse).log10()
    }
}
