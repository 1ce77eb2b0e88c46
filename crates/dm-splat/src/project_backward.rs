//! Reverse mode of [`project`](crate::project): from gradients with respect
//! to (2D mean, conic, opacity) back to (mean, log-scale, quaternion,
//! opacity logit). Intermediates are recomputed from the inputs (cheaper
//! than storing them). Matrix gradients are written `G_X = ∂L/∂X`:
//!
//! - conic `Q = Σ₂⁻¹`: `G_Σ₂ = −Q G_Q Q` with `G_Q` the symmetric matrix
//!   `[[g_A, g_B/2], [g_B/2, g_C]]` (B sits in both off-diagonal slots);
//! - `Σ₂ = J Σ_c Jᵀ + 0.3 I`: `G_Σc = Jᵀ G_Σ₂ J`, `G_J = 2 G_Σ₂ J Σ_c`;
//! - `Σ_c = W Σ₃ Wᵀ`: `G_Σ₃ = Wᵀ G_Σc W`;  `Σ₃ = M Mᵀ`: `G_M = 2 G_Σ₃ M`;
//! - `M = R diag(s)`: `G_R = G_M diag(s)`, `g_sⱼ = Σᵢ (G_M)ᵢⱼ Rᵢⱼ`,
//!   `g_log_s = g_s ∘ s`; `R(q̂)` differentiated entry by entry, then the
//!   normalisation `q̂ = q/|q|`: `g_q = (g_q̂ − q̂ (q̂·g_q̂)) / |q|`;
//! - `J` and the 2D mean depend on the camera-space point (a clamped x/z
//!   contributes through z only), which maps back by `Wᵀ`.
//!
//! Radius and depth are piecewise constant / sort keys: no gradient.

use dm_mpm::real::Real;
use nalgebra::{Matrix2, Matrix3, Vector3};
use rayon::prelude::*;

use crate::gaussians::{GaussianGrads, Gaussians};
use crate::project::{CameraParams, ProjectedOne, intermediates};
use crate::rasterize_backward::ProjectedGrads;

/// Gradients of one Gaussian's projection inputs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProjectOneGrads<T: Real> {
    pub mean: Vector3<T>,
    pub log_scale: Vector3<T>,
    pub rotation: [T; 4],
}

/// Gradient of `⟨G, R(q)⟩` with respect to the (unit) quaternion `q = (w, x, y, z)`.
#[inline]
pub fn quat_to_matrix_vjp<T: Real>(q: &[T; 4], g: &Matrix3<T>) -> [T; 4] {
    let [w, x, y, z] = *q;
    let two = T::lit(2.0);
    let four = T::lit(4.0);
    let gw = two
        * (z * (g[(1, 0)] - g[(0, 1)]) + y * (g[(0, 2)] - g[(2, 0)]) + x * (g[(2, 1)] - g[(1, 2)]));
    let gx = two
        * (y * (g[(0, 1)] + g[(1, 0)]) + z * (g[(0, 2)] + g[(2, 0)]) + w * (g[(2, 1)] - g[(1, 2)]))
        - four * x * (g[(1, 1)] + g[(2, 2)]);
    let gy = two
        * (x * (g[(0, 1)] + g[(1, 0)]) + w * (g[(0, 2)] - g[(2, 0)]) + z * (g[(1, 2)] + g[(2, 1)]))
        - four * y * (g[(0, 0)] + g[(2, 2)]);
    let gz = two
        * (w * (g[(1, 0)] - g[(0, 1)]) + x * (g[(0, 2)] + g[(2, 0)]) + y * (g[(1, 2)] + g[(2, 1)]))
        - four * z * (g[(0, 0)] + g[(1, 1)]);
    [gw, gx, gy, gz]
}

/// Vector-Jacobian product of [`project_one`](crate::project::project_one)
/// for a Gaussian it did not cull (`projected` is its output); `grad_mean2d`
/// and `grad_conic` are the upstream gradients.
pub fn project_one_vjp<T: Real>(
    cam: &CameraParams<T>,
    mean: &Vector3<T>,
    log_scale: &Vector3<T>,
    quat: &[T; 4],
    near_plane: T,
    low_pass: T,
    projected: &ProjectedOne<T>,
    grad_mean2d: [T; 2],
    grad_conic: [T; 3],
) -> ProjectOneGrads<T> {
    let zero = ProjectOneGrads {
        mean: Vector3::zeros(),
        log_scale: Vector3::zeros(),
        rotation: [T::zero(); 4],
    };
    let Some(it) = intermediates(cam, mean, log_scale, quat, near_plane, low_pass) else {
        return zero;
    };
    let two = T::lit(2.0);
    let half = T::lit(0.5);
    let [a_q, b_q, c_q] = projected.conic;
    let conic = Matrix2::new(a_q, b_q, b_q, c_q);
    let g_conic = Matrix2::new(
        grad_conic[0],
        half * grad_conic[1],
        half * grad_conic[1],
        grad_conic[2],
    );
    let g_cov2d = -(conic * g_conic * conic);
    let j = it.jacobian;
    let g_cov_cam = j.transpose() * g_cov2d * j;
    let g_j = (g_cov2d * j * it.cov_cam) * two;
    let w = cam.rotation;
    let g_cov_world = w.transpose() * g_cov_cam * w;
    let g_m = (g_cov_world * it.m) * two;
    let mut g_rot = g_m;
    let mut g_log_scale = Vector3::zeros();
    for col in 0..3 {
        let mut g_s = T::zero();
        for row in 0..3 {
            g_rot[(row, col)] *= it.scale[col];
            g_s += g_m[(row, col)] * it.rot[(row, col)];
        }
        g_log_scale[col] = g_s * it.scale[col];
    }
    let g_unit = quat_to_matrix_vjp(&it.unit_quat, &g_rot);
    let q = it.unit_quat;
    let radial = q[0] * g_unit[0] + q[1] * g_unit[1] + q[2] * g_unit[2] + q[3] * g_unit[3];
    let g_quat: [T; 4] = std::array::from_fn(|k| (g_unit[k] - q[k] * radial) / it.quat_norm);

    // Camera-space point.
    let p = it.p_cam;
    let inv_z = T::one() / p.z;
    let inv_z2 = inv_z * inv_z;
    let inv_z3 = inv_z2 * inv_z;
    let (fx, fy) = (cam.fx, cam.fy);
    let mut g_p = Vector3::new(
        grad_mean2d[0] * fx * inv_z,
        grad_mean2d[1] * fy * inv_z,
        -(grad_mean2d[0] * fx * p.x + grad_mean2d[1] * fy * p.y) * inv_z2,
    );
    let tx = it.clamped_x.map_or(p.x, |c| c * p.z);
    let ty = it.clamped_y.map_or(p.y, |c| c * p.z);
    g_p.z += -g_j[(0, 0)] * fx * inv_z2 - g_j[(1, 1)] * fy * inv_z2
        + two * (g_j[(0, 2)] * fx * tx + g_j[(1, 2)] * fy * ty) * inv_z3;
    let g_tx = -g_j[(0, 2)] * fx * inv_z2;
    let g_ty = -g_j[(1, 2)] * fy * inv_z2;
    match it.clamped_x {
        None => g_p.x += g_tx,
        Some(c) => g_p.z += g_tx * c,
    }
    match it.clamped_y {
        None => g_p.y += g_ty,
        Some(c) => g_p.z += g_ty * c,
    }
    ProjectOneGrads {
        mean: w.transpose() * g_p,
        log_scale: g_log_scale,
        rotation: g_quat,
    }
}

/// Gradients with respect to every Gaussian parameter from the
/// rasterizer's gradients (parallel over Gaussians; each output depends
/// only on its own Gaussian, so the result is thread-count independent).
pub fn project_backward<T: Real>(
    gaussians: &Gaussians<T>,
    cam: &CameraParams<T>,
    near_plane: T,
    low_pass: T,
    projected: &crate::project::Projected<T>,
    grads: &ProjectedGrads<T>,
) -> GaussianGrads<T> {
    let per_gaussian: Vec<(ProjectOneGrads<T>, T)> = (0..gaussians.len())
        .into_par_iter()
        .map(|i| {
            let opacity = projected.opacity[i];
            let g_logit = grads.opacity[i] * opacity * (T::one() - opacity);
            if projected.tile_rect[i].is_empty() {
                let zero = ProjectOneGrads {
                    mean: Vector3::zeros(),
                    log_scale: Vector3::zeros(),
                    rotation: [T::zero(); 4],
                };
                return (zero, g_logit);
            }
            let one = ProjectedOne {
                mean2d: projected.mean2d[i],
                conic: projected.conic[i],
                depth: projected.depth[i],
                radius: projected.radius[i],
            };
            let g = project_one_vjp(
                cam,
                &gaussians.means[i],
                &gaussians.log_scales[i],
                &gaussians.rotations[i],
                near_plane,
                low_pass,
                &one,
                grads.mean2d[i],
                grads.conic[i],
            );
            (g, g_logit)
        })
        .collect();
    let mut out = GaussianGrads::zeros(gaussians.len());
    for (i, (g, g_logit)) in per_gaussian.into_iter().enumerate() {
        out.means[i] = g.mean;
        out.log_scales[i] = g.log_scale;
        out.rotations[i] = g.rotation;
        out.opacity_logits[i] = g_logit;
        out.colors[i] = grads.color[i];
    }
    out
}
