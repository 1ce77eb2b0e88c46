//! EWA projection of 3D Gaussians to screen-space conics (forward).
//!
//! Per Gaussian: `p = W μ + t` (camera space); `Σ₃ = M Mᵀ` with
//! `M = R(q/|q|) diag(exp(log_scale))`; `Σ_c = W Σ₃ Wᵀ`; `J` the Jacobian
//! of `(fx x/z + cx, fy y/z + cy)` at `p` (with x/z and y/z clamped to a
//! little beyond the field of view, as 3DGS does, so Gaussians far outside
//! the image do not get absurdly stretched footprints);
//! `Σ₂ = J Σ_c Jᵀ + 0.3 I` (the low-pass "dilation" that keeps every
//! footprint at least about a pixel wide); conic `= Σ₂⁻¹`; radius
//! `= ⌈3 √λ_max(Σ₂)⌉` pixels.

use dm_mpm::real::Real;
use dm_view::Camera;
use nalgebra::{Matrix2x3, Matrix3, Vector3};
use rayon::prelude::*;

use crate::gaussians::{Gaussians, normalize_quat, quat_to_matrix, sigmoid};
use crate::tiles::{TILE_SIZE, TileRect};

/// Fraction of the half field of view by which the x/z, y/z used in the
/// Jacobian may exceed the image edge before being clamped (3DGS: 1.3 × tan
/// of the half angle, i.e. 0.3 beyond the edge).
pub const JACOBIAN_CLAMP_MARGIN: f64 = 0.3;

/// Lower bound of the discriminant in the eigenvalue formula of the radius
/// (3DGS uses 0.1 so near-isotropic footprints do not hit a zero root).
const RADIUS_DISCRIMINANT_FLOOR: f64 = 0.1;

/// `a > b`, false when either is NaN (so NaN inputs are culled).
#[inline(always)]
fn strictly_greater<T: PartialOrd>(a: T, b: T) -> bool {
    matches!(a.partial_cmp(&b), Some(std::cmp::Ordering::Greater))
}

/// Camera quantities in the kernel's float type.
#[derive(Debug, Clone)]
pub struct CameraParams<T: Real> {
    pub rotation: Matrix3<T>,
    pub translation: Vector3<T>,
    pub fx: T,
    pub fy: T,
    pub cx: T,
    pub cy: T,
    pub width: u32,
    pub height: u32,
    /// Clamp limits of x/z: `[-lim_x_neg, lim_x_pos]`, likewise y.
    pub lim_x_neg: T,
    pub lim_x_pos: T,
    pub lim_y_neg: T,
    pub lim_y_pos: T,
}

impl<T: Real> CameraParams<T> {
    pub fn new(camera: &Camera) -> Self {
        let rotation = camera
            .world_to_camera
            .rotation
            .to_rotation_matrix()
            .into_inner()
            .map(T::lit);
        let translation = camera.world_to_camera.translation.vector.map(T::lit);
        let (w, h) = (f64::from(camera.width), f64::from(camera.height));
        let tan_x = 0.5 * w / camera.fx;
        let tan_y = 0.5 * h / camera.fy;
        let m = JACOBIAN_CLAMP_MARGIN;
        Self {
            rotation,
            translation,
            fx: T::lit(camera.fx),
            fy: T::lit(camera.fy),
            cx: T::lit(camera.cx),
            cy: T::lit(camera.cy),
            width: camera.width,
            height: camera.height,
            lim_x_neg: T::lit(camera.cx / camera.fx + m * tan_x),
            lim_x_pos: T::lit((w - camera.cx) / camera.fx + m * tan_x),
            lim_y_neg: T::lit(camera.cy / camera.fy + m * tan_y),
            lim_y_pos: T::lit((h - camera.cy) / camera.fy + m * tan_y),
        }
    }

    pub fn tiles_x(&self) -> u32 {
        self.width.div_ceil(TILE_SIZE)
    }

    pub fn tiles_y(&self) -> u32 {
        self.height.div_ceil(TILE_SIZE)
    }
}

/// One projected Gaussian.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProjectedOne<T> {
    /// Continuous image coordinates of the centre.
    pub mean2d: [T; 2],
    /// `(A, B, C)` of `Σ₂⁻¹ = [[A, B], [B, C]]`.
    pub conic: [T; 3],
    /// Camera-space z (sort key).
    pub depth: T,
    /// 3σ radius in pixels (an integer value).
    pub radius: T,
}

/// Intermediates of one projection, shared by the forward pass and the
/// backward recomputation so both see the same numbers.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ProjectionIntermediates<T: Real> {
    pub p_cam: Vector3<T>,
    pub jacobian: Matrix2x3<T>,
    /// Which of x/z, y/z were clamped: `None` or the clamp value used.
    pub clamped_x: Option<T>,
    pub clamped_y: Option<T>,
    pub unit_quat: [T; 4],
    pub quat_norm: T,
    pub rot: Matrix3<T>,
    pub scale: Vector3<T>,
    pub m: Matrix3<T>,
    pub cov_cam: Matrix3<T>,
    /// `(a, b, c)` of `Σ₂ = [[a, b], [b, c]]` after the low-pass.
    pub cov2d: [T; 3],
}

/// The forward map up to the 2D covariance; `None` when the centre is not in
/// front of the near plane.
#[inline]
pub(crate) fn intermediates<T: Real>(
    cam: &CameraParams<T>,
    mean: &Vector3<T>,
    log_scale: &Vector3<T>,
    quat: &[T; 4],
    near_plane: T,
    low_pass: T,
) -> Option<ProjectionIntermediates<T>> {
    let p_cam = cam.rotation * mean + cam.translation;
    if !strictly_greater(p_cam.z, near_plane) {
        return None;
    }
    let z = p_cam.z;
    let inv_z = T::one() / z;
    let clamp = |ratio: T, neg: T, pos: T| {
        if ratio < -neg {
            Some(-neg)
        } else if ratio > pos {
            Some(pos)
        } else {
            None
        }
    };
    let clamped_x = clamp(p_cam.x * inv_z, cam.lim_x_neg, cam.lim_x_pos);
    let clamped_y = clamp(p_cam.y * inv_z, cam.lim_y_neg, cam.lim_y_pos);
    let tx = clamped_x.map_or(p_cam.x, |c| c * z);
    let ty = clamped_y.map_or(p_cam.y, |c| c * z);
    let inv_z2 = inv_z * inv_z;
    let zero = T::zero();
    let jacobian = Matrix2x3::new(
        cam.fx * inv_z,
        zero,
        -cam.fx * tx * inv_z2,
        zero,
        cam.fy * inv_z,
        -cam.fy * ty * inv_z2,
    );
    let (unit_quat, quat_norm) = normalize_quat(quat);
    let rot = quat_to_matrix(&unit_quat);
    let scale = log_scale.map(|s| s.exp());
    let m = rot * Matrix3::from_diagonal(&scale);
    let cov_world = m * m.transpose();
    let cov_cam = cam.rotation * cov_world * cam.rotation.transpose();
    let cov = jacobian * cov_cam * jacobian.transpose();
    let cov2d = [cov[(0, 0)] + low_pass, cov[(0, 1)], cov[(1, 1)] + low_pass];
    Some(ProjectionIntermediates {
        p_cam,
        jacobian,
        clamped_x,
        clamped_y,
        unit_quat,
        quat_norm,
        rot,
        scale,
        m,
        cov_cam,
        cov2d,
    })
}

/// Projects one Gaussian; `None` when it is culled (behind the near plane,
/// degenerate or non-finite footprint, or entirely off-screen).
#[inline]
pub fn project_one<T: Real>(
    cam: &CameraParams<T>,
    mean: &Vector3<T>,
    log_scale: &Vector3<T>,
    quat: &[T; 4],
    near_plane: T,
    low_pass: T,
) -> Option<ProjectedOne<T>> {
    let it = intermediates(cam, mean, log_scale, quat, near_plane, low_pass)?;
    let [a, b, c] = it.cov2d;
    let det = a * c - b * b;
    if !strictly_greater(det, T::zero()) || !det.finite() {
        return None;
    }
    let inv_det = T::one() / det;
    let conic = [c * inv_det, -b * inv_det, a * inv_det];
    let half = T::lit(0.5);
    let mid = half * (a + c);
    let disc = (mid * mid - det).max(T::lit(RADIUS_DISCRIMINANT_FLOOR));
    let lambda_max = mid + disc.sqrt();
    let radius = (T::lit(3.0) * lambda_max.sqrt()).ceil();
    let p = it.p_cam;
    let inv_z = T::one() / p.z;
    let mean2d = [cam.fx * p.x * inv_z + cam.cx, cam.fy * p.y * inv_z + cam.cy];
    let all_finite = conic.iter().chain(&mean2d).all(|v| v.finite()) && radius.finite();
    if !all_finite || !strictly_greater(radius, T::zero()) {
        return None;
    }
    Some(ProjectedOne {
        mean2d,
        conic,
        depth: p.z,
        radius,
    })
}

/// Projected Gaussians (struct of arrays). Culled Gaussians have an empty
/// tile rectangle; their other entries are zero.
#[derive(Debug, Clone)]
pub struct Projected<T: Real> {
    pub mean2d: Vec<[T; 2]>,
    pub conic: Vec<[T; 3]>,
    pub depth: Vec<T>,
    pub radius: Vec<T>,
    /// Sigmoid of the opacity logit.
    pub opacity: Vec<T>,
    pub tile_rect: Vec<TileRect>,
}

impl<T: Real> Projected<T> {
    pub fn len(&self) -> usize {
        self.mean2d.len()
    }

    pub fn is_empty(&self) -> bool {
        self.mean2d.is_empty()
    }

    pub fn visible_count(&self) -> usize {
        self.tile_rect.iter().filter(|r| !r.is_empty()).count()
    }
}

/// Projects every Gaussian (in parallel; each result depends only on its
/// own Gaussian).
pub fn project_gaussians<T: Real>(
    gaussians: &Gaussians<T>,
    cam: &CameraParams<T>,
    near_plane: T,
    low_pass: T,
) -> Projected<T> {
    let (tiles_x, tiles_y) = (cam.tiles_x(), cam.tiles_y());
    let results: Vec<(ProjectedOne<T>, TileRect, T)> = (0..gaussians.len())
        .into_par_iter()
        .map(|i| {
            let opacity = sigmoid(gaussians.opacity_logits[i]);
            let culled = (
                ProjectedOne {
                    mean2d: [T::zero(); 2],
                    conic: [T::zero(); 3],
                    depth: T::zero(),
                    radius: T::zero(),
                },
                TileRect::EMPTY,
                opacity,
            );
            let Some(p) = project_one(
                cam,
                &gaussians.means[i],
                &gaussians.log_scales[i],
                &gaussians.rotations[i],
                near_plane,
                low_pass,
            ) else {
                return culled;
            };
            let rect = TileRect::covering(
                p.mean2d[0].to_f64(),
                p.mean2d[1].to_f64(),
                p.radius.to_f64(),
                tiles_x,
                tiles_y,
            );
            if rect.is_empty() {
                return culled;
            }
            (p, rect, opacity)
        })
        .collect();
    let mut out = Projected {
        mean2d: Vec::with_capacity(results.len()),
        conic: Vec::with_capacity(results.len()),
        depth: Vec::with_capacity(results.len()),
        radius: Vec::with_capacity(results.len()),
        opacity: Vec::with_capacity(results.len()),
        tile_rect: Vec::with_capacity(results.len()),
    };
    for (p, rect, opacity) in results {
        out.mean2d.push(p.mean2d);
        out.conic.push(p.conic);
        out.depth.push(p.depth);
        out.radius.push(p.radius);
        out.opacity.push(opacity);
        out.tile_rect.push(rect);
    }
    out
}
