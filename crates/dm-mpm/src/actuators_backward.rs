//! Backward twin of `actuators.rs`.
//!
//! Forward: a_p = n^{-1/2} Σ_c [k_p ((x_c − x_p) − o_pc) + k_d (v_c − v_p)].
//! Backward (given ā_p): x̄_p −= k_p √n ā_p, v̄_p −= k_d √n ā_p,
//! k̄_p += n^{-1/2} Σ_c ((x_c − x_p) − o_pc)·ā_p, k̄_d likewise with the
//! velocity difference; the anchors get x̄_c += k_p n^{-1/2} ā_p and
//! v̄_c += k_d n^{-1/2} ā_p. Rigid mode has no acceleration (its constraint is
//! handled by the frame's backward pass).

use crate::actuators::{ActuatorMode, Actuators};
use crate::real::{Real, Vec3};

/// Gradients of the actuator gains.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GainGrads {
    pub kp: f64,
    pub kd: f64,
}

impl<T: Real> Actuators<T> {
    /// VJP of [`Actuators::accelerations`]: adds the state adjoints to
    /// `grad_x`, `grad_v` and returns the gains' gradients (summed in
    /// particle order, so independent of the thread count).
    pub fn accelerations_vjp(
        &self,
        x: &[Vec3<T>],
        v: &[Vec3<T>],
        anchor_x: &[Vec3<T>],
        anchor_v: &[Vec3<T>],
        grad_accel: &[Vec3<T>],
        grad_x: &mut [Vec3<T>],
        grad_v: &mut [Vec3<T>],
    ) -> GainGrads {
        let mut gains = GainGrads::default();
        if self.config.mode == ActuatorMode::Rigid {
            return gains;
        }
        let kp = T::lit(self.config.kp);
        let kd = T::lit(self.config.kd);
        for p in 0..x.len() {
            let (s, e) = (self.row_start[p] as usize, self.row_start[p + 1] as usize);
            if e == s {
                continue;
            }
            let n = T::lit((e - s) as f64);
            let g = grad_accel[p];
            grad_x[p] -= g * (kp * n.sqrt());
            grad_v[p] -= g * (kd * n.sqrt());
            let mut spring = Vec3::zeros();
            let mut damper = Vec3::zeros();
            for i in s..e {
                let c = self.anchor[i] as usize;
                spring += (anchor_x[c] - x[p]) - self.rest_offset[i];
                damper += anchor_v[c] - v[p];
            }
            gains.kp += (spring.dot(&g) / n.sqrt()).to_f64();
            gains.kd += (damper.dot(&g) / n.sqrt()).to_f64();
        }
        gains
    }

    /// The anchors' share of the same VJP: x̄_c += k_p n^{-1/2} ā_p and
    /// v̄_c += k_d n^{-1/2} ā_p over the particles p tied to anchor c
    /// (summed in particle order). Rigid mode adds nothing.
    pub fn anchors_vjp(
        &self,
        grad_accel: &[Vec3<T>],
        grad_anchor_x: &mut [[f64; 3]],
        grad_anchor_v: &mut [[f64; 3]],
    ) {
        if self.config.mode == ActuatorMode::Rigid {
            return;
        }
        let (kp, kd) = (self.config.kp, self.config.kd);
        for (p, g) in grad_accel.iter().enumerate() {
            let (s, e) = (self.row_start[p] as usize, self.row_start[p + 1] as usize);
            if e == s {
                continue;
            }
            let scale = 1.0 / ((e - s) as f64).sqrt();
            for i in s..e {
                let c = self.anchor[i] as usize;
                for a in 0..3 {
                    let ga = g[a].to_f64() * scale;
                    grad_anchor_x[c][a] += kp * ga;
                    grad_anchor_v[c][a] += kd * ga;
                }
            }
        }
    }

    /// Whether particle `p` (slot) is coupled to an anchor.
    pub fn is_coupled(&self, p: usize) -> bool {
        self.row_start[p + 1] > self.row_start[p]
    }
}
