//! Reverse-mode (vector-Jacobian) products of the material patches in
//! [`crate::material`] (method.md §3): from per-particle gradients of
//! (μ, λ, expert weights) back to the unbounded per-patch parameters.
//!
//! Forward chain: patch raw values → bounded E (log-sigmoid), ν (sigmoid)
//! and softmax expert weights per patch → blended to particles with the
//! fixed β → Lamé (μ, λ) per particle.

use crate::material::{MaterialBounds, MaterialPatches, PatchParams, sigmoid, softmax3};
use crate::real::Real;

/// VJP of [`crate::experts::lame`]: `(∂L/∂E, ∂L/∂ν)` from `(∂L/∂μ, ∂L/∂λ)`.
///
/// `μ = E / (2(1 + ν))`, `λ = E ν / D` with `D = (1 + ν)(1 − 2ν)`;
/// `∂λ/∂ν = E (1 + 2ν²) / D²`.
#[inline]
pub fn lame_vjp<T: Real>(youngs: T, poisson: T, grad_mu: T, grad_lambda: T) -> (T, T) {
    let one = T::one();
    let two = T::lit(2.0);
    let one_plus = one + poisson;
    let denom = one_plus * (one - two * poisson);
    let dmu_de = one / (two * one_plus);
    let dmu_dnu = -youngs / (two * one_plus * one_plus);
    let dlambda_de = poisson / denom;
    let dlambda_dnu = youngs * (one + two * poisson * poisson) / (denom * denom);
    (
        grad_mu * dmu_de + grad_lambda * dlambda_de,
        grad_mu * dmu_dnu + grad_lambda * dlambda_dnu,
    )
}

/// VJP of [`softmax3`]: `∂L/∂lₖ = qₖ (∂L/∂qₖ − Σⱼ qⱼ ∂L/∂qⱼ)`.
#[inline]
pub fn softmax3_vjp(logits: &[f64; 3], grad_q: &[f64; 3]) -> [f64; 3] {
    let q = softmax3(logits);
    let mean = q[0] * grad_q[0] + q[1] * grad_q[1] + q[2] * grad_q[2];
    [0, 1, 2].map(|k| q[k] * (grad_q[k] - mean))
}

impl MaterialBounds {
    /// `d youngs(raw) / d raw = E (ln hi − ln lo) s (1 − s)`, `s = sigmoid(raw)`.
    #[inline]
    pub fn youngs_derivative(&self, raw: f64) -> f64 {
        let [lo, hi] = self.youngs_pa;
        let s = sigmoid(raw);
        self.youngs(raw) * (hi.ln() - lo.ln()) * s * (1.0 - s)
    }

    /// `d poisson(raw) / d raw = (hi − lo) s (1 − s)`.
    #[inline]
    pub fn poisson_derivative(&self, raw: f64) -> f64 {
        let [lo, hi] = self.poisson;
        let s = sigmoid(raw);
        (hi - lo) * s * (1.0 - s)
    }
}

impl MaterialPatches {
    /// Transpose of [`MaterialPatches::blend`]: scatters per-particle
    /// gradients back to patches with the same β.
    pub fn blend_vjp(&self, grad_particles: &[f64]) -> Vec<f64> {
        let mut grad_patch = vec![0.0; self.patch_count()];
        for ((ids, beta), &g) in self.neighbours.iter().zip(&self.beta).zip(grad_particles) {
            for s in 0..3 {
                grad_patch[ids[s] as usize] += beta[s] * g;
            }
        }
        grad_patch
    }

    /// VJP of [`MaterialPatches::particle_fields`]: gradients of the
    /// per-particle E (Pa), ν and expert weights, back to the patch raw
    /// values and logits.
    ///
    /// # Panics
    /// If the gradient slices are not one per particle or `params` is not
    /// one per patch (a caller bug, not a data condition).
    pub fn particle_fields_vjp(
        &self,
        params: &PatchParams,
        bounds: &MaterialBounds,
        grad_youngs: &[f64],
        grad_poisson: &[f64],
        grad_weights: &[[f64; 3]],
    ) -> PatchParams {
        let particles = self.neighbours.len();
        let patches = self.patch_count();
        assert_eq!(
            grad_youngs.len(),
            particles,
            "grad_youngs: one per particle"
        );
        assert_eq!(
            grad_poisson.len(),
            particles,
            "grad_poisson: one per particle"
        );
        assert_eq!(
            grad_weights.len(),
            particles,
            "grad_weights: one per particle"
        );
        assert_eq!(
            params.youngs_raw.len(),
            patches,
            "youngs_raw: one per patch"
        );
        assert_eq!(
            params.poisson_raw.len(),
            patches,
            "poisson_raw: one per patch"
        );
        assert_eq!(params.logits.len(), patches, "logits: one per patch");

        let youngs_raw = self
            .blend_vjp(grad_youngs)
            .iter()
            .zip(&params.youngs_raw)
            .map(|(g, &raw)| g * bounds.youngs_derivative(raw))
            .collect();
        let poisson_raw = self
            .blend_vjp(grad_poisson)
            .iter()
            .zip(&params.poisson_raw)
            .map(|(g, &raw)| g * bounds.poisson_derivative(raw))
            .collect();

        let mut grad_q = vec![[0.0; 3]; patches];
        for ((ids, beta), g) in self.neighbours.iter().zip(&self.beta).zip(grad_weights) {
            for s in 0..3 {
                let patch = &mut grad_q[ids[s] as usize];
                for k in 0..3 {
                    patch[k] += beta[s] * g[k];
                }
            }
        }
        let logits = params
            .logits
            .iter()
            .zip(&grad_q)
            .map(|(l, g)| softmax3_vjp(l, g))
            .collect();
        PatchParams {
            youngs_raw,
            poisson_raw,
            logits,
        }
    }

    /// VJP of [`MaterialPatches::particle_material`]: per-particle gradients
    /// of (μ, λ, expert weights) — what the stress backward produces — to
    /// patch-parameter gradients. Recomputes the forward E, ν per particle
    /// (Lamé is applied after blending) and chains through [`lame_vjp`].
    ///
    /// # Panics
    /// As [`MaterialPatches::particle_fields_vjp`].
    pub fn particle_material_vjp<T: Real>(
        &self,
        params: &PatchParams,
        bounds: &MaterialBounds,
        grad_mu: &[T],
        grad_lambda: &[T],
        grad_weights: &[[T; 3]],
    ) -> PatchParams {
        let particles = self.neighbours.len();
        assert_eq!(grad_mu.len(), particles, "grad_mu: one per particle");
        assert_eq!(
            grad_lambda.len(),
            particles,
            "grad_lambda: one per particle"
        );
        let (youngs, poisson, _) = self.particle_fields(params, bounds);
        let (grad_youngs, grad_poisson): (Vec<f64>, Vec<f64>) = youngs
            .iter()
            .zip(&poisson)
            .zip(grad_mu.iter().zip(grad_lambda))
            .map(|((&e, &nu), (gm, gl))| lame_vjp(e, nu, gm.to_f64(), gl.to_f64()))
            .unzip();
        let grad_weights: Vec<[f64; 3]> =
            grad_weights.iter().map(|g| g.map(|x| x.to_f64())).collect();
        self.particle_fields_vjp(params, bounds, &grad_youngs, &grad_poisson, &grad_weights)
    }
}
