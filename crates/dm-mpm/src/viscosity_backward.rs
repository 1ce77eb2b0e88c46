//! Backward twin of `viscosity.rs`.
//!
//! Forward: (M + dt K(m, η)) v = M u. With λ = (M + dt K)⁻¹ v̄ (the
//! operator is symmetric, so the adjoint solve is the forward one):
//!
//!   ū   = M λ
//!   m̄_n = λ_n·(u_n − v_n) − Σ_{c∋n} 2η dt ∂V_c/∂m_n sym(∇v_c):sym(∇λ_c)
//!   η̄   = −2 dt Σ_c V_c sym(∇v_c):sym(∇λ_c)
//!
//! The first mass term is M's own; the second is K's, through the cell
//! volumes V_c = 8 / (ρ Σ_q 1/m_q), so ∂V_c/∂m_n = ρ V_c² / (8 m_n²). The
//! active set (non-empty nodes, full cells) is the forward one, as for the
//! empty-node cut of the grid update.

use crate::real::{Real, Vec3};
use crate::viscosity::{NONE, ViscousSolver};

/// The adjoints of one viscous solve, per unknown (and η).
pub(crate) struct ViscosityGrads<T> {
    pub(crate) u: Vec<Vec3<T>>,
    pub(crate) mass: Vec<T>,
    pub(crate) viscosity: T,
}

impl<T: Real> ViscousSolver<T> {
    /// VJP of the last [`ViscousSolver::solve_grid`] (its input `u` and
    /// output `v`), given v̄ per unknown.
    pub(crate) fn vjp(&mut self, grad_v: &[Vec3<T>]) -> ViscosityGrads<T> {
        let (u, v) = (&self.u, &self.v);
        let system = &self.system;
        let mut lambda: Vec<Vec3<T>> = grad_v
            .iter()
            .zip(&system.diagonal)
            .map(|(g, d)| g / *d)
            .collect();
        system.solve(grad_v, &mut lambda, &mut self.cg);
        let mut strain_v = Vec::new();
        let mut strain_lambda = Vec::new();
        system.strain_rates(v, &mut strain_v);
        system.strain_rates(&lambda, &mut strain_lambda);
        let contraction: Vec<T> = strain_v
            .iter()
            .zip(&strain_lambda)
            .map(|(a, b)| a.component_mul(b).sum())
            .collect();
        let viscosity = -system.two_dt
            * system
                .cells
                .iter()
                .zip(&contraction)
                .fold(T::zero(), |s, (c, x)| s + c.volume * *x);
        let per_volume_squared = system.scale * system.density / T::lit(8.0);
        let mass = lambda
            .iter()
            .zip(u.iter().zip(v))
            .zip(system.node_cells.iter().zip(&system.mass))
            .map(|((l, (u, v)), (adjacent, &m))| {
                adjacent
                    .iter()
                    .filter(|(c, _)| *c != NONE)
                    .fold(l.dot(&(u - v)), |g, &(c, _)| {
                        let volume = system.cells[c as usize].volume;
                        g - per_volume_squared * volume * volume / (m * m) * contraction[c as usize]
                    })
            })
            .collect();
        let u_bar = lambda
            .iter()
            .zip(&system.mass)
            .map(|(l, m)| l * *m)
            .collect();
        ViscosityGrads {
            u: u_bar,
            mass,
            viscosity,
        }
    }
}
