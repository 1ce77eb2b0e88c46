//! Backward twin of `correction.rs`. Given the adjoints x̄, v̄ of the
//! corrected state: where an axis was not clipped, Δv̄ = v̄ + Δt_frame·x̄
//! and x̃̄ = x̄; where it was clipped the corrected position is constant in
//! both; ṽ̄ = v̄ always.

use crate::correction::CorrectionTape;
use crate::g2p_backward::ParticleGrads;
use crate::real::{Real, Vec3};

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
