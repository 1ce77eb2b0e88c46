//! Backward twin of `g2p.rs`: the adjoint of the grid-to-particle gather,
//! the F update, the singular-value clamps and the advection.
//!
//! Forward, per particle p with grid velocities u_i and weights w_ip:
//!   ṽ = Σ w u,  B = Σ w u (x_i − x_p)ᵀ,  C' = 4/dx² B,  v' = κ ṽ,
//!   F' = clamp((I + dt C') F),  x' = clip(x + dt v').
//! Backward (given x̄', v̄', F̄', C̄'): the clip masks x̄'; x̄ += x̄',
//! v̄' += dt x̄'; F̄ = (I + dt C')ᵀ F̄'_pre; C̄' += dt F̄'_pre Fᵀ; ṽ̄ = κ v̄';
//! B̄ = 4/dx² C̄'; then ū_i += w (ṽ̄ + B̄ (x_i − x_p)) and
//! x̄ += Σ ∇w (u·ṽ̄ + uᵀ B̄ (x_i − x_p)) − Σ w B̄ᵀ u.

use crate::grid::{Grid, stencil};
use crate::p2g::BlockSchedule;
use crate::real::{Lane4, Mat3, Real, Vec3};
use crate::state::Consts;
use crate::svd::clamp_singular_values;
use crate::svd_backward::clamp_singular_values_vjp;
use rayon::prelude::*;

/// Adjoint of a particle state (x, v, F, C).
#[derive(Clone, Debug, PartialEq)]
pub struct ParticleGrads<T> {
    pub x: Vec<Vec3<T>>,
    pub v: Vec<Vec3<T>>,
    pub f: Vec<Mat3<T>>,
    pub c: Vec<Mat3<T>>,
}

impl<T: Real> ParticleGrads<T> {
    pub fn zeros(n: usize) -> Self {
        Self {
            x: vec![Vec3::zeros(); n],
            v: vec![Vec3::zeros(); n],
            f: vec![Mat3::zeros(); n],
            c: vec![Mat3::zeros(); n],
        }
    }
}

/// Gradient of the node velocity u_i (lane 3 unused).
pub type NodeVelocityGrads<T> = Vec<<T as Real>::Lane4>;

fn xyz<T: Real>(l: T::Lane4) -> Vec3<T> {
    let a = l.to_array();
    Vec3::new(a[0], a[1], a[2])
}

/// Adjoint of `g2p`. `x`, `f` are the particle state before the gather,
/// `grid` holds the updated node velocities, `out` the adjoint of the
/// gather's outputs. Writes the adjoint of x and F into `grad_in` (v and C
/// are not read by the gather: their entries are set to zero) and the
/// adjoint of the node velocities into `grad_u` (overwritten).
pub fn g2p_backward<T: Real>(
    k: &Consts<T>,
    schedule: &BlockSchedule,
    grid: &Grid<T>,
    x: &[Vec3<T>],
    f: &[Mat3<T>],
    out: &ParticleGrads<T>,
    grad_in: &mut ParticleGrads<T>,
    grad_u: &mut NodeVelocityGrads<T>,
) {
    let n = x.len();
    let res = k.res;
    let apic_scale = T::lit(4.0) * k.inv_dx * k.inv_dx;
    // Pass 1 (gather, parallel over particles): the per-particle adjoints
    // and the two quantities pass 2 scatters to the grid.
    let mut v_tilde_bar = vec![Vec3::zeros(); n];
    let mut b_bar = vec![Mat3::zeros(); n];
    (
        grad_in.x.par_iter_mut(),
        grad_in.f.par_iter_mut(),
        v_tilde_bar.par_iter_mut(),
        b_bar.par_iter_mut(),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(p, (gx, gf, vtb, bb))| {
            let st = stencil(&x[p], &k.origin, k.inv_dx, res);
            let u = |i: usize, j: usize, kk: usize| {
                xyz::<T>(
                    grid.nodes[((st.base[0] + i) * res + st.base[1] + j) * res + st.base[2] + kk],
                )
            };
            // Forward recomputation of this particle's gather.
            let mut v_tilde = Vec3::zeros();
            let mut b = Mat3::zeros();
            for i in 0..3 {
                for j in 0..3 {
                    for kk in 0..3 {
                        let w = st.w[0][i] * st.w[1][j] * st.w[2][kk];
                        let ui = u(i, j, kk);
                        v_tilde += ui * w;
                        b += (ui * w) * st.node_offset(k.dx, i, j, kk).transpose();
                    }
                }
            }
            let c_new = b * apic_scale;
            let v_new = v_tilde * k.particle_damping_factor;
            let f_pre = (Mat3::identity() + c_new * k.dt) * f[p];
            let x_pre = x[p] + v_new * k.dt;

            // Adjoint of the position clip: clipped components get none.
            let mut x_bar = out.x[p];
            for a in 0..3 {
                if x_pre[a] < k.clip_lo[a] || x_pre[a] > k.clip_hi[a] {
                    x_bar[a] = T::zero();
                }
            }
            // Adjoint of the clamps, outermost first.
            let f_plastic = match k.plastic {
                Some((lo, hi)) => clamp_singular_values(&f_pre, lo, hi).unwrap_or(f_pre),
                None => f_pre,
            };
            let mut f_bar = clamp_singular_values_vjp(&f_plastic, k.svd_lo, k.svd_hi, &out.f[p]);
            if let Some((lo, hi)) = k.plastic {
                f_bar = clamp_singular_values_vjp(&f_pre, lo, hi, &f_bar);
            }
            let v_new_bar = out.v[p] + x_bar * k.dt;
            let c_new_bar = out.c[p] + f_bar * f[p].transpose() * k.dt;
            *gf = (Mat3::identity() + c_new * k.dt).transpose() * f_bar;
            let vt_bar = v_new_bar * k.particle_damping_factor;
            let bbar = c_new_bar * apic_scale;
            // Through the weights and the node offsets.
            let slopes = st.slopes();
            let mut gx_acc = x_bar;
            for i in 0..3 {
                for j in 0..3 {
                    for kk in 0..3 {
                        let w = st.w[0][i] * st.w[1][j] * st.w[2][kk];
                        let ui = u(i, j, kk);
                        let d = st.node_offset(k.dx, i, j, kk);
                        let grad_w = st.weight_gradient(&slopes, k.inv_dx, i, j, kk);
                        gx_acc += grad_w * (ui.dot(&vt_bar) + ui.dot(&(bbar * d)));
                        gx_acc -= bbar.transpose() * ui * w;
                    }
                }
            }
            *gx = gx_acc;
            *vtb = vt_bar;
            *bb = bbar;
        });
    grad_in.v.iter_mut().for_each(|g| *g = Vec3::zeros());
    grad_in.c.iter_mut().for_each(|g| *g = Mat3::zeros());

    // Pass 2 (scatter, deterministic colouring): ū_i += w (ṽ̄ + B̄ (x_i − x_p)).
    grad_u.clear();
    grad_u.resize(res * res * res, T::Lane4::default());
    schedule.scatter(k, x, grad_u, |p, st, nodes| {
        for i in 0..3 {
            for j in 0..3 {
                for kk in 0..3 {
                    let w = st.w[0][i] * st.w[1][j] * st.w[2][kk];
                    let g = (v_tilde_bar[p] + b_bar[p] * st.node_offset(k.dx, i, j, kk)) * w;
                    let node = nodes.node(i, j, kk);
                    *node += T::Lane4::from_array([g.x, g.y, g.z, T::zero()]);
                }
            }
        }
    });
}
