//! Backward twin of `p2g.rs`: a gather, so it runs in parallel over
//! particles with no write conflicts.
//!
//! Forward: m_i = Σ w m_p, P_i = Σ w (q_p + A_p (x_i − x_p)).
//! Backward (given P̄_i, m̄_i): q̄ = Σ w P̄, Ā = Σ w P̄ (x_i − x_p)ᵀ,
//! x̄ += Σ ∇w (P̄·(q + A (x_i − x_p)) + m̄ m_p) − Σ w Aᵀ P̄,
//! m̄_p = Σ w m̄ (the mass's own scatter; its share in q and A is
//! `stress_backward.rs`'s).

use crate::grid::{gather_moments, stencil};
use crate::real::{Lane4, Mat3, Real, Vec3};
use crate::state::Consts;
use crate::stress::ImpulseInputs;

/// Adjoint of one particle's scatter: its affine matrix, momentum and the
/// position (through the weights and node offsets), and the mass through
/// the node masses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScatterGrads<T> {
    pub affine: Mat3<T>,
    pub momentum: Vec3<T>,
    pub x: Vec3<T>,
    pub mass: T,
}

/// VJP of particle `p`'s contribution to `p2g` (its impulse `(a, q)`, see
/// [`crate::stress::particle_impulse`]), given the adjoint of the
/// pre-update grid `[P̄_x, P̄_y, P̄_z, m̄]` per node.
///
/// All three sums come from the stencil moments of the node adjoints
/// (see [`gather_moments`]): with x_i − x_p = (o_i − frac) dx,
/// q̄ = sum, Ā = (moment − q̄ fracᵀ) dx, and per axis c
/// Σ ∇w_{i,c} ([P̄_i, m̄_i]·[q, m]) = slope[c]·[q, m] / dx,
/// Σ ∇w_{i,c} P̄_i·(A d_i) = (Σ_b A_{:,b}·slope_moment[c][b] − slope[c]·A frac),
/// Σ w Aᵀ P̄ = Aᵀ q̄.
#[inline]
pub fn p2g_particle_vjp<T: Real>(
    k: &Consts<T>,
    inputs: &ImpulseInputs<'_, T>,
    p: usize,
    (a, q): (Mat3<T>, Vec3<T>),
    grad_grid: &[T::Lane4],
) -> ScatterGrads<T> {
    let m = inputs.particles.mass[p];
    let st = stencil(&inputs.particles.x[p], &k.origin, k.inv_dx, k.res);
    let mo = gather_moments::<T>(&st, grad_grid, k.res);
    let xyz = |l: T::Lane4| {
        let a = l.to_array();
        Vec3::new(a[0], a[1], a[2])
    };
    let grad_q = xyz(mo.sum);
    let moment_cols = mo.moment.map(xyz);
    let grad_a = (Mat3::from_columns(&moment_cols) - grad_q * st.frac.transpose()) * k.dx;
    let a_frac = a * st.frac;
    let mut grad_x = -(a.transpose() * grad_q);
    for c in 0..3 {
        let slope = mo.slope[c].to_array();
        let through_weights = slope[0] * q.x + slope[1] * q.y + slope[2] * q.z + slope[3] * m;
        let mut through_offsets = -xyz(mo.slope[c]).dot(&a_frac);
        for b in 0..3 {
            through_offsets += a.column(b).dot(&xyz(mo.slope_moment[c][b]));
        }
        grad_x[c] += (through_weights + through_offsets * k.dx) * k.inv_dx;
    }
    ScatterGrads {
        affine: grad_a,
        momentum: grad_q,
        x: grad_x,
        mass: mo.sum.to_array()[3],
    }
}
