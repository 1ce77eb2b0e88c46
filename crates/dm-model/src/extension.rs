//! Physics a diagnosis added to a fitted model (issue 6) that does not
//! live in `PhysicsConfig::effects`: a stiffer ball, a density gradient
//! and a time shift of the hand track. The effects that do (drag,
//! friction, plasticity, viscosity, gravity) are set on `physics` itself.

use dm_bundle::Bundle;
use dm_mpm::ParticleMaterial;
use serde::{Deserialize, Serialize};

/// A ball of particles whose Lamé parameters are scaled by `factor`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StiffBall {
    pub centre: [f64; 3],
    pub radius: f64,
    pub factor: f64,
}

/// Density graded linearly along `axis` (unit vector): the particle at
/// the low end of the object along it has factor 1, the one at the high
/// end `1 + excess` (a negative `excess` makes the low end heavy by
/// `1 + |excess|`), so every factor is ≥ 1 and the CFL substep chosen for
/// the base density stays stable.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DensityGradient {
    pub axis: [f64; 3],
    pub excess: f64,
}

/// Extension terms of a model; the default adds nothing.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ModelExtension {
    /// The actuators follow the recorded hand track `hand_lag_frames`
    /// frames later (linear interpolation, held at the clip's ends): a
    /// positive value means the recording lags the real hands.
    pub hand_lag_frames: f64,
    pub stiff_ball: Option<StiffBall>,
    pub density: Option<DensityGradient>,
}

impl ModelExtension {
    pub fn is_empty(&self) -> bool {
        self.hand_lag_frames == 0.0 && self.stiff_ball.is_none() && self.density.is_none()
    }

    /// Scales the material inside the stiff ball (caller's particle order).
    pub fn apply_to_material(&self, particles: &[[f64; 3]], material: &mut ParticleMaterial<f32>) {
        let Some(ball) = &self.stiff_ball else {
            return;
        };
        let factor = ball.factor as f32;
        for (i, p) in particles.iter().enumerate() {
            let d2: f64 = (0..3).map(|a| (p[a] - ball.centre[a]).powi(2)).sum();
            if d2 < ball.radius * ball.radius {
                material.mu[i] *= factor;
                material.lambda[i] *= factor;
            }
        }
    }

    /// Per-particle density factors (≥ 1), or `None` for a uniform density.
    pub fn density_factors(&self, particles: &[[f64; 3]]) -> Option<Vec<f64>> {
        let g = self.density.as_ref()?;
        let coords: Vec<f64> = particles
            .iter()
            .map(|p| (0..3).map(|a| p[a] * g.axis[a]).sum())
            .collect();
        let lo = coords.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = coords.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let span = (hi - lo).max(1e-9);
        Some(
            coords
                .iter()
                .map(|c| {
                    let s = (c - lo) / span;
                    1.0 + if g.excess >= 0.0 {
                        g.excess * s
                    } else {
                        -g.excess * (1.0 - s)
                    }
                })
                .collect(),
        )
    }

    /// Hand anchors driving the model at (possibly fractional) frame
    /// `t + hand_lag_frames`.
    pub fn hand_anchors(&self, bundle: &Bundle, t: usize) -> Vec<[f64; 3]> {
        hand_anchors_at(bundle, t as f64 + self.hand_lag_frames)
    }
}

/// The recorded hand anchors at fractional frame `time` (linear
/// interpolation, held at the first and last frame).
pub fn hand_anchors_at(bundle: &Bundle, time: f64) -> Vec<[f64; 3]> {
    let last = bundle.frame_count().saturating_sub(1);
    let time = time.clamp(0.0, last as f64);
    let t0 = (time.floor() as usize).min(last);
    let t1 = (t0 + 1).min(last);
    let w = time - t0 as f64;
    let a = crate::hand_anchors(bundle, t0);
    let b = crate::hand_anchors(bundle, t1);
    a.iter()
        .zip(&b)
        .map(|(p, q)| [0, 1, 2].map(|k| p[k] + w * (q[k] - p[k])))
        .collect()
}
