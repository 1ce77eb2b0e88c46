//! Reverse-mode (vector-Jacobian) products of the Kirchhoff stresses in
//! [`crate::experts`] (method.md §3): given the upstream gradient `G` of
//! τ, the gradients with respect to F, μ, λ and the expert weights.
//!
//! Each expert's τ is linear in (μ, λ): `τₖ = μ Aₖ(F) + λ Bₖ(F)`, so
//! `⟨G, τₖ⟩ = μ ∂/∂μ + λ ∂/∂λ` — the weight gradient comes for free from
//! the parameter gradients, without re-evaluating τₖ.

use crate::experts::{Expert, inverse_transpose};
use crate::real::{Mat3, Real};
use crate::svd::polar_rotation;
use crate::svd_backward::polar_rotation_vjp;

/// Gradients of `⟨G, τ⟩` for the mixture Kirchhoff stress.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KirchhoffGrads<T> {
    pub f: Mat3<T>,
    pub mu: T,
    pub lambda: T,
    /// `⟨G, τₖ⟩` per expert (Neo-Hookean, fixed corotated, StVK), also for
    /// experts whose weight is zero (learnt weights need it).
    pub weights: [T; 3],
}

/// Gradients of `⟨G, τₖ⟩` for one expert at fixed weight 1.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExpertGrads<T> {
    pub f: Mat3<T>,
    pub mu: T,
    pub lambda: T,
}

/// Frobenius inner product `⟨A, B⟩ = tr(Aᵀ B)`.
#[inline(always)]
fn dot<T: Real>(a: &Mat3<T>, b: &Mat3<T>) -> T {
    a.component_mul(b).sum()
}

/// VJP of the Neo-Hookean Kirchhoff stress `τ = μ(FFᵀ − I) + λ ln J I`
/// (also the pure Neo-Hookean fast path, `neo_hookean_kirchhoff`, which has
/// no weight input and hence no weight gradient):
/// `∂/∂F = μ (G + Gᵀ) F + λ tr(G) F⁻ᵀ`.
#[inline]
pub fn neo_hookean_kirchhoff_vjp<T: Real>(
    f: &Mat3<T>,
    mu: T,
    lambda: T,
    grad_tau: &Mat3<T>,
) -> ExpertGrads<T> {
    let j = f.determinant();
    let g_sym2 = grad_tau + grad_tau.transpose();
    let trace_g = grad_tau.trace();
    let f_inv_t = inverse_transpose(f, j);
    ExpertGrads {
        f: g_sym2 * f * mu + f_inv_t * (lambda * trace_g),
        mu: dot(grad_tau, &(f * f.transpose())) - trace_g,
        lambda: trace_g * j.ln(),
    }
}

/// Gradients of the Neo-Hookean τ with respect to (μ, λ) only (for a
/// zero-weight expert, whose F gradient is not needed).
#[inline]
fn neo_hookean_param_grads<T: Real>(f: &Mat3<T>, grad_tau: &Mat3<T>) -> (T, T) {
    let trace_g = grad_tau.trace();
    (
        dot(grad_tau, &(f * f.transpose())) - trace_g,
        trace_g * f.determinant().ln(),
    )
}

/// VJP of the fixed-corotated Kirchhoff stress
/// `τ = 2μ(F − R)Fᵀ + λ(J − 1)J I`, given `R = polar_rotation(F)`:
/// `∂/∂F = 2μ (G F + Gᵀ(F − R)) − R'ᵀ[2μ G F] + λ(2J − 1)J tr(G) F⁻ᵀ`,
/// with `R'ᵀ` the polar-rotation VJP.
#[inline]
pub fn fixed_corotated_kirchhoff_vjp_with_rotation<T: Real>(
    f: &Mat3<T>,
    r: &Mat3<T>,
    mu: T,
    lambda: T,
    grad_tau: &Mat3<T>,
) -> ExpertGrads<T> {
    let j = f.determinant();
    let two_mu = mu + mu;
    let trace_g = grad_tau.trace();
    let f_minus_r = f - r;
    let g_f = grad_tau * f;
    let grad_r = -(g_f * two_mu);
    let f_inv_t = inverse_transpose(f, j);
    let volume_scale = lambda * (j + j - T::one()) * j * trace_g;
    ExpertGrads {
        f: (g_f + grad_tau.transpose() * f_minus_r) * two_mu
            + polar_rotation_vjp(f, r, &grad_r)
            + f_inv_t * volume_scale,
        mu: dot(grad_tau, &(f_minus_r * f.transpose())) * T::lit(2.0),
        lambda: trace_g * (j - T::one()) * j,
    }
}

/// VJP of the fixed-corotated Kirchhoff stress (computes the rotation).
#[inline]
pub fn fixed_corotated_kirchhoff_vjp<T: Real>(
    f: &Mat3<T>,
    mu: T,
    lambda: T,
    grad_tau: &Mat3<T>,
) -> ExpertGrads<T> {
    fixed_corotated_kirchhoff_vjp_with_rotation(f, &polar_rotation(f), mu, lambda, grad_tau)
}

#[inline]
fn fixed_corotated_param_grads<T: Real>(f: &Mat3<T>, r: &Mat3<T>, grad_tau: &Mat3<T>) -> (T, T) {
    let j = f.determinant();
    (
        dot(grad_tau, &((f - r) * f.transpose())) * T::lit(2.0),
        grad_tau.trace() * (j - T::one()) * j,
    )
}

/// VJP of the St. Venant–Kirchhoff Kirchhoff stress `τ = F S Fᵀ`,
/// `S = 2μE + λ tr(E) I`, `E = (FᵀF − I)/2`: with `H = Fᵀ G F`,
/// `∂/∂F = (G + Gᵀ) F S + F (2μ sym(H) + λ tr(H) I)`.
#[inline]
pub fn stvk_kirchhoff_vjp<T: Real>(
    f: &Mat3<T>,
    mu: T,
    lambda: T,
    grad_tau: &Mat3<T>,
) -> ExpertGrads<T> {
    let id = Mat3::<T>::identity();
    let ft = f.transpose();
    let green = (ft * f - id) * T::lit(0.5);
    let trace_e = green.trace();
    let two_mu = mu + mu;
    let second_piola = green * two_mu + id * (lambda * trace_e);
    let h = ft * grad_tau * f;
    let h_sym = (h + h.transpose()) * T::lit(0.5);
    let g_sym2 = grad_tau + grad_tau.transpose();
    ExpertGrads {
        f: g_sym2 * f * second_piola + f * (h_sym * two_mu + id * (lambda * h.trace())),
        mu: dot(&h, &green) * T::lit(2.0),
        lambda: h.trace() * trace_e,
    }
}

#[inline]
fn st_venant_kirchhoff_param_grads<T: Real>(f: &Mat3<T>, grad_tau: &Mat3<T>) -> (T, T) {
    let ft = f.transpose();
    let green = (ft * f - Mat3::identity()) * T::lit(0.5);
    let h = ft * grad_tau * f;
    (dot(&h, &green) * T::lit(2.0), h.trace() * green.trace())
}

/// VJP of one expert's Kirchhoff stress at weight 1.
#[inline]
pub fn expert_kirchhoff_vjp<T: Real>(
    expert: Expert,
    f: &Mat3<T>,
    mu: T,
    lambda: T,
    grad_tau: &Mat3<T>,
) -> ExpertGrads<T> {
    match expert {
        Expert::NeoHookean => neo_hookean_kirchhoff_vjp(f, mu, lambda, grad_tau),
        Expert::FixedCorotated => fixed_corotated_kirchhoff_vjp(f, mu, lambda, grad_tau),
        Expert::StVenantKirchhoff => stvk_kirchhoff_vjp(f, mu, lambda, grad_tau),
    }
}

/// VJP of [`crate::experts::mixture_kirchhoff`]: `τ = Σₖ wₖ τₖ`.
///
/// Like the forward, an expert with zero weight contributes nothing to the
/// F, μ and λ gradients (and the polar decomposition is only needed for
/// its weight gradient); its weight gradient `⟨G, τₖ⟩` is still returned.
#[inline]
pub fn mixture_kirchhoff_vjp<T: Real>(
    f: &Mat3<T>,
    mu: T,
    lambda: T,
    weights: &[T; 3],
    grad_tau: &Mat3<T>,
) -> KirchhoffGrads<T> {
    mixture_kirchhoff_vjp_with_rotation(f, &polar_rotation(f), mu, lambda, weights, grad_tau)
}

/// [`mixture_kirchhoff_vjp`] given `R = polar_rotation(F)` (the forward
/// pass's, saving its recomputation).
#[inline]
pub fn mixture_kirchhoff_vjp_with_rotation<T: Real>(
    f: &Mat3<T>,
    r: &Mat3<T>,
    mu: T,
    lambda: T,
    weights: &[T; 3],
    grad_tau: &Mat3<T>,
) -> KirchhoffGrads<T> {
    let mut out = KirchhoffGrads {
        f: Mat3::zeros(),
        mu: T::zero(),
        lambda: T::zero(),
        weights: [T::zero(); 3],
    };
    for (k, &w) in weights.iter().enumerate() {
        let (grad_mu, grad_lambda) = if w != T::zero() {
            let expert = match Expert::ALL[k] {
                Expert::FixedCorotated => {
                    fixed_corotated_kirchhoff_vjp_with_rotation(f, r, mu, lambda, grad_tau)
                }
                expert => expert_kirchhoff_vjp(expert, f, mu, lambda, grad_tau),
            };
            out.f += expert.f * w;
            (expert.mu, expert.lambda)
        } else {
            match k {
                0 => neo_hookean_param_grads(f, grad_tau),
                1 => fixed_corotated_param_grads(f, r, grad_tau),
                _ => st_venant_kirchhoff_param_grads(f, grad_tau),
            }
        };
        out.mu += grad_mu * w;
        out.lambda += grad_lambda * w;
        // ⟨G, τₖ⟩ by linearity of τₖ in (μ, λ).
        out.weights[k] = mu * grad_mu + lambda * grad_lambda;
    }
    out
}
