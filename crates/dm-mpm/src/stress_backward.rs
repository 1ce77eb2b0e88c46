//! Backward twin of `stress.rs`: the adjoint of the per-particle impulse
//! `affine = s τ(F) + m C`, `momentum = m (v + dt a)` with
//! `s = −dt V 4/dx²` and `a = a_ext − (k₁ + k₂|v|) v` (air drag).
//! (Viscous damping is implicit, on the grid: `viscosity_backward.rs`.)

use crate::experts_backward::{
    KirchhoffGrads, mixture_kirchhoff_vjp, mixture_kirchhoff_vjp_with_rotation,
    neo_hookean_kirchhoff_vjp,
};
use crate::real::{Mat3, Real, Vec3};
use crate::state::Consts;
use crate::stress::{ImpulseInputs, accel};

/// Adjoint of one particle's impulse with respect to its inputs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImpulseGrads<T> {
    pub v: Vec3<T>,
    pub f: Mat3<T>,
    pub c: Mat3<T>,
    pub mu: T,
    pub lambda: T,
    pub weights: [T; 3],
    /// Adjoint of the external (actuator) acceleration.
    pub external_accel: Vec3<T>,
    /// This particle's share of the adjoints of the effect parameters
    /// `[k₁ (air_drag_linear), k₂ (air_drag_quadratic)]`; a parameter's
    /// gradient is the sum over particles.
    pub effects: [T; 2],
    /// Adjoint of the particle's mass (a density gradient's parameter):
    /// `Ā : C + M̄ · (v + dt a)`.
    pub mass: T,
}

/// VJP of [`crate::stress::particle_impulse`] for particle `p`, given the
/// adjoints of its affine matrix and momentum, and (for a mixture) the
/// polar rotation of its F.
#[inline]
pub fn particle_impulse_vjp<T: Real>(
    k: &Consts<T>,
    inputs: &ImpulseInputs<'_, T>,
    p: usize,
    rotation: Option<&Mat3<T>>,
    grad_affine: &Mat3<T>,
    grad_momentum: &Vec3<T>,
) -> ImpulseGrads<T> {
    let particles = inputs.particles;
    let material = inputs.material;
    let mass = particles.mass[p];
    let v = particles.v[p];
    let stress_scale = -k.dt * T::lit(4.0) * k.inv_dx * k.inv_dx * particles.volume[p];
    let grad_tau = grad_affine * stress_scale;
    let (f, mu, lambda) = (&particles.f[p], material.mu[p], material.lambda[p]);
    // A pure Neo-Hookean world has no learnable expert weights: skip their
    // gradients (they would cost a polar decomposition per particle).
    let kg = if inputs.pure_neo_hookean {
        let g = neo_hookean_kirchhoff_vjp(f, mu, lambda, &grad_tau);
        KirchhoffGrads {
            f: g.f,
            mu: g.mu,
            lambda: g.lambda,
            weights: [T::zero(); 3],
        }
    } else {
        let weights = &material.expert_weights[p];
        match rotation {
            Some(r) => mixture_kirchhoff_vjp_with_rotation(f, r, mu, lambda, weights, &grad_tau),
            None => mixture_kirchhoff_vjp(f, mu, lambda, weights, &grad_tau),
        }
    };
    let grad_accel = grad_momentum * (mass * k.dt);
    let mut grad_v = grad_momentum * mass;
    // ∂a/∂k₁ = −v, ∂a/∂k₂ = −|v| v.
    let accel_along_v = grad_accel.dot(&v);
    let effects = [-accel_along_v, -v.norm() * accel_along_v];
    if k.drag_linear != T::zero() || k.drag_quadratic != T::zero() {
        let speed = v.norm();
        grad_v -= grad_accel * (k.drag_linear + k.drag_quadratic * speed);
        if speed > T::zero() {
            grad_v -= v * (k.drag_quadratic * v.dot(&grad_accel) / speed);
        }
    }
    let grad_c = grad_affine * mass;
    let grad_mass = grad_affine.component_mul(&particles.c[p]).sum()
        + grad_momentum.dot(&(v + accel(k, inputs, p, &v) * k.dt));
    ImpulseGrads {
        v: grad_v,
        f: kg.f,
        c: grad_c,
        mu: kg.mu,
        lambda: kg.lambda,
        weights: kg.weights,
        external_accel: if inputs.external_accel.is_some() {
            grad_accel
        } else {
            Vec3::zeros()
        },
        effects,
        mass: grad_mass,
    }
}
