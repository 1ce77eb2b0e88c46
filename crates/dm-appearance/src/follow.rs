//! Gaussians that follow a rollout: bound once to the model's first-frame
//! particles, moved frame to frame by the LBS bridge (method.md §6).

use dm_splat::lbs::{LBS_NEIGHBORS, LbsBridge, SkinBinding};
use dm_splat::{Gaussians, SplatError};

/// The fitted Gaussians and their incremental skinning state.
#[derive(Debug, Clone)]
pub struct SplatFollower {
    gaussians: Gaussians<f32>,
    bridge: LbsBridge,
}

impl SplatFollower {
    /// Binds `gaussians` (fitted at frame 0) to the first-frame
    /// `particles` (K = 16 bones each).
    pub fn new(gaussians: Gaussians<f32>, particles: &[[f64; 3]]) -> Result<Self, SplatError> {
        Ok(Self {
            bridge: LbsBridge::new(particles, LBS_NEIGHBORS)?,
            gaussians,
        })
    }

    /// The Gaussians at the last frame advanced to.
    pub fn gaussians(&self) -> &Gaussians<f32> {
        &self.gaussians
    }

    /// Moves the Gaussians with the particles to `positions` (the next
    /// frame of a rollout, the particles in the model's order).
    pub fn advance(&mut self, positions: &[[f32; 3]]) -> Result<(), SplatError> {
        let current: Vec<[f64; 3]> = positions.iter().map(|p| p.map(f64::from)).collect();
        self.advance_f64(&current).map(|_| ())
    }

    /// [`advance`](Self::advance) for f64 positions, returning the skinning
    /// weights used (for `dm_splat::lbs_backward`).
    pub fn advance_f64(&mut self, positions: &[[f64; 3]]) -> Result<SkinBinding, SplatError> {
        self.bridge.advance(&mut self.gaussians, positions)
    }
}
