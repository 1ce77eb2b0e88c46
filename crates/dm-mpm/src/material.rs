//! Material patches of the Mixture of Constitutive Experts (method.md §3):
//! learnable parameters live on patch centres chosen by farthest-point
//! sampling; each particle blends its 3 nearest patches with fixed
//! inverse-distance weights.

use crate::experts::lame;
use crate::neighbors::{PointIndex, farthest_point_sampling};
use crate::real::Real;
use serde::{Deserialize, Serialize};

/// Per-particle material the stress stage reads.
#[derive(Clone, Debug, PartialEq)]
pub struct ParticleMaterial<T> {
    pub mu: Vec<T>,
    pub lambda: Vec<T>,
    /// Weights of (Neo-Hookean, fixed corotated, StVK); sum to 1.
    pub expert_weights: Vec<[T; 3]>,
}

impl<T: Real> ParticleMaterial<T> {
    /// One homogeneous material with a single expert weight triple.
    pub fn uniform(count: usize, youngs_pa: f64, poisson: f64, weights: [f64; 3]) -> Self {
        let (mu, lambda) = lame(youngs_pa, poisson);
        Self {
            mu: vec![T::lit(mu); count],
            lambda: vec![T::lit(lambda); count],
            expert_weights: vec![weights.map(T::lit); count],
        }
    }

    /// Per-particle Young's modulus and Poisson ratio, one expert mix.
    pub fn from_fields(youngs_pa: &[f64], poisson: &[f64], weights: &[[f64; 3]]) -> Self {
        let (mu, lambda): (Vec<T>, Vec<T>) = youngs_pa
            .iter()
            .zip(poisson)
            .map(|(&e, &nu)| {
                let (mu, la) = lame(e, nu);
                (T::lit(mu), T::lit(la))
            })
            .unzip();
        Self {
            mu,
            lambda,
            expert_weights: weights.iter().map(|w| w.map(T::lit)).collect(),
        }
    }

    pub fn len(&self) -> usize {
        self.mu.len()
    }

    pub fn is_empty(&self) -> bool {
        self.mu.is_empty()
    }

    /// True when every particle is pure Neo-Hookean (the fast path).
    pub fn is_pure_neo_hookean(&self) -> bool {
        self.expert_weights
            .iter()
            .all(|w| w[0] == T::one() && w[1] == T::zero() && w[2] == T::zero())
    }
}

/// Bounds of the learnable material (log-sigmoid for E, sigmoid for ν).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaterialBounds {
    pub youngs_pa: [f64; 2],
    pub poisson: [f64; 2],
}

impl MaterialBounds {
    /// Ropes and cloths (method.md §2).
    pub const THIN: MaterialBounds = MaterialBounds {
        youngs_pa: [1e4, 1e6],
        poisson: [0.0, 0.35],
    };
    /// Plush toys.
    pub const VOLUMETRIC: MaterialBounds = MaterialBounds {
        youngs_pa: [1e5, 1e7],
        poisson: [0.0, 0.45],
    };

    pub fn youngs(&self, raw: f64) -> f64 {
        let [lo, hi] = self.youngs_pa;
        (lo.ln() + (hi.ln() - lo.ln()) * sigmoid(raw)).exp()
    }

    pub fn poisson(&self, raw: f64) -> f64 {
        let [lo, hi] = self.poisson;
        lo + (hi - lo) * sigmoid(raw)
    }

    /// Inverse of `youngs`: the raw value giving `e` (clamped inside the bounds).
    pub fn youngs_raw(&self, e: f64) -> f64 {
        let [lo, hi] = self.youngs_pa;
        let s = ((e.ln() - lo.ln()) / (hi.ln() - lo.ln())).clamp(1e-6, 1.0 - 1e-6);
        logit(s)
    }

    pub fn poisson_raw(&self, nu: f64) -> f64 {
        let [lo, hi] = self.poisson;
        logit(((nu - lo) / (hi - lo)).clamp(1e-6, 1.0 - 1e-6))
    }
}

pub fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

fn logit(s: f64) -> f64 {
    (s / (1.0 - s)).ln()
}

/// Unbounded per-patch parameters (what an optimiser updates).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PatchParams {
    pub youngs_raw: Vec<f64>,
    pub poisson_raw: Vec<f64>,
    /// Expert logits (Neo-Hookean, fixed corotated, StVK) per patch.
    pub logits: Vec<[f64; 3]>,
}

impl PatchParams {
    /// Every patch at the same material and expert logits.
    pub fn uniform(
        patches: usize,
        bounds: &MaterialBounds,
        youngs_pa: f64,
        poisson: f64,
        logits: [f64; 3],
    ) -> Self {
        Self {
            youngs_raw: vec![bounds.youngs_raw(youngs_pa); patches],
            poisson_raw: vec![bounds.poisson_raw(poisson); patches],
            logits: vec![logits; patches],
        }
    }
}

/// Softmax over the three expert logits.
pub fn softmax3(l: &[f64; 3]) -> [f64; 3] {
    let m = l[0].max(l[1]).max(l[2]);
    let e = l.map(|x| (x - m).exp());
    let s = e[0] + e[1] + e[2];
    e.map(|x| x / s)
}

/// Patch centres and each particle's fixed blend of its nearest patches.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaterialPatches {
    pub centres: Vec<[f64; 3]>,
    /// Per particle: nearest patch indices (up to 3) and their normalised
    /// inverse-distance weights (beta), padded with weight 0.
    pub neighbours: Vec<[u32; 3]>,
    pub beta: Vec<[f64; 3]>,
}

impl MaterialPatches {
    /// Picks `patch_count` centres by FPS over the first-frame particles.
    pub fn build(first_frame: &[[f64; 3]], patch_count: usize) -> Self {
        let centre_ids = farthest_point_sampling(first_frame, patch_count.max(1));
        let centres: Vec<[f64; 3]> = centre_ids.iter().map(|&i| first_frame[i]).collect();
        let index = PointIndex::new(&centres);
        let mut neighbours = Vec::with_capacity(first_frame.len());
        let mut beta = Vec::with_capacity(first_frame.len());
        for p in first_frame {
            let near = index.nearest(p, 3);
            let mut ids = [0u32; 3];
            let mut w = [0.0f64; 3];
            // A particle sitting on a centre takes that patch alone.
            if let Some(&(hit, _)) = near.first().filter(|n| n.1 < 1e-9) {
                ids[0] = hit as u32;
                w[0] = 1.0;
            } else {
                let total: f64 = near.iter().map(|n| 1.0 / n.1).sum();
                for (slot, &(id, d)) in near.iter().enumerate() {
                    ids[slot] = id as u32;
                    w[slot] = (1.0 / d) / total;
                }
            }
            neighbours.push(ids);
            beta.push(w);
        }
        Self {
            centres,
            neighbours,
            beta,
        }
    }

    pub fn patch_count(&self) -> usize {
        self.centres.len()
    }

    /// Blends per-patch values to particles with the fixed weights.
    pub fn blend(&self, per_patch: &[f64]) -> Vec<f64> {
        self.neighbours
            .iter()
            .zip(&self.beta)
            .map(|(ids, w)| (0..3).map(|s| w[s] * per_patch[ids[s] as usize]).sum())
            .collect()
    }

    /// Per-particle E (Pa), ν and expert weights from patch parameters.
    pub fn particle_fields(
        &self,
        params: &PatchParams,
        bounds: &MaterialBounds,
    ) -> (Vec<f64>, Vec<f64>, Vec<[f64; 3]>) {
        let e_patch: Vec<f64> = params
            .youngs_raw
            .iter()
            .map(|&r| bounds.youngs(r))
            .collect();
        let nu_patch: Vec<f64> = params
            .poisson_raw
            .iter()
            .map(|&r| bounds.poisson(r))
            .collect();
        let q: Vec<[f64; 3]> = params.logits.iter().map(softmax3).collect();
        let weights = self
            .neighbours
            .iter()
            .zip(&self.beta)
            .map(|(ids, b)| {
                let mut w = [0.0; 3];
                for s in 0..3 {
                    for k in 0..3 {
                        w[k] += b[s] * q[ids[s] as usize][k];
                    }
                }
                w
            })
            .collect();
        (self.blend(&e_patch), self.blend(&nu_patch), weights)
    }

    /// The per-particle material the simulator reads.
    pub fn particle_material<T: Real>(
        &self,
        params: &PatchParams,
        bounds: &MaterialBounds,
    ) -> ParticleMaterial<T> {
        let (e, nu, w) = self.particle_fields(params, bounds);
        ParticleMaterial::from_fields(&e, &nu, &w)
    }
}
