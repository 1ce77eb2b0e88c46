//! Reverse mode of [`rasterize`](crate::rasterize::rasterize).
//!
//! Each pixel is walked back to front from where the forward walk stopped,
//! reconstructing the transmittance before each splat as `Tᵢ = Tᵢ₊₁ / (1 −
//! αᵢ)` (αᵢ ≤ 0.99, so the division is safe) and carrying the colour
//! "behind" splat i, `Bᵢ = αᵢ₊₁ cᵢ₊₁ + (1 − αᵢ₊₁) Bᵢ₊₁` (B = background
//! past the last splat). With `g = ∂L/∂pixel`:
//! `∂L/∂cᵢ = αᵢ Tᵢ g` and `∂L/∂αᵢ = Tᵢ (cᵢ − Bᵢ)·g`; α then goes to the
//! opacity (`∂α/∂o = exp(power)`) and through `power` to the 2D mean and
//! the conic, except where α was clamped at 0.99 (zero there).
//!
//! Determinism: each tile accumulates into its own per-entry buffer, pixel
//! by pixel in a fixed order; entries are then summed into their Gaussians
//! in tile order on one thread. No atomics, no thread-dependent order.

use dm_mpm::real::Real;
use nalgebra::Vector3;
use rayon::prelude::*;

use crate::project::Projected;
use crate::rasterize::{Rasterized, TileSplats, splat_alpha, tile_pixels};
use crate::tiles::TileBins;

/// Gradients with respect to the rasterizer's inputs, per Gaussian.
#[derive(Debug, Clone, PartialEq)]
pub struct ProjectedGrads<T: Real> {
    pub mean2d: Vec<[T; 2]>,
    /// With respect to `(A, B, C)` of the conic as stored (B once).
    pub conic: Vec<[T; 3]>,
    /// With respect to the opacity after the sigmoid.
    pub opacity: Vec<T>,
    pub color: Vec<Vector3<T>>,
}

impl<T: Real> ProjectedGrads<T> {
    pub fn zeros(n: usize) -> Self {
        Self {
            mean2d: vec![[T::zero(); 2]; n],
            conic: vec![[T::zero(); 3]; n],
            opacity: vec![T::zero(); n],
            color: vec![Vector3::zeros(); n],
        }
    }
}

/// Gradient contributions of one (tile, Gaussian) entry.
#[derive(Debug, Clone, Copy)]
struct EntryGrad<T: Real> {
    mean2d: [T; 2],
    conic: [T; 3],
    opacity: T,
    color: Vector3<T>,
}

impl<T: Real> EntryGrad<T> {
    fn zero() -> Self {
        Self {
            mean2d: [T::zero(); 2],
            conic: [T::zero(); 3],
            opacity: T::zero(),
            color: Vector3::zeros(),
        }
    }
}

/// Vector-Jacobian product of the rasterizer: `grad_image` is `∂L/∂image`
/// (row-major RGB, one entry per pixel).
pub fn rasterize_backward<T: Real>(
    projected: &Projected<T>,
    colors: &[Vector3<T>],
    bins: &TileBins,
    forward: &Rasterized<T>,
    background: [T; 3],
    grad_image: &[[T; 3]],
) -> ProjectedGrads<T> {
    let (width, height) = (forward.width, forward.height);
    let background = Vector3::from(background);
    let half = T::lit(0.5);
    let per_tile: Vec<Vec<EntryGrad<T>>> = (0..bins.tile_count())
        .into_par_iter()
        .map(|tile| {
            let splats = TileSplats::gather(bins.tile_list(tile), projected, colors);
            let mut grads = vec![EntryGrad::zero(); splats.mean2d.len()];
            let (x0, y0, x1, y1) = tile_pixels(tile, bins.tiles_x, width, height);
            for y in y0..y1 {
                let py = T::from_index(y as usize) + half;
                for x in x0..x1 {
                    let p = (y * width + x) as usize;
                    let g = Vector3::from(grad_image[p]);
                    if g.iter().all(|c| *c == T::zero()) {
                        continue;
                    }
                    let px = T::from_index(x as usize) + half;
                    let mut transmittance = forward.final_transmittance[p];
                    let mut behind = background;
                    for k in (0..forward.walk_end[p] as usize).rev() {
                        let Some(s) = splat_alpha(&splats, k, px, py) else {
                            continue;
                        };
                        let one_minus_alpha = T::one() - s.alpha;
                        transmittance /= one_minus_alpha;
                        let color = splats.color[k];
                        let entry = &mut grads[k];
                        entry.color += g * (s.alpha * transmittance);
                        let grad_alpha = transmittance * (color - behind).dot(&g);
                        behind = color * s.alpha + behind * one_minus_alpha;
                        if s.clamped {
                            continue;
                        }
                        entry.opacity += grad_alpha * s.falloff;
                        let grad_power = grad_alpha * s.alpha;
                        let conic = &splats.conic[k];
                        entry.conic[0] -= half * s.dx * s.dx * grad_power;
                        entry.conic[1] -= s.dx * s.dy * grad_power;
                        entry.conic[2] -= half * s.dy * s.dy * grad_power;
                        entry.mean2d[0] += (conic[0] * s.dx + conic[1] * s.dy) * grad_power;
                        entry.mean2d[1] += (conic[2] * s.dy + conic[1] * s.dx) * grad_power;
                    }
                }
            }
            grads
        })
        .collect();
    let mut out = ProjectedGrads::zeros(projected.len());
    for (tile, grads) in per_tile.iter().enumerate() {
        for (&id, e) in bins.tile_list(tile).iter().zip(grads) {
            let i = id as usize;
            out.mean2d[i][0] += e.mean2d[0];
            out.mean2d[i][1] += e.mean2d[1];
            for c in 0..3 {
                out.conic[i][c] += e.conic[c];
            }
            out.opacity[i] += e.opacity;
            out.color[i] += e.color;
        }
    }
    out
}
