//! Stage 1 of a substep: per-particle stress and external forces, turned
//! into the two quantities P2G scatters (MLS-MPM, Hu et al. 2018):
//! the affine matrix `-dt V 4/dx² P Fᵀ + m C` and the momentum
//! `m v + dt m a_ext`.

use crate::experts::{mixture_kirchhoff, neo_hookean_kirchhoff};
use crate::material::ParticleMaterial;
use crate::real::{Mat3, Real, Vec3};
use crate::state::{Consts, Particles};

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

/// `(affine, momentum)` of particle `p`: what P2G scatters. Pure, so P2G
/// evaluates it inline (no per-particle buffers to stream through memory)
/// and the backward pass can recompute it.
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
    let mass = particles.mass[p];
    let v = particles.v[p];
    let stress_scale = -k.dt * T::lit(4.0) * k.inv_dx * k.inv_dx * particles.volume[p];
    let c = &particles.c[p];
    let affine = kirchhoff * stress_scale + c * mass;
    (affine, (v + accel(k, inputs, p, &v) * k.dt) * mass)
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
