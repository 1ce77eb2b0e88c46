//! The per-frame velocity correction hook of the neural residual
//! (method.md §5): after a frame's substeps, v ← ṽ + Δv and
//! x ← clip(x̃ + Δv·Δt_frame); F and C are unchanged. Its backward twin is
//! `correction_backward.rs`.

use crate::SimError;
use crate::real::Real;
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
