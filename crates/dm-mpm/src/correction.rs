//! The per-frame velocity correction hook of the neural residual
//! (method.md §5): after a frame's substeps, v ← ṽ + Δv and
//! x ← clip(x̃ + Δv·Δt_frame); F and C are unchanged.
//!
//! Backward (given the adjoints x̄, v̄ of the corrected state): where an axis
//! was not clipped, Δv̄ = v̄ + Δt_frame·x̄ and x̃̄ = x̄; where it was clipped
//! the corrected position is constant in both; ṽ̄ = v̄ always.

use crate::SimError;
use crate::g2p_backward::ParticleGrads;
use crate::real::{Real, Vec3};
use crate::world::World;

/// What the backward pass of one correction needs (caller's order).
#[derive(Clone, Debug, PartialEq)]
pub struct CorrectionTape {
    /// Axes whose corrected position was clipped to the domain.
    pub clipped: Vec<[bool; 3]>,
    /// Δt_frame of the correction, seconds.
    pub frame_dt: f64,
}

impl<T: Real> World<T> {
    /// Seconds of one video frame (substeps × the substep in force).
    pub fn frame_dt(&self) -> f64 {
        self.config().dt * self.config().substeps_per_frame as f64
    }

    /// Applies a velocity correction `dv` (m/s, caller's order) after a
    /// frame. Rejects non-finite corrections instead of writing them.
    pub fn apply_velocity_correction(
        &mut self,
        dv: &[[f64; 3]],
    ) -> Result<CorrectionTape, SimError> {
        if dv.len() != self.particle_count() {
            return Err(SimError::InvalidInput(format!(
                "velocity correction has {} entries for {} particles",
                dv.len(),
                self.particle_count()
            )));
        }
        if let Some(p) = dv.iter().position(|d| d.iter().any(|c| !c.is_finite())) {
            return Err(SimError::Diverged {
                frame: self.frame(),
                substep: 0,
                particle: p,
                reason: "its velocity correction is not finite".into(),
            });
        }
        let frame_dt = self.frame_dt();
        let (lo, hi) = (self.consts.clip_lo, self.consts.clip_hi);
        let mut clipped = vec![[false; 3]; dv.len()];
        for (slot, &id) in self.id_of_slot.iter().enumerate() {
            let d = dv[id as usize];
            let x = &mut self.particles.x[slot];
            let v = &mut self.particles.v[slot];
            for a in 0..3 {
                v[a] += T::lit(d[a]);
                let moved = x[a] + T::lit(d[a] * frame_dt);
                clipped[id as usize][a] = moved < lo[a] || moved > hi[a];
                x[a] = moved.max(lo[a]).min(hi[a]);
            }
        }
        Ok(CorrectionTape { clipped, frame_dt })
    }
}

impl CorrectionTape {
    /// Adjoint of the correction: turns `grads` (of the corrected state,
    /// caller's order) into those of the state before it, in place, and
    /// returns the adjoint of Δv.
    pub fn backward<T: Real>(&self, grads: &mut ParticleGrads<T>) -> Vec<Vec3<T>> {
        let dt = T::lit(self.frame_dt);
        grads
            .x
            .iter_mut()
            .zip(&grads.v)
            .zip(&self.clipped)
            .map(|((gx, gv), clipped)| {
                let mut gdv = *gv;
                for a in 0..3 {
                    if clipped[a] {
                        gx[a] = T::lit(0.0);
                    } else {
                        gdv[a] += dt * gx[a];
                    }
                }
                gdv
            })
            .collect()
    }
}
