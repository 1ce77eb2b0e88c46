//! Stage 4: grid-to-particle gather of velocity and the APIC matrix C,
//! particle damping, F ← (I + dt C) F with the divergence check, the
//! singular-value clamp (and plastic projection), advection and the
//! position clip.

use crate::grid::{Grid, offsets, stencil};
use crate::lanes::{Lanes, M3};
use crate::real::{Lane4, Mat3, Real, Vec3};
use crate::state::{Consts, Particles};
use crate::stress::CHUNK;
use crate::svd::{clamp_singular_values, singular_values_surely_within_lanes};
use rayon::prelude::*;

/// The first particle (lowest slot) whose state became invalid.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ParticleFailure {
    pub slot: usize,
    pub reason: &'static str,
}

pub fn g2p<T: Real>(
    k: &Consts<T>,
    grid: &Grid<T>,
    particles: &mut Particles<T>,
) -> Result<(), ParticleFailure> {
    let width = T::Wide::WIDTH;
    let Particles { x, v, f, c, .. } = particles;
    let failures: Option<ParticleFailure> = x
        .par_chunks_mut(CHUNK)
        .zip(v.par_chunks_mut(CHUNK))
        .zip(f.par_chunks_mut(CHUNK))
        .zip(c.par_chunks_mut(CHUNK))
        .enumerate()
        .map(|(chunk, (((xs, vs), fs), cs))| {
            let mut first = None;
            let mut gathered = [(Vec3::zeros(), Mat3::zeros()); MAX_LANES];
            for group in (0..xs.len()).step_by(width) {
                let len = width.min(xs.len() - group);
                for (i, slot) in gathered[..len].iter_mut().enumerate() {
                    *slot = gather_velocity(k, grid, &xs[group + i]);
                }
                // (I + dt C) F and the cheap clamp test, several particles
                // per register (spare lanes repeat the last particle).
                let lane = |i: usize| group + i.min(len - 1);
                let apic = T::Wide::broadcast(T::lit(4.0) * k.inv_dx * k.inv_dx);
                let new_c = M3::<T::Wide>::gather(|i, r, col| gathered[i.min(len - 1)].1[(r, col)])
                    .scale(apic);
                let old_f = M3::<T::Wide>::gather(|i, r, col| fs[lane(i)][(r, col)]);
                let one = T::Wide::broadcast(T::one());
                let new_f = new_c
                    .scale(T::Wide::broadcast(k.dt))
                    .add_diagonal(one)
                    .matmul(&old_f);
                let det = new_f.determinant();
                let lo = T::Wide::broadcast(k.svd_lo);
                let hi = T::Wide::broadcast(k.svd_hi);
                let within = singular_values_surely_within_lanes(&new_f, lo, hi);
                for i in 0..len {
                    let o = group + i;
                    let to_mat = |m: &M3<T::Wide>| {
                        let entries = m.lane(i);
                        Mat3::from_fn(|r, col| entries[r][col])
                    };
                    let det = T::Wide::lane(det, i);
                    // `finite` also catches NaN.
                    if det <= T::zero() || !det.finite() {
                        first.get_or_insert(ParticleFailure {
                            slot: chunk * CHUNK + o,
                            reason: "det F <= 0 or not finite",
                        });
                        continue;
                    }
                    let mut new_f = to_mat(&new_f);
                    if let Some((lo, hi)) = k.plastic
                        && let Some(projected) = clamp_singular_values(&new_f, lo, hi)
                    {
                        new_f = projected;
                    }
                    let surely_within = T::Wide::mask_lane(within, i) && k.plastic.is_none();
                    if !surely_within
                        && let Some(clamped) = clamp_singular_values(&new_f, k.svd_lo, k.svd_hi)
                    {
                        new_f = clamped;
                    }
                    let new_v = gathered[i].0 * k.particle_damping_factor;
                    let mut new_x = xs[o] + new_v * k.dt;
                    if !(new_x.iter().all(|c| c.finite()) && new_v.iter().all(|c| c.finite())) {
                        first.get_or_insert(ParticleFailure {
                            slot: chunk * CHUNK + o,
                            reason: "position or velocity not finite",
                        });
                        continue;
                    }
                    for a in 0..3 {
                        new_x[a] = new_x[a].max(k.clip_lo[a]).min(k.clip_hi[a]);
                    }
                    xs[o] = new_x;
                    vs[o] = new_v;
                    fs[o] = new_f;
                    cs[o] = to_mat(&new_c);
                }
            }
            first
        })
        .reduce(
            || None,
            |a, b| match (a, b) {
                (Some(a), Some(b)) => Some(if a.slot <= b.slot { a } else { b }),
                (a, b) => a.or(b),
            },
        );
    match failures {
        Some(failure) => Err(failure),
        None => Ok(()),
    }
}

/// The most lanes a [`Real::Wide`] register holds.
const MAX_LANES: usize = 8;

/// The grid velocity at a particle at `x` and the APIC moment
/// `B = Σ w v_g (x_g − x_p)ᵀ` (C = 4/dx² B).
#[inline(always)]
fn gather_velocity<T: Real>(k: &Consts<T>, grid: &Grid<T>, x: &Vec3<T>) -> (Vec3<T>, Mat3<T>) {
    let res = k.res;
    let off = offsets::<T>();
    let two = T::lit(2.0);
    let st = stencil(x, &k.origin, k.inv_dx, res);
    // v = Σ w v_g and S = Σ w v_g ⊗ offset, summed axis by axis so the
    // innermost loop is 6 multiply-adds per node; then
    // Σ w v_g (x_g − x_p)ᵀ = (S − v ⊗ frac) dx.
    let zero = T::Lane4::default();
    let (mut sum_v, mut s0, mut s1, mut s2) = (zero, zero, zero, zero);
    for i in 0..3 {
        let (mut v_i, mut sj_i, mut sk_i) = (zero, zero, zero);
        for j in 0..3 {
            let row = ((st.base[0] + i) * res + st.base[1] + j) * res + st.base[2];
            let n = &grid.nodes[row..row + 3];
            let g0 = n[0] * T::Lane4::splat(st.w[2][0]);
            let g1 = n[1] * T::Lane4::splat(st.w[2][1]);
            let g2 = n[2] * T::Lane4::splat(st.w[2][2]);
            let v_ij = g0 + g1 + g2;
            let sk_ij = g2.mul_add(T::Lane4::splat(two), g1);
            let wy = st.w[1][j];
            v_i = v_ij.mul_add(T::Lane4::splat(wy), v_i);
            sj_i = v_ij.mul_add(T::Lane4::splat(wy * off[j]), sj_i);
            sk_i = sk_ij.mul_add(T::Lane4::splat(wy), sk_i);
        }
        let wx = T::Lane4::splat(st.w[0][i]);
        sum_v = v_i.mul_add(wx, sum_v);
        s0 = v_i.mul_add(T::Lane4::splat(st.w[0][i] * off[i]), s0);
        s1 = sj_i.mul_add(wx, s1);
        s2 = sk_i.mul_add(wx, s2);
    }
    let xyz = |l: T::Lane4| {
        let a = l.to_array();
        Vec3::new(a[0], a[1], a[2])
    };
    let sum_v = xyz(sum_v);
    let s_cols = [xyz(s0), xyz(s1), xyz(s2)];
    let b = (Mat3::from_columns(&s_cols) - sum_v * st.frac.transpose()) * k.dx;
    (sum_v, b)
}
