//! The three constitutive experts of the mixture (method.md §3): first
//! Piola-Kirchhoff stress P(F) for given Lamé parameters.

use crate::lanes::{Lanes, M3};
use crate::real::{Mat3, Real, from_lanes, to_lanes};
use crate::svd::polar_rotation;

/// Index of each expert in the per-particle weight triple.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Expert {
    NeoHookean = 0,
    FixedCorotated = 1,
    StVenantKirchhoff = 2,
}

impl Expert {
    pub const ALL: [Expert; 3] = [
        Expert::NeoHookean,
        Expert::FixedCorotated,
        Expert::StVenantKirchhoff,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Expert::NeoHookean => "neo_hookean",
            Expert::FixedCorotated => "fixed_corotated",
            Expert::StVenantKirchhoff => "st_venant_kirchhoff",
        }
    }
}

/// Lamé parameters from Young's modulus (Pa) and Poisson's ratio.
#[inline]
pub fn lame<T: Real>(youngs: T, poisson: T) -> (T, T) {
    let one = T::one();
    let two = T::lit(2.0);
    let mu = youngs / (two * (one + poisson));
    let lambda = youngs * poisson / ((one + poisson) * (one - two * poisson));
    (mu, lambda)
}

/// Compressible Neo-Hookean: P = μ(F − F⁻ᵀ) + λ ln(J) F⁻ᵀ.
#[inline]
pub fn neo_hookean<T: Real>(f: &Mat3<T>, mu: T, lambda: T) -> Mat3<T> {
    let j = f.determinant();
    let f_inv_t = inverse_transpose(f, j);
    (f - f_inv_t) * mu + f_inv_t * (lambda * j.ln())
}

/// Fixed corotated (Stomakhin et al. 2012): P = 2μ(F − R) + λ(J − 1) J F⁻ᵀ.
#[inline]
pub fn fixed_corotated<T: Real>(f: &Mat3<T>, mu: T, lambda: T) -> Mat3<T> {
    let j = f.determinant();
    let r = polar_rotation(f);
    let f_inv_t = inverse_transpose(f, j);
    (f - r) * (mu + mu) + f_inv_t * (lambda * (j - T::one()) * j)
}

/// St. Venant–Kirchhoff: P = F (2μ E + λ tr(E) I), E = (FᵀF − I)/2.
#[inline]
pub fn st_venant_kirchhoff<T: Real>(f: &Mat3<T>, mu: T, lambda: T) -> Mat3<T> {
    let green = (f.transpose() * f - Mat3::identity()) * T::lit(0.5);
    f * (green * (mu + mu) + Mat3::identity() * (lambda * green.trace()))
}

pub fn expert_stress<T: Real>(expert: Expert, f: &Mat3<T>, mu: T, lambda: T) -> Mat3<T> {
    match expert {
        Expert::NeoHookean => neo_hookean(f, mu, lambda),
        Expert::FixedCorotated => fixed_corotated(f, mu, lambda),
        Expert::StVenantKirchhoff => st_venant_kirchhoff(f, mu, lambda),
    }
}

/// P_mix = Σ_k w_k P_k; experts with zero weight are skipped (so a pure
/// Neo-Hookean particle never pays for the polar decomposition).
#[inline]
pub fn mixture_stress<T: Real>(f: &Mat3<T>, mu: T, lambda: T, weights: &[T; 3]) -> Mat3<T> {
    let mut p = Mat3::zeros();
    for expert in Expert::ALL {
        let w = weights[expert as usize];
        if w != T::zero() {
            p += expert_stress(expert, f, mu, lambda) * w;
        }
    }
    p
}

/// F⁻ᵀ given det F (cofactor matrix / J).
#[inline(always)]
pub fn inverse_transpose<T: Real>(f: &Mat3<T>, j: T) -> Mat3<T> {
    let cof = Mat3::new(
        f[(1, 1)] * f[(2, 2)] - f[(1, 2)] * f[(2, 1)],
        f[(1, 2)] * f[(2, 0)] - f[(1, 0)] * f[(2, 2)],
        f[(1, 0)] * f[(2, 1)] - f[(1, 1)] * f[(2, 0)],
        f[(0, 2)] * f[(2, 1)] - f[(0, 1)] * f[(2, 2)],
        f[(0, 0)] * f[(2, 2)] - f[(0, 2)] * f[(2, 0)],
        f[(0, 1)] * f[(2, 0)] - f[(0, 0)] * f[(2, 1)],
        f[(0, 1)] * f[(1, 2)] - f[(0, 2)] * f[(1, 1)],
        f[(0, 2)] * f[(1, 0)] - f[(0, 0)] * f[(1, 2)],
        f[(0, 0)] * f[(1, 1)] - f[(0, 1)] * f[(1, 0)],
    );
    cof / j
}

/// Kirchhoff stress τ = P Fᵀ of the mixture, what MLS-MPM scatters. Each
/// expert has a form without F⁻¹ (NH: μ(FFᵀ − I) + λ ln J I; FCR:
/// 2μ(F − R)Fᵀ + λ(J − 1)J I; StVK: F(2μE + λ tr E I)Fᵀ), which is both
/// cheaper and defined for any F with J > 0.
#[inline]
pub fn mixture_kirchhoff<T: Real>(f: &Mat3<T>, mu: T, lambda: T, weights: &[T; 3]) -> Mat3<T> {
    let weights = weights.map(|w| (w != T::zero()).then_some(w));
    let rotation = weights[1].map(|_| to_lanes(&polar_rotation(f)));
    from_lanes(&mixture_kirchhoff_lanes(
        &to_lanes(f),
        mu,
        lambda,
        &weights,
        rotation.as_ref(),
    ))
}

/// [`mixture_kirchhoff`] of every lane. Experts whose weight is `None`
/// are skipped; `rotation` (the polar rotation of `f`) is needed when the
/// fixed-corotated expert is weighted.
#[inline(always)]
pub fn mixture_kirchhoff_lanes<L: Lanes>(
    f: &M3<L>,
    mu: L,
    lambda: L,
    weights: &[Option<L>; 3],
    rotation: Option<&M3<L>>,
) -> M3<L>
where
    L::Scalar: Real,
{
    let lit = |x: f64| L::broadcast(<L::Scalar as Real>::lit(x));
    let one = lit(1.0);
    let ft = f.transpose();
    let j = f.determinant();
    let mut tau: Option<M3<L>> = None;
    let mut accumulate = |term: M3<L>| {
        tau = Some(match tau {
            Some(sum) => sum.add(&term),
            None => term,
        })
    };
    if let Some(w) = weights[0] {
        accumulate(neo_hookean_kirchhoff_with_det(f, &ft, j, mu, lambda).scale(w));
    }
    if let (Some(w), Some(r)) = (weights[1], rotation) {
        let term = f
            .sub(r)
            .matmul(&ft)
            .scale(mu + mu)
            .add_diagonal(lambda * (j - one) * j);
        accumulate(term.scale(w));
    }
    if let Some(w) = weights[2] {
        let green = ft.matmul(f).add_diagonal(-one).scale(lit(0.5));
        let inner = green.scale(mu + mu).add_diagonal(lambda * green.trace());
        accumulate(f.matmul(&inner).matmul(&ft).scale(w));
    }
    tau.unwrap_or_else(|| M3::from_fn(|_, _| lit(0.0)))
}

/// Kirchhoff stress of the pure Neo-Hookean expert (the fast path).
#[inline]
pub fn neo_hookean_kirchhoff<T: Real>(f: &Mat3<T>, mu: T, lambda: T) -> Mat3<T> {
    from_lanes(&neo_hookean_kirchhoff_lanes(&to_lanes(f), mu, lambda))
}

/// [`neo_hookean_kirchhoff`] of every lane.
#[inline(always)]
pub fn neo_hookean_kirchhoff_lanes<L: Lanes>(f: &M3<L>, mu: L, lambda: L) -> M3<L>
where
    L::Scalar: Real,
{
    neo_hookean_kirchhoff_with_det(f, &f.transpose(), f.determinant(), mu, lambda)
}

#[inline(always)]
fn neo_hookean_kirchhoff_with_det<L: Lanes>(f: &M3<L>, ft: &M3<L>, j: L, mu: L, lambda: L) -> M3<L>
where
    L::Scalar: Real,
{
    let one = L::broadcast(<L::Scalar as Real>::lit(1.0));
    f.matmul(ft)
        .add_diagonal(-one)
        .scale(mu)
        .add_diagonal(lambda * L::natural_log(j))
}
