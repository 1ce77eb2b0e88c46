//! Backward twin of `p2g.rs`: a gather, so it runs in parallel over
//! particles with no write conflicts.
//!
//! Forward: m_i = Σ w m_p, P_i = Σ w (q_p + A_p (x_i − x_p)).
//! Backward (given P̄_i, m̄_i): q̄ = Σ w P̄, Ā = Σ w P̄ (x_i − x_p)ᵀ,
//! x̄ += Σ ∇w (P̄·(q + A (x_i − x_p)) + m̄ m_p) − Σ w Aᵀ P̄.

use crate::grid::stencil;
use crate::real::{Lane4, Mat3, Real, Vec3};
use crate::state::Consts;
use crate::stress::{ImpulseInputs, particle_impulse};

/// Adjoint of one particle's scatter: its affine matrix, momentum and the
/// position (through the weights and node offsets).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScatterGrads<T> {
    pub affine: Mat3<T>,
    pub momentum: Vec3<T>,
    pub x: Vec3<T>,
}

/// VJP of particle `p`'s contribution to `p2g`, given the adjoint of the
/// pre-update grid `[P̄_x, P̄_y, P̄_z, m̄]` per node.
#[inline]
pub fn p2g_particle_vjp<T: Real>(
    k: &Consts<T>,
    inputs: &ImpulseInputs<'_, T>,
    p: usize,
    grad_grid: &[T::Lane4],
) -> ScatterGrads<T> {
    let res = k.res;
    let (a, q) = particle_impulse(k, inputs, p);
    let m = inputs.particles.mass[p];
    let st = stencil(&inputs.particles.x[p], &k.origin, k.inv_dx, res);
    let slopes = st.slopes();
    let mut grad_q = Vec3::zeros();
    let mut grad_a = Mat3::zeros();
    let mut grad_x = Vec3::zeros();
    for i in 0..3 {
        for j in 0..3 {
            for kk in 0..3 {
                let g = grad_grid
                    [((st.base[0] + i) * res + st.base[1] + j) * res + st.base[2] + kk]
                    .to_array();
                let gp = Vec3::new(g[0], g[1], g[2]);
                let gm = g[3];
                let w = st.w[0][i] * st.w[1][j] * st.w[2][kk];
                let d = st.node_offset(k.dx, i, j, kk);
                grad_q += gp * w;
                grad_a += (gp * w) * d.transpose();
                let grad_w = st.weight_gradient(&slopes, k.inv_dx, i, j, kk);
                grad_x += grad_w * (gp.dot(&(q + a * d)) + gm * m);
                grad_x -= a.transpose() * gp * w;
            }
        }
    }
    ScatterGrads {
        affine: grad_a,
        momentum: grad_q,
        x: grad_x,
    }
}
