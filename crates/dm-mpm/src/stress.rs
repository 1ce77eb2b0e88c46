//! Stage 1 of a substep: per-particle stress and external forces, turned
//! into the two quantities P2G scatters (MLS-MPM, Hu et al. 2018):
//! the affine matrix `-dt V 4/dx² P Fᵀ + m C` and the momentum
//! `m v + dt m a_ext`.

use crate::experts::{
    mixture_kirchhoff, mixture_kirchhoff_lanes, neo_hookean_kirchhoff, neo_hookean_kirchhoff_lanes,
};
use crate::lanes::{Lanes, M3};
use crate::material::ParticleMaterial;
use crate::real::{Mat3, Real, Vec3};
use crate::state::{Consts, Particles};
use crate::svd::{polar_rotation, polar_rotation_lanes};
use rayon::prelude::*;

pub(crate) const CHUNK: usize = 1024;

/// Read-only inputs of the per-particle impulse.
#[derive(Clone, Copy, Debug)]
pub struct ImpulseInputs<'a, T> {
    pub particles: &'a Particles<T>,
    pub material: &'a ParticleMaterial<T>,
    pub pure_neo_hookean: bool,
    /// Per-particle actuator acceleration, if any particle is coupled.
    pub external_accel: Option<&'a [Vec3<T>]>,
}

/// `(affine, momentum)` of particle `p`: what P2G scatters, one particle
/// at a time — the reference [`Impulses`] must equal bitwise (P2G and the
/// backward pass take theirs from [`Impulses`]).
#[inline(always)]
pub fn particle_impulse<T: Real>(
    k: &Consts<T>,
    inputs: &ImpulseInputs<'_, T>,
    p: usize,
) -> (Mat3<T>, Vec3<T>) {
    let particles = inputs.particles;
    let material = inputs.material;
    let f = &particles.f[p];
    let (mu, lambda) = (material.mu[p], material.lambda[p]);
    let kirchhoff = if inputs.pure_neo_hookean {
        neo_hookean_kirchhoff(f, mu, lambda)
    } else {
        mixture_kirchhoff(f, mu, lambda, &material.expert_weights[p])
    };
    impulse_from_kirchhoff(k, inputs, p, &kirchhoff)
}

/// [`particle_impulse`] given particle `p`'s Kirchhoff stress.
#[inline(always)]
fn impulse_from_kirchhoff<T: Real>(
    k: &Consts<T>,
    inputs: &ImpulseInputs<'_, T>,
    p: usize,
    kirchhoff: &Mat3<T>,
) -> (Mat3<T>, Vec3<T>) {
    let particles = inputs.particles;
    let mass = particles.mass[p];
    let v = particles.v[p];
    let stress_scale = -k.dt * T::lit(4.0) * k.inv_dx * k.inv_dx * particles.volume[p];
    let c = &particles.c[p];
    let affine = kirchhoff * stress_scale + c * mass;
    (affine, (v + accel(k, inputs, p, &v) * k.dt) * mass)
}

/// Every particle's [`particle_impulse`], computed before the scatter in
/// parallel over fixed chunks, the stress of several particles at once in
/// SIMD lanes — bitwise what [`particle_impulse`] gives.
#[derive(Clone, Debug, Default)]
pub struct Impulses<T: Real> {
    pub affine: Vec<Mat3<T>>,
    pub momentum: Vec<Vec3<T>>,
    /// Each particle's polar rotation, when asked for and the world is a
    /// mixture (the backward pass's fixed-corotated gradients need it).
    pub rotation: Vec<Mat3<T>>,
}

impl<T: Real> Impulses<T> {
    pub fn compute(&mut self, k: &Consts<T>, inputs: &ImpulseInputs<'_, T>, rotations: bool) {
        let n = inputs.particles.len();
        let rotations = rotations && !inputs.pure_neo_hookean;
        self.affine.resize(n, Mat3::zeros());
        self.momentum.resize(n, Vec3::zeros());
        self.rotation
            .resize(if rotations { n } else { 0 }, Mat3::zeros());
        let width = T::Wide::WIDTH;
        // Without rotations, every chunk gets an empty slice.
        let mut rotation_chunks: Vec<&mut [Mat3<T>]> = self.rotation.chunks_mut(CHUNK).collect();
        rotation_chunks.resize_with(n.div_ceil(CHUNK), Default::default);
        self.affine
            .par_chunks_mut(CHUNK)
            .zip(self.momentum.par_chunks_mut(CHUNK))
            .zip(rotation_chunks.into_par_iter())
            .enumerate()
            .for_each(|(chunk, ((affine, momentum), rotation))| {
                let start = chunk * CHUNK;
                for group in (0..affine.len()).step_by(width) {
                    let len = width.min(affine.len() - group);
                    let (tau, r) = kirchhoff_group(inputs, start + group, len, rotations);
                    if let Some(r) = r.filter(|_| rotations) {
                        for i in 0..len {
                            let lane = r.lane(i);
                            rotation[group + i] = Mat3::from_fn(|row, col| lane[row][col]);
                        }
                    }
                    for i in 0..len {
                        let p = start + group + i;
                        let lane = tau.lane(i);
                        let kirchhoff = Mat3::from_fn(|r, c| lane[r][c]);
                        let (a, q) = impulse_from_kirchhoff(k, inputs, p, &kirchhoff);
                        affine[group + i] = a;
                        momentum[group + i] = q;
                    }
                }
            });
    }
}

/// Kirchhoff stress of particles `first..first + len` (`len` at most the
/// lane count; spare lanes repeat the last particle), and their polar
/// rotations when the fixed-corotated expert is weighted or `rotations`.
#[inline(always)]
fn kirchhoff_group<T: Real>(
    inputs: &ImpulseInputs<'_, T>,
    first: usize,
    len: usize,
    rotations: bool,
) -> (M3<T::Wide>, Option<M3<T::Wide>>) {
    let particles = inputs.particles;
    let material = inputs.material;
    let slot = |i: usize| first + i.min(len - 1);
    let f = M3::<T::Wide>::gather(|i, r, c| particles.f[slot(i)][(r, c)]);
    let mu = T::Wide::from_fn(|i| material.mu[slot(i)]);
    let lambda = T::Wide::from_fn(|i| material.lambda[slot(i)]);
    if inputs.pure_neo_hookean {
        return (neo_hookean_kirchhoff_lanes(&f, mu, lambda), None);
    }
    let weights = &material.expert_weights;
    let weight: [Option<T::Wide>; 3] = std::array::from_fn(|e| {
        (0..len)
            .any(|i| weights[first + i][e] != T::zero())
            .then(|| T::Wide::from_fn(|i| weights[slot(i)][e]))
    });
    let rotation = (weight[1].is_some() || rotations).then(|| {
        let (r, degenerate) = polar_rotation_lanes(&f);
        if (0..len).any(|i| T::Wide::mask_lane(degenerate, i)) {
            // A singular iterate: those lanes take the SVD's rotation.
            let fixed: Vec<Mat3<T>> = (0..len)
                .map(|i| polar_rotation(&particles.f[first + i]))
                .collect();
            M3::gather(|i, row, col| fixed[i.min(len - 1)][(row, col)])
        } else {
            r
        }
    });
    let tau = mixture_kirchhoff_lanes(&f, mu, lambda, &weight, rotation.as_ref());
    (tau, rotation)
}

/// The acceleration of particle `p` (velocity `v`) besides stress and
/// gravity: the actuators' and air drag.
#[inline(always)]
pub(crate) fn accel<T: Real>(
    k: &Consts<T>,
    inputs: &ImpulseInputs<'_, T>,
    p: usize,
    v: &Vec3<T>,
) -> Vec3<T> {
    let mut accel = Vec3::zeros();
    if let Some(ext) = inputs.external_accel {
        accel += ext[p];
    }
    if k.drag_linear != T::zero() || k.drag_quadratic != T::zero() {
        accel -= v * (k.drag_linear + k.drag_quadratic * v.norm());
    }
    accel
}
