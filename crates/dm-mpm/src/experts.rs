//! The three constitutive experts of the mixture (method.md §3): first
//! Piola-Kirchhoff stress P(F) for given Lamé parameters.

use crate::real::{Mat3, Real};
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
    let ft = f.transpose();
    let id = Mat3::<T>::identity();
    let mut tau = Mat3::zeros();
    let j = f.determinant();
    if weights[0] != T::zero() {
        tau += ((f * ft - id) * mu + id * (lambda * j.ln())) * weights[0];
    }
    if weights[1] != T::zero() {
        let r = polar_rotation(f);
        tau += ((f - r) * ft * (mu + mu) + id * (lambda * (j - T::one()) * j)) * weights[1];
    }
    if weights[2] != T::zero() {
        let green = (ft * f - id) * T::lit(0.5);
        tau += f * (green * (mu + mu) + id * (lambda * green.trace())) * ft * weights[2];
    }
    tau
}

/// Kirchhoff stress of the pure Neo-Hookean expert (the fast path).
#[inline]
pub fn neo_hookean_kirchhoff<T: Real>(f: &Mat3<T>, mu: T, lambda: T) -> Mat3<T> {
    let id = Mat3::<T>::identity();
    (f * f.transpose() - id) * mu + id * (lambda * f.determinant().ln())
}
