//! The LBS bridge: Gaussians follow the material particles (method.md §6,
//! PhysTwin's variant).
//!
//! Each frame applies the particle motion since the previous frame
//! (incremental): every Gaussian takes its K = 16 nearest particles (at
//! their previous positions) as bones with inverse-distance weights; every
//! particle's rotation is the Procrustes fit (Kabsch, SVD) of its own K
//! nearest neighbours' previous → current offsets; a Gaussian's new mean is
//! `Σ_b w_b (R_b (μ − x_b) + x_b')` and its rotation is the normalised,
//! sign-aligned weighted sum of the bone quaternions applied on the left.
//! A rigid motion of the particles therefore moves the Gaussians rigidly,
//! to round-off (tested). Work is parallel per particle / per Gaussian with
//! no shared sums, so results do not depend on the thread count.

use dm_mpm::neighbors::PointIndex;
use dm_mpm::real::Real;
use nalgebra::{Matrix3, Quaternion, Rotation3, UnitQuaternion, Vector3};
use rayon::prelude::*;

use crate::{Gaussians, SplatError};

/// Bones per Gaussian and neighbours per Procrustes fit (PhysTwin: 16).
pub const LBS_NEIGHBORS: usize = 16;
/// Added to bone distances before inverting, so a Gaussian sitting on a
/// particle gets a large but finite weight (metres; far below particle
/// spacings of millimetres).
const WEIGHT_DISTANCE_EPS: f64 = 1e-9;

/// Incremental skinning state: the particle positions of the last frame.
#[derive(Debug, Clone)]
pub struct LbsBridge {
    neighbors: usize,
    previous: Vec<[f64; 3]>,
}

impl LbsBridge {
    /// Binds to the particles of the first frame; `neighbors` is K (at least
    /// 1, and at most the particle count is used).
    pub fn new(particles: &[[f64; 3]], neighbors: usize) -> Result<Self, SplatError> {
        if particles.is_empty() {
            return Err(SplatError::Lbs("no particles to bind to".into()));
        }
        if neighbors == 0 {
            return Err(SplatError::Lbs("K must be at least 1".into()));
        }
        check_finite(particles)?;
        Ok(Self {
            neighbors,
            previous: particles.to_vec(),
        })
    }

    /// Particle positions the next [`advance`](Self::advance) starts from.
    pub fn previous(&self) -> &[[f64; 3]] {
        &self.previous
    }

    /// Per-particle rotation of the motion `previous → current`.
    pub fn particle_rotations(&self, current: &[[f64; 3]]) -> Vec<Matrix3<f64>> {
        let index = PointIndex::new(&self.previous);
        self.rotations_of(&index, current, &vec![true; self.previous.len()])
    }

    /// [`Self::particle_rotations`] of the particles marked in `wanted`
    /// (the identity elsewhere); `index` holds the previous positions.
    fn rotations_of(
        &self,
        index: &PointIndex,
        current: &[[f64; 3]],
        wanted: &[bool],
    ) -> Vec<Matrix3<f64>> {
        let prev = &self.previous;
        (0..prev.len())
            .into_par_iter()
            .map(|p| {
                if !wanted[p] {
                    return Matrix3::identity();
                }
                let centre_prev = Vector3::from(prev[p]);
                let centre_cur = Vector3::from(current[p]);
                let mut cross = Matrix3::zeros();
                for (j, _) in index.nearest(&prev[p], self.neighbors + 1) {
                    let a = Vector3::from(prev[j]) - centre_prev;
                    let b = Vector3::from(current[j]) - centre_cur;
                    cross += b * a.transpose();
                }
                procrustes_rotation(&cross)
            })
            .collect()
    }

    /// Moves the Gaussians with the particles from the previous frame to
    /// `current`, then makes `current` the previous frame. Returns the
    /// skinning weights used, for [`crate::lbs_backward`].
    pub fn advance<T: Real>(
        &mut self,
        gaussians: &mut Gaussians<T>,
        current: &[[f64; 3]],
    ) -> Result<SkinBinding, SplatError> {
        if current.len() != self.previous.len() {
            return Err(SplatError::Lbs(format!(
                "{} particles this frame, {} bound",
                current.len(),
                self.previous.len()
            )));
        }
        check_finite(current)?;
        gaussians.validate()?;
        let means: Vec<Vector3<f64>> = gaussians
            .means
            .iter()
            .map(|m| m.map(|c| c.to_f64()))
            .collect();
        let index = PointIndex::new(&self.previous);
        let binding = self.bind_with(&index, &means);
        // Only the Gaussians' bones need a rotation (a fraction of the
        // particles when the splats cover the surface).
        let mut is_bone = vec![false; self.previous.len()];
        for &(b, _) in binding.bones.iter().flatten() {
            is_bone[b as usize] = true;
        }
        let rotations = self.rotations_of(&index, current, &is_bone);
        let new_means = skin_means(&binding, &means, &self.previous, current, &rotations);
        let quats: Vec<UnitQuaternion<f64>> = rotations
            .par_iter()
            .zip(&is_bone)
            .map(|(r, &bone)| {
                if bone {
                    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*r))
                } else {
                    UnitQuaternion::identity()
                }
            })
            .collect();
        let blended: Vec<UnitQuaternion<f64>> = binding
            .bones
            .par_iter()
            .map(|bones| {
                let reference = quats[bones[0].0 as usize].into_inner();
                let mut blend = Quaternion::new(0.0, 0.0, 0.0, 0.0);
                for &(b, w) in bones {
                    // q and −q are the same rotation: align signs before summing.
                    let q = quats[b as usize].into_inner();
                    let sign = if q.dot(&reference) < 0.0 { -1.0 } else { 1.0 };
                    blend += q * (w * sign);
                }
                UnitQuaternion::from_quaternion(blend)
            })
            .collect();
        for (g, (mean, rotation)) in new_means.into_iter().zip(blended).enumerate() {
            let q = gaussians.rotations[g];
            let old = Quaternion::new(q[0].to_f64(), q[1].to_f64(), q[2].to_f64(), q[3].to_f64());
            let new = rotation.into_inner() * old;
            gaussians.means[g] = mean.map(T::lit);
            gaussians.rotations[g] = [new.w, new.i, new.j, new.k].map(T::lit);
        }
        self.previous = current.to_vec();
        Ok(binding)
    }

    /// Each Gaussian's K nearest particles at the previous frame and their
    /// normalised inverse-distance weights.
    pub fn bind(&self, means: &[Vector3<f64>]) -> SkinBinding {
        self.bind_with(&PointIndex::new(&self.previous), means)
    }

    /// [`Self::bind`] with the index of the previous positions at hand.
    fn bind_with(&self, index: &PointIndex, means: &[Vector3<f64>]) -> SkinBinding {
        let bones = means
            .par_iter()
            .map(|mean| {
                let near = index.nearest(&[mean.x, mean.y, mean.z], self.neighbors);
                let total: f64 = near
                    .iter()
                    .map(|(_, d)| 1.0 / (d + WEIGHT_DISTANCE_EPS))
                    .sum();
                near.iter()
                    .map(|&(b, d)| (b as u32, 1.0 / (d + WEIGHT_DISTANCE_EPS) / total))
                    .collect()
            })
            .collect();
        SkinBinding { bones }
    }
}

/// The bones of every Gaussian for one frame's skinning: `(particle,
/// weight)` pairs, weights summing to one.
#[derive(Debug, Clone, PartialEq)]
pub struct SkinBinding {
    pub bones: Vec<Vec<(u32, f64)>>,
}

/// New Gaussian means `Σ_b w_b (R_b (μ − x_b) + x_b')` for particle
/// positions `previous` (x) → `current` (x') and per-particle rotations R.
pub fn skin_means(
    binding: &SkinBinding,
    means: &[Vector3<f64>],
    previous: &[[f64; 3]],
    current: &[[f64; 3]],
    rotations: &[Matrix3<f64>],
) -> Vec<Vector3<f64>> {
    binding
        .bones
        .par_iter()
        .zip(means)
        .map(|(bones, mean)| {
            let mut new_mean = Vector3::zeros();
            for &(b, w) in bones {
                let b = b as usize;
                let offset = mean - Vector3::from(previous[b]);
                new_mean += (rotations[b] * offset + Vector3::from(current[b])) * w;
            }
            new_mean
        })
        .collect()
}

/// Proper rotation closest to `cross = Σ bᵢ aᵢᵀ` (maps the a's onto the
/// b's): `U diag(1, 1, det(U Vᵀ)) Vᵀ`. A degenerate neighbourhood (all
/// offsets zero) gives the identity.
pub fn procrustes_rotation(cross: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = cross.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Matrix3::identity();
    };
    let det = (u * v_t).determinant();
    let fix = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, det.signum()));
    let r = u * fix * v_t;
    if r.iter().all(|c| c.is_finite()) {
        r
    } else {
        Matrix3::identity()
    }
}

fn check_finite(points: &[[f64; 3]]) -> Result<(), SplatError> {
    match points.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
        Some(i) => Err(SplatError::Lbs(format!("particle {i} is not finite"))),
        None => Ok(()),
    }
}
