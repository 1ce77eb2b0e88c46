use image::{Rgb, RgbImage};

use crate::Frame;

/// Gap between images in [`side_by_side`], pixels.
const STRIP_GAP_PX: u32 = 4;

/// Concatenates images left to right with a 4 px black gap, top-aligned (shorter
/// images are padded with black). `labels` are accepted for future captions but not
/// drawn yet: no font is bundled.
pub fn side_by_side(images: &[RgbImage], labels: &[&str]) -> RgbImage {
    let _ = labels;
    let height = images.iter().map(RgbImage::height).max().unwrap_or(0);
    let gaps = STRIP_GAP_PX * (images.len().saturating_sub(1) as u32);
    let width = images.iter().map(RgbImage::width).sum::<u32>() + gaps;
    let mut strip = RgbImage::from_pixel(width, height, Rgb([0, 0, 0]));
    let mut x_offset = 0;
    for image in images {
        for (x, y, pixel) in image.enumerate_pixels() {
            strip.put_pixel(x_offset + x, y, *pixel);
        }
        x_offset += image.width() + STRIP_GAP_PX;
    }
    strip
}

/// Adds deterministic per-pixel, per-channel uniform noise in
/// `[-amplitude, amplitude]` to the RGB image (a cheap sensor-noise model). The noise
/// depends only on `(seed, x, y, channel)`, so it is reproducible and independent of
/// threading; results are clamped to `[0, 1]`.
pub fn add_sensor_noise(frame: &mut Frame, amplitude: f32, seed: u64) {
    let width = frame.width as u64;
    for (index, pixel) in frame.rgb.iter_mut().enumerate() {
        let index = index as u64;
        let (x, y) = (index % width.max(1), index / width.max(1));
        for (channel, value) in pixel.iter_mut().enumerate() {
            let hash = split_mix64(seed ^ split_mix64((y << 32) ^ (x << 2) ^ channel as u64));
            // Top 24 bits -> uniform in [0, 1).
            let unit = (hash >> 40) as f32 / (1u64 << 24) as f32;
            *value = (*value + amplitude * (2.0 * unit - 1.0)).clamp(0.0, 1.0);
        }
    }
}

fn split_mix64(mut state: u64) -> u64 {
    state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    state = (state ^ (state >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    state = (state ^ (state >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    state ^ (state >> 31)
}
