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

use crate::grid::{Grid, StencilMoments, gather_moments, stencil};
use crate::p2g::{BlockSchedule, scatter_affine};
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

#[inline(always)]
fn xyz<T: Real>(l: T::Lane4) -> Vec3<T> {
    let a = l.to_array();
    Vec3::new(a[0], a[1], a[2])
}

/// What pass 1 of [`g2p_backward`] hands to its scatter, per particle: the
/// adjoints of the gathered velocity ṽ and of B = Σ w u (x_i − x_p)ᵀ, and
/// the particle's share of the damping factor κ's adjoint, v̄'·ṽ.
#[derive(Clone, Copy, Debug, Default)]
pub struct GatherAdjoint<T: Real> {
    pub v_tilde: Vec3<T>,
    pub b: Mat3<T>,
    pub damping: T,
}

/// Adjoint of `g2p`. `x`, `f` are the particle state before the gather,
/// `grid` holds the updated node velocities, `out` the adjoint of the
/// gather's outputs. Writes the adjoint of x and F into `grad_in` (v and C
/// are not read by the gather: their entries are left untouched), the
/// adjoint of the node velocities into `grad_u` (overwritten) and uses
/// `gather_bar` as per-particle scratch. Returns the adjoint of the
/// particle damping factor κ (summed over particles in order).
pub fn g2p_backward<T: Real>(
    k: &Consts<T>,
    schedule: &BlockSchedule,
    grid: &Grid<T>,
    x: &[Vec3<T>],
    f: &[Mat3<T>],
    out: &ParticleGrads<T>,
    grad_in: &mut ParticleGrads<T>,
    grad_u: &mut NodeVelocityGrads<T>,
    gather_bar: &mut Vec<GatherAdjoint<T>>,
    scatter_spare: &mut Vec<Vec<T::Lane4>>,
) -> T {
    let n = x.len();
    let res = k.res;
    let apic_scale = T::lit(4.0) * k.inv_dx * k.inv_dx;
    // Pass 1 (gather, parallel over particles): the per-particle adjoints
    // and the two quantities pass 2 scatters to the grid.
    gather_bar.resize(n, GatherAdjoint::default());
    (
        grad_in.x.par_iter_mut(),
        grad_in.f.par_iter_mut(),
        gather_bar.par_iter_mut(),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(p, (gx, gf, bar))| {
            let st = stencil(&x[p], &k.origin, k.inv_dx, res);
            // One pass over the stencil yields both the forward gather
            // (sum, moment: the same sums, in the same order, as `g2p`) and
            // the sums its position adjoint needs (slope, slope_moment).
            let m = gather_moments::<T>(&st, &grid.nodes, res);
            let v_tilde = xyz::<T>(m.sum);
            let s_cols = m.moment.map(xyz::<T>);
            let b = (Mat3::from_columns(&s_cols) - v_tilde * st.frac.transpose()) * k.dx;
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
            *gx = x_bar + gather_position_adjoint(k, &st.frac, &m, &vt_bar, &bbar);
            *bar = GatherAdjoint {
                v_tilde: vt_bar,
                b: bbar,
                damping: v_new_bar.dot(&v_tilde),
            };
        });
    let damping = gather_bar
        .iter()
        .fold(T::zero(), |sum, bar| sum + bar.damping);

    // Pass 2 (scatter, deterministic parts): ū_i += w (ṽ̄ + B̄ (x_i − x_p)),
    // an affine field in the node offset: ṽ̄ − B̄ frac dx + B̄ dx (i, j, k).
    grad_u.clear();
    grad_u.resize(res * res * res, T::Lane4::default());
    let zero = T::zero();
    let lanes = |v: Vec3<T>| T::Lane4::from_array([v.x, v.y, v.z, zero]);
    schedule.scatter(k, x, grad_u, scatter_spare, |p, st, nodes| {
        let GatherAdjoint { v_tilde, b, .. } = gather_bar[p];
        let q0 = lanes(v_tilde - b * (st.frac * k.dx));
        let cols = [0, 1, 2].map(|c| lanes(b.column(c) * k.dx));
        scatter_affine::<T>(st, q0, cols, nodes);
    });
    damping
}

/// Position adjoint of the gather through the weights and node offsets,
/// `Σ_i ∇w_i (u_i·ṽ̄ + u_iᵀ B̄ (x_i − x_p)) − Σ_i w_i B̄ᵀ u_i`, from the
/// stencil moments of u: with x_i − x_p = (o_i − frac) dx the second sum
/// is `dx (Σ_b B̄_{:,b}·slope_moment[c][b] − slope[c]·B̄ frac)` per axis c,
/// and the last is `B̄ᵀ ṽ`.
#[inline(always)]
fn gather_position_adjoint<T: Real>(
    k: &Consts<T>,
    frac: &Vec3<T>,
    m: &StencilMoments<T::Lane4>,
    vt_bar: &Vec3<T>,
    bbar: &Mat3<T>,
) -> Vec3<T> {
    let v_tilde = xyz::<T>(m.sum);
    let bbar_frac = bbar * frac;
    let mut g = -(bbar.transpose() * v_tilde);
    for c in 0..3 {
        let slope = xyz::<T>(m.slope[c]);
        let mut through_offsets = -slope.dot(&bbar_frac);
        for b in 0..3 {
            through_offsets += bbar.column(b).dot(&xyz::<T>(m.slope_moment[c][b]));
        }
        g[c] += (slope.dot(vt_bar) + through_offsets * k.dx) * k.inv_dx;
    }
    g
}
