//! Reverse-mode (vector-Jacobian) products of the 3x3 decompositions in
//! [`crate::svd`]: the singular-value clamp and the polar rotation.
//!
//! Each `*_vjp` takes the forward inputs and the upstream gradient of the
//! forward output, and returns the gradient with respect to the input.

use crate::real::{Mat3, Real, Vec3};
use crate::svd::{clamp_singular_values, svd3};

/// Gap below which two singular values count as equal in the clamp VJP
/// (relative to their size): the divided difference of the clamp is then
/// replaced by its slope at their mean. The divided difference of a
/// 1-Lipschitz monotone map is in [0, 1] however close the values are, so
/// this only avoids 0/0; 1e-12 is far below any gap that matters in f64 and
/// f32 gaps that small already round to 0.
const SIGMA_EQUAL_RTOL: f64 = 1e-12;

/// Floor on |σᵢ + σⱼ| in the clamp VJP. The sum only nears zero for an
/// inverted F (negative last singular value), where the SVD's rotation
/// derivative is genuinely unbounded; the floor keeps the result finite.
const SIGMA_SUM_FLOOR: f64 = 1e-12;

/// Skew matrix `[w]×` with `[w]× v = w × v`.
#[inline(always)]
fn cross_matrix<T: Real>(w: &Vec3<T>) -> Mat3<T> {
    Mat3::new(
        T::zero(),
        -w.z,
        w.y,
        w.z,
        T::zero(),
        -w.x,
        -w.y,
        w.x,
        T::zero(),
    )
}

/// `vee(A − Aᵀ)`: the vector `a` with `⟨A, [w]×⟩ = w · a` for every `w`.
#[inline(always)]
fn skew_axial<T: Real>(a: &Mat3<T>) -> Vec3<T> {
    Vec3::new(
        a[(2, 1)] - a[(1, 2)],
        a[(0, 2)] - a[(2, 0)],
        a[(1, 0)] - a[(0, 1)],
    )
}

/// VJP of the polar rotation `R(F)` (`F = R S`, S symmetric positive
/// definite): given `R = polar_rotation(F)` and `∂L/∂R`, returns `∂L/∂F`.
///
/// Derivation: with `dR = R [ω]×`, the skew part of `Rᵀ dF = [ω]× S + dS`
/// gives `(tr S · I − S) ω = vee(Rᵀ dF − dFᵀ R)`. Transposing that linear
/// map: `y = (tr S · I − S)⁻¹ vee(Rᵀ G − Gᵀ R)` and `∂L/∂F = R [y]×`.
/// `tr S · I − S` has eigenvalues σᵢ + σⱼ > 0, so the solve is well posed
/// for det F > 0; a singular system (an F the forward cannot handle
/// either) yields a zero gradient rather than NaNs.
#[inline]
pub fn polar_rotation_vjp<T: Real>(f: &Mat3<T>, r: &Mat3<T>, grad_r: &Mat3<T>) -> Mat3<T> {
    let rt = r.transpose();
    let s = rt * f;
    // S is symmetric up to the forward's round-off; use its symmetric part.
    let s = (s + s.transpose()) * T::lit(0.5);
    let system = Mat3::identity() * s.trace() - s;
    let rhs = skew_axial(&(rt * grad_r));
    match system.try_inverse() {
        Some(inverse) => r * cross_matrix(&(inverse * rhs)),
        None => Mat3::zeros(),
    }
}

/// VJP of `F ↦ clamp_singular_values(F, lo, hi).unwrap_or(F)`.
///
/// When the forward leaves F alone (the common case, decided by the same
/// call) the map is the identity and so is its VJP. Otherwise, with
/// `F = U Σ Vᵀ` and output `U Σ' Vᵀ`, `Σ' = clamp(Σ)`, the standard SVD
/// derivative in the rotated frame `P = Uᵀ dF V` gives the output
/// variation `Q = Uᵀ dOut V` as
///
/// * `Qᵢᵢ = clamp'(σᵢ) Pᵢᵢ` — zero for a clamped σᵢ (only the clamped
///   singular values stop carrying gradient; the rotations still do);
/// * `Qᵢⱼ = ½ (σ'ⱼ − σ'ᵢ)/(σⱼ − σᵢ) (Pᵢⱼ + Pⱼᵢ) + ½ (σ'ⱼ + σ'ᵢ)/(σⱼ + σᵢ) (Pᵢⱼ − Pⱼᵢ)`,
///
/// which is the usual `1/(σⱼ² − σᵢ²)` form regrouped into symmetric and
/// antisymmetric parts. That map is self-adjoint, so the VJP is
/// `U Q(Uᵀ G V) Vᵀ`.
pub fn clamp_singular_values_vjp<T: Real>(
    f: &Mat3<T>,
    lo: T,
    hi: T,
    grad_out: &Mat3<T>,
) -> Mat3<T> {
    if clamp_singular_values(f, lo, hi).is_none() {
        return *grad_out;
    }
    let svd = svd3(f);
    let sigma = svd.sigma;
    let clamped = sigma.map(|x| x.max(lo).min(hi));
    let slope = |x: T| {
        if x > lo && x < hi {
            T::one()
        } else {
            T::zero()
        }
    };
    let g = svd.u.transpose() * grad_out * svd.v;
    let mut q = Mat3::zeros();
    for i in 0..3 {
        q[(i, i)] = slope(sigma[i]) * g[(i, i)];
    }
    for i in 0..3 {
        for j in (i + 1)..3 {
            let gap = sigma[j] - sigma[i];
            let size = sigma[i].abs() + sigma[j].abs();
            let divided_difference = if gap.abs() <= T::lit(SIGMA_EQUAL_RTOL) * size {
                slope((sigma[i] + sigma[j]) * T::lit(0.5))
            } else {
                // In [0, 1] up to round-off: clamp is 1-Lipschitz and monotone.
                ((clamped[j] - clamped[i]) / gap)
                    .max(T::zero())
                    .min(T::one())
            };
            let sum = sigma[i] + sigma[j];
            let floor = T::lit(SIGMA_SUM_FLOOR);
            let sum = if sum.abs() < floor {
                if sum < T::zero() { -floor } else { floor }
            } else {
                sum
            };
            let rotation_ratio = (clamped[i] + clamped[j]) / sum;
            let sym = (g[(i, j)] + g[(j, i)]) * T::lit(0.5) * divided_difference;
            let anti = (g[(i, j)] - g[(j, i)]) * T::lit(0.5) * rotation_ratio;
            q[(i, j)] = sym + anti;
            q[(j, i)] = sym - anti;
        }
    }
    svd.u * q * svd.v.transpose()
}
