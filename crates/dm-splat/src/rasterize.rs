//! Front-to-back alpha compositing of depth-sorted splats per 16×16 tile.
//!
//! For pixel centre `p` and a splat with centre `μ`, conic `(A, B, C)` and
//! opacity `o`: `d = p − μ`, `power = −½(A dx² + C dy²) − B dx dy`,
//! `α = min(0.99, o·exp(power))`. Splats with `power > 0` (only possible
//! from round-off in a near-singular conic) or `α < 1/255` are skipped; the
//! walk stops before the splat that would bring the transmittance below
//! 1e-4 (that splat is not drawn — 3DGS's rule). The pixel is
//! `Σ cᵢ αᵢ Tᵢ + T_final · background`.

use dm_mpm::real::Real;
use nalgebra::Vector3;
use rayon::prelude::*;

use crate::project::Projected;
use crate::tiles::{TILE_SIZE, TileBins};

/// Splats fainter than this at a pixel are skipped.
pub const ALPHA_MIN: f64 = 1.0 / 255.0;
/// Cap on a single splat's alpha, so transmittance never hits zero and the
/// backward pass can divide by `1 − α`.
pub const ALPHA_MAX: f64 = 0.99;
/// The walk stops once the transmittance would fall below this.
pub const TRANSMITTANCE_MIN: f64 = 1e-4;
/// Below `ln(ALPHA_MIN / o)` minus this, `o·exp(power)` is below
/// [`ALPHA_MIN`] whatever the rounding of `exp` and `ln` (a relative
/// 1e-3, far above f32's): such pixels are skipped without `exp`, which
/// most pixels of a tile's splats are, and the image is unchanged.
const POWER_FLOOR_MARGIN: f64 = 1e-3;

/// Alpha of one splat at one pixel, as used by forward and backward alike.
#[derive(Debug, Clone, Copy)]
pub(crate) struct SplatAlpha<T> {
    pub alpha: T,
    /// `exp(power)`.
    pub falloff: T,
    pub dx: T,
    pub dy: T,
    /// Whether `o·exp(power)` was above [`ALPHA_MAX`] (no gradient then).
    pub clamped: bool,
}

#[inline(always)]
pub(crate) fn splat_alpha<T: Real>(
    splats: &TileSplats<T>,
    k: usize,
    px: T,
    py: T,
) -> Option<SplatAlpha<T>> {
    let (mean2d, conic, opacity) = (&splats.mean2d[k], &splats.conic[k], splats.opacity[k]);
    let dx = px - mean2d[0];
    let dy = py - mean2d[1];
    let power = T::lit(-0.5) * (conic[0] * dx * dx + conic[2] * dy * dy) - conic[1] * dx * dy;
    if power > T::zero() || power < splats.power_floor[k] {
        return None;
    }
    let falloff = power.exp();
    let raw = opacity * falloff;
    let alpha_max = T::lit(ALPHA_MAX);
    let clamped = raw > alpha_max;
    let alpha = if clamped { alpha_max } else { raw };
    if alpha < T::lit(ALPHA_MIN) {
        return None;
    }
    Some(SplatAlpha {
        alpha,
        falloff,
        dx,
        dy,
        clamped,
    })
}

/// The splats of one tile gathered contiguously (cache-friendly inner loop).
#[derive(Debug)]
pub(crate) struct TileSplats<T> {
    pub mean2d: Vec<[T; 2]>,
    pub conic: Vec<[T; 3]>,
    pub opacity: Vec<T>,
    pub color: Vec<Vector3<T>>,
    /// Where `power` leaves a splat certainly below [`ALPHA_MIN`].
    pub power_floor: Vec<T>,
}

impl<T: Real> TileSplats<T> {
    pub fn gather(ids: &[u32], projected: &Projected<T>, colors: &[Vector3<T>]) -> Self {
        let idx = |i: &u32| *i as usize;
        Self {
            mean2d: ids.iter().map(|i| projected.mean2d[idx(i)]).collect(),
            conic: ids.iter().map(|i| projected.conic[idx(i)]).collect(),
            opacity: ids.iter().map(|i| projected.opacity[idx(i)]).collect(),
            color: ids.iter().map(|i| colors[idx(i)]).collect(),
            power_floor: ids
                .iter()
                .map(|i| {
                    (T::lit(ALPHA_MIN) / projected.opacity[idx(i)]).ln()
                        - T::lit(POWER_FLOOR_MARGIN)
                })
                .collect(),
        }
    }
}

/// Forward result: the image and what the backward pass needs per pixel.
#[derive(Debug, Clone)]
pub struct Rasterized<T: Real> {
    pub width: u32,
    pub height: u32,
    /// Row-major RGB.
    pub image: Vec<[T; 3]>,
    /// Transmittance left after the last drawn splat (1 − coverage).
    pub final_transmittance: Vec<T>,
    /// One past the position (in the pixel's tile list) of the last splat
    /// the walk looked at before stopping; the backward walk starts there.
    pub walk_end: Vec<u32>,
}

/// Pixel rectangle of a tile, clipped to the image: `(x0, y0, x1, y1)`.
#[inline]
pub(crate) fn tile_pixels(
    tile: usize,
    tiles_x: u32,
    width: u32,
    height: u32,
) -> (u32, u32, u32, u32) {
    let tx = tile as u32 % tiles_x;
    let ty = tile as u32 / tiles_x;
    let x0 = tx * TILE_SIZE;
    let y0 = ty * TILE_SIZE;
    (
        x0,
        y0,
        (x0 + TILE_SIZE).min(width),
        (y0 + TILE_SIZE).min(height),
    )
}

/// Composites every tile (in parallel; each pixel is computed by exactly
/// one task, in a fixed order).
pub fn rasterize<T: Real>(
    projected: &Projected<T>,
    colors: &[Vector3<T>],
    bins: &TileBins,
    width: u32,
    height: u32,
    background: [T; 3],
) -> Rasterized<T> {
    let transmittance_min = T::lit(TRANSMITTANCE_MIN);
    let background = Vector3::from(background);
    let tiles: Vec<Vec<([T; 3], T, u32)>> = (0..bins.tile_count())
        .into_par_iter()
        .map(|tile| {
            let splats = TileSplats::gather(bins.tile_list(tile), projected, colors);
            let (x0, y0, x1, y1) = tile_pixels(tile, bins.tiles_x, width, height);
            let mut out = Vec::with_capacity(((x1 - x0) * (y1 - y0)) as usize);
            for y in y0..y1 {
                let py = T::from_index(y as usize) + T::lit(0.5);
                for x in x0..x1 {
                    let px = T::from_index(x as usize) + T::lit(0.5);
                    let mut transmittance = T::one();
                    let mut color = Vector3::<T>::zeros();
                    let mut walk_end = 0u32;
                    for k in 0..splats.mean2d.len() {
                        walk_end = k as u32 + 1;
                        let Some(s) = splat_alpha(&splats, k, px, py) else {
                            continue;
                        };
                        let next = transmittance * (T::one() - s.alpha);
                        if next < transmittance_min {
                            walk_end = k as u32;
                            break;
                        }
                        color += splats.color[k] * (s.alpha * transmittance);
                        transmittance = next;
                    }
                    color += background * transmittance;
                    out.push(([color.x, color.y, color.z], transmittance, walk_end));
                }
            }
            out
        })
        .collect();
    let pixels = width as usize * height as usize;
    let mut result = Rasterized {
        width,
        height,
        image: vec![[T::zero(); 3]; pixels],
        final_transmittance: vec![T::one(); pixels],
        walk_end: vec![0; pixels],
    };
    for (tile, values) in tiles.into_iter().enumerate() {
        let (x0, y0, x1, y1) = tile_pixels(tile, bins.tiles_x, width, height);
        let mut values = values.into_iter();
        for y in y0..y1 {
            for x in x0..x1 {
                if let Some((c, t, end)) = values.next() {
                    let p = (y * width + x) as usize;
                    result.image[p] = c;
                    result.final_transmittance[p] = t;
                    result.walk_end[p] = end;
                }
            }
        }
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The largest value below `x`.
    fn next_down(x: f32) -> f32 {
        if x > 0.0 {
            f32::from_bits(x.to_bits() - 1)
        } else {
            f32::from_bits(x.to_bits() + 1)
        }
    }

    /// The early skip changes no pixel: at the largest power below the
    /// floor, `o·exp(power)` is already below ALPHA_MIN, for opacities
    /// from 1e-6 to 1 (f32, the renderer's precision).
    #[test]
    fn the_power_floor_skips_only_splats_below_the_alpha_threshold() {
        for step in 0..=600 {
            let opacity = 10f32.powf(-6.0 + 0.01 * step as f32);
            let floor = (ALPHA_MIN as f32 / opacity).ln() - POWER_FLOOR_MARGIN as f32;
            let power = next_down(floor).min(0.0);
            let alpha = opacity * power.exp();
            assert!(
                alpha < ALPHA_MIN as f32,
                "opacity {opacity}: skipped at power {power} with alpha {alpha}"
            );
        }
    }
}
