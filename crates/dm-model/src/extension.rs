//! Physics a diagnosis added to a fitted model that does not
//! live in `PhysicsConfig::effects`: a stiffer ball, a density gradient
//! and a time shift of the hand track. The effects that do (drag,
//! friction, plasticity, viscosity, gravity) are set on `physics` itself.

use dm_bundle::Bundle;
use dm_mpm::{ParticleMaterial, Real};
use serde::{Deserialize, Serialize};

/// A ball of particles whose Lamé parameters are scaled by `factor`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StiffBall {
    pub centre: [f64; 3],
    pub radius: f64,
    pub factor: f64,
}

/// Density graded linearly along `axis` (unit vector): the particle at
/// the low end of the object along it has factor 1, the one at the high
/// end `1 + excess` (a negative `excess` makes the low end heavy by
/// `1 + |excess|`), so every factor is ≥ 1 and the CFL substep chosen for
/// the base density stays stable.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DensityGradient {
    pub axis: [f64; 3],
    pub excess: f64,
}

/// Extension terms of a model; the default adds nothing.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ModelExtension {
    /// The actuators follow the recorded hand track `hand_lag_frames`
    /// frames later (linear interpolation, held at the clip's ends): a
    /// positive value means the recording lags the real hands.
    pub hand_lag_frames: f64,
    pub stiff_ball: Option<StiffBall>,
    pub density: Option<DensityGradient>,
}

impl ModelExtension {
    pub fn is_empty(&self) -> bool {
        self.hand_lag_frames == 0.0 && self.stiff_ball.is_none() && self.density.is_none()
    }

    /// Which particles (caller's order) lie inside the stiff ball, if any.
    fn inside_ball<'a>(
        &'a self,
        particles: &'a [[f64; 3]],
    ) -> Option<impl Iterator<Item = bool> + 'a> {
        let ball = self.stiff_ball.as_ref()?;
        Some(particles.iter().map(move |p| {
            let d2: f64 = (0..3).map(|a| (p[a] - ball.centre[a]).powi(2)).sum();
            d2 < ball.radius * ball.radius
        }))
    }

    /// Scales the material inside the stiff ball (caller's particle order).
    pub fn apply_to_material<T: Real>(
        &self,
        particles: &[[f64; 3]],
        material: &mut ParticleMaterial<T>,
    ) {
        let (Some(ball), Some(inside)) = (&self.stiff_ball, self.inside_ball(particles)) else {
            return;
        };
        let factor = T::lit(ball.factor);
        for (i, _) in inside.enumerate().filter(|(_, inside)| *inside) {
            material.mu[i] *= factor;
            material.lambda[i] *= factor;
        }
    }

    /// ∂L/∂ln(factor) of the stiff ball, given ∂L/∂μ and ∂L/∂λ of the
    /// scaled material the world ran (`base` is it before
    /// [`Self::apply_to_material`]): μ = factor μ_base inside the ball, so
    /// ∂μ/∂ln factor = μ. Zero without a ball.
    pub fn stiffness_log_factor_gradient(
        &self,
        particles: &[[f64; 3]],
        base: &ParticleMaterial<f32>,
        grad_mu: &[f32],
        grad_lambda: &[f32],
    ) -> f64 {
        let (Some(ball), Some(inside)) = (&self.stiff_ball, self.inside_ball(particles)) else {
            return 0.0;
        };
        inside
            .enumerate()
            .filter(|(_, inside)| *inside)
            .map(|(i, _)| {
                ball.factor
                    * (f64::from(grad_mu[i]) * f64::from(base.mu[i])
                        + f64::from(grad_lambda[i]) * f64::from(base.lambda[i]))
            })
            .sum()
    }

    /// Turns ∂L/∂μ, ∂L/∂λ of the scaled material into those of the base
    /// material (the fitted fields): × factor inside the stiff ball.
    pub fn base_material_grads(
        &self,
        particles: &[[f64; 3]],
        grad_mu: &mut [f32],
        grad_lambda: &mut [f32],
    ) {
        let (Some(ball), Some(inside)) = (&self.stiff_ball, self.inside_ball(particles)) else {
            return;
        };
        let factor = ball.factor as f32;
        for (i, _) in inside.enumerate().filter(|(_, inside)| *inside) {
            grad_mu[i] *= factor;
            grad_lambda[i] *= factor;
        }
    }

    /// Each particle's position along the density gradient's axis, 0 at
    /// the object's low end and 1 at its high end.
    fn density_coordinates(g: &DensityGradient, particles: &[[f64; 3]]) -> Vec<f64> {
        let coords: Vec<f64> = particles
            .iter()
            .map(|p| (0..3).map(|a| p[a] * g.axis[a]).sum())
            .collect();
        let lo = coords.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = coords.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let span = (hi - lo).max(1e-9);
        coords.iter().map(|c| (c - lo) / span).collect()
    }

    /// The factor at coordinate `s` for `excess`, and its derivative in
    /// `excess`. The two branches meet at excess 0 with slopes s and
    /// −(1 − s), which differ by a constant: once the mean factor is
    /// divided out (the diagnosis keeps the total mass), the masses are
    /// smooth through 0 to first order.
    fn density_factor(excess: f64, s: f64) -> (f64, f64) {
        if excess >= 0.0 {
            (1.0 + excess * s, s)
        } else {
            (1.0 - excess * (1.0 - s), -(1.0 - s))
        }
    }

    /// Per-particle density factors (≥ 1), or `None` for a uniform density.
    pub fn density_factors(&self, particles: &[[f64; 3]]) -> Option<Vec<f64>> {
        let g = self.density.as_ref()?;
        Some(
            Self::density_coordinates(g, particles)
                .into_iter()
                .map(|s| Self::density_factor(g.excess, s).0)
                .collect(),
        )
    }

    /// Mean of [`Self::density_factors`] (1 without a gradient): the base
    /// density divided by it keeps the object's total mass.
    pub fn mean_density_factor(&self, particles: &[[f64; 3]]) -> f64 {
        self.density_factors(particles)
            .map_or(1.0, |f| f.iter().sum::<f64>() / f.len().max(1) as f64)
    }

    /// ∂L/∂excess of the density gradient with the total mass kept (the
    /// base density following 1 / mean factor, as
    /// [`Self::set_density_excess`] writes it), given each particle's mass
    /// and its adjoint: m_p ∝ f_p / F, so
    /// ∂L/∂a = Σ_p m̄_p m_p (f_p′ / f_p − F′ / F). Zero without a gradient.
    pub fn density_excess_gradient(
        &self,
        particles: &[[f64; 3]],
        masses: &[f64],
        grad_mass: &[f64],
    ) -> f64 {
        let Some(g) = &self.density else {
            return 0.0;
        };
        let factors: Vec<(f64, f64)> = Self::density_coordinates(g, particles)
            .into_iter()
            .map(|s| Self::density_factor(g.excess, s))
            .collect();
        let count = factors.len().max(1) as f64;
        let mean = factors.iter().map(|f| f.0).sum::<f64>() / count;
        let mean_slope = factors.iter().map(|f| f.1).sum::<f64>() / count;
        factors
            .iter()
            .zip(masses.iter().zip(grad_mass))
            .map(|((f, slope), (m, gm))| gm * m * (slope / f - mean_slope / mean))
            .sum()
    }

    /// ∂L/∂axis of the density gradient with the total mass kept, given
    /// each particle's mass and its adjoint. The coordinates s_p =
    /// (p·n − p_lo·n) / (p_hi·n − p_lo·n) do not change with |n|, so the
    /// gradient is perpendicular to the axis: it turns it. With ∂f/∂s = a
    /// on both branches, ∂s_p/∂n = ((p − p_lo) − s_p (p_hi − p_lo)) / span
    /// (the end particles held: a kink where another particle becomes
    /// the end) and ∂L/∂n = Σ_p m̄_p m_p (∂f_p/∂n / f_p − mean ∂f/∂n / F).
    /// Zero without a gradient.
    pub fn density_axis_gradient(
        &self,
        particles: &[[f64; 3]],
        masses: &[f64],
        grad_mass: &[f64],
    ) -> [f64; 3] {
        let Some(g) = &self.density else {
            return [0.0; 3];
        };
        let coords: Vec<f64> = particles
            .iter()
            .map(|p| (0..3).map(|a| p[a] * g.axis[a]).sum())
            .collect();
        let end = |better: fn(f64, f64) -> bool| {
            (0..coords.len()).fold(0, |best, i| {
                if better(coords[i], coords[best]) {
                    i
                } else {
                    best
                }
            })
        };
        let (lo, hi) = (end(|a, b| a < b), end(|a, b| a > b));
        let span = (coords[hi] - coords[lo]).max(1e-9);
        let s = Self::density_coordinates(g, particles);
        let factor_slopes: Vec<[f64; 3]> = particles
            .iter()
            .zip(&s)
            .map(|(p, s)| {
                std::array::from_fn(|a| {
                    g.excess
                        * ((p[a] - particles[lo][a]) - s * (particles[hi][a] - particles[lo][a]))
                        / span
                })
            })
            .collect();
        let count = particles.len().max(1) as f64;
        let mean = s
            .iter()
            .map(|s| Self::density_factor(g.excess, *s).0)
            .sum::<f64>()
            / count;
        let mean_slope: [f64; 3] =
            std::array::from_fn(|a| factor_slopes.iter().map(|d| d[a]).sum::<f64>() / count);
        let mut grad = [0.0; 3];
        for ((s, slope), (m, gm)) in s
            .iter()
            .zip(&factor_slopes)
            .zip(masses.iter().zip(grad_mass))
        {
            let f = Self::density_factor(g.excess, *s).0;
            for a in 0..3 {
                grad[a] += gm * m * (slope[a] / f - mean_slope[a] / mean);
            }
        }
        grad
    }

    /// Turns the density gradient's axis to `axis` (normalised), rescaling
    /// the base `density` so the total mass stays as it was. No-op without
    /// a gradient or for a zero axis.
    pub fn set_density_axis(&mut self, particles: &[[f64; 3]], axis: [f64; 3], density: &mut f64) {
        let length = axis.iter().map(|c| c * c).sum::<f64>().sqrt();
        if !(length > 0.0 && length.is_finite()) {
            return;
        }
        let before = self.mean_density_factor(particles);
        let Some(g) = self.density.as_mut() else {
            return;
        };
        g.axis = axis.map(|c| c / length);
        *density *= before / self.mean_density_factor(particles);
    }

    /// Sets the density gradient's excess, rescaling the base `density` so
    /// the total mass stays as it was. No-op without a gradient.
    pub fn set_density_excess(&mut self, particles: &[[f64; 3]], excess: f64, density: &mut f64) {
        let before = self.mean_density_factor(particles);
        let Some(g) = self.density.as_mut() else {
            return;
        };
        g.excess = excess;
        *density *= before / self.mean_density_factor(particles);
    }

    /// Hand anchors driving the model at (possibly fractional) frame
    /// `t + hand_lag_frames`, the track smoothed with σ `smoothing_frames`.
    pub fn hand_anchors(&self, bundle: &Bundle, t: usize, smoothing_frames: f64) -> Vec<[f64; 3]> {
        hand_anchors_at(bundle, t as f64 + self.hand_lag_frames, smoothing_frames)
    }
}

/// The recorded hand anchors at fractional frame `time` (linear
/// interpolation, held at the first and last frame), smoothed with σ
/// `smoothing_frames` (`crate::hand_filter`; 0 reads the raw track).
pub fn hand_anchors_at(bundle: &Bundle, time: f64, smoothing_frames: f64) -> Vec<[f64; 3]> {
    let last = bundle.frame_count().saturating_sub(1);
    let time = time.clamp(0.0, last as f64);
    let t0 = (time.floor() as usize).min(last);
    let t1 = (t0 + 1).min(last);
    let w = time - t0 as f64;
    let tracks = &bundle.tracks;
    let frame = |t| {
        crate::hand_filter::smoothed_frame(
            &tracks.hand_points,
            &tracks.hand_visibility,
            t,
            smoothing_frames,
        )
    };
    let (a, b) = (frame(t0), frame(t1));
    a.iter()
        .zip(&b)
        .map(|(p, q)| [0, 1, 2].map(|k| p[k] + w * (q[k] - p[k])))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bent line of particles: coordinates along any axis are uneven.
    fn particles() -> Vec<[f64; 3]> {
        (0..40)
            .map(|i| {
                let t = f64::from(i) / 39.0;
                [0.3 * t, 0.05 * (7.0 * t).sin(), 0.02 * t * t]
            })
            .collect()
    }

    /// A fixed pseudo-random weight per particle (the loss's direction).
    fn weight(i: usize, salt: f64) -> f64 {
        ((i as f64 + 1.0) * 12.9898 + salt).sin() * 43.7585 % 1.0
    }

    /// FD step and tolerance of these chain-rule checks: the maps are
    /// smooth closed forms in f64, so a 1e-6 central difference leaves
    /// truncation (O(h²)) and round-off (≈ 1e-10 / 1e-6) near 1e-9.
    const FD_STEP: f64 = 1e-6;
    const FD_RTOL: f64 = 1e-7;

    fn assert_close(name: &str, analytic: f64, numeric: f64) {
        let rel = (analytic - numeric).abs() / numeric.abs().max(1e-12);
        assert!(
            rel < FD_RTOL,
            "{name}: {analytic:e} vs {numeric:e} ({rel:.1e})"
        );
    }

    /// Masses of a model with `excess`, its base density kept as the
    /// diagnosis writes it (total mass of the start model kept).
    fn masses(extension: &ModelExtension, particles: &[[f64; 3]], excess: f64) -> Vec<f64> {
        let mut e = extension.clone();
        let mut density = 800.0;
        e.set_density_excess(particles, excess, &mut density);
        e.density_factors(particles)
            .expect("gradient")
            .iter()
            .map(|f| 1e-6 * density * f)
            .collect()
    }

    #[test]
    fn density_excess_gradient_matches_finite_differences_on_both_branches() {
        let particles = particles();
        let grad_mass: Vec<f64> = (0..particles.len()).map(|i| weight(i, 0.0)).collect();
        // Both signs, and just beside 0 where the branches meet.
        for excess in [2.5, -1.7, 1e-3, -1e-3] {
            let extension = ModelExtension {
                density: Some(DensityGradient {
                    axis: [0.8, 0.6, 0.0],
                    excess,
                }),
                ..ModelExtension::default()
            };
            let m = masses(&extension, &particles, excess);
            let analytic = extension.density_excess_gradient(&particles, &m, &grad_mass);
            let loss = |a: f64| -> f64 {
                masses(&extension, &particles, a)
                    .iter()
                    .zip(&grad_mass)
                    .map(|(m, g)| m * g)
                    .sum()
            };
            let numeric = (loss(excess + FD_STEP) - loss(excess - FD_STEP)) / (2.0 * FD_STEP);
            assert_close(&format!("excess {excess}"), analytic, numeric);
            let total: f64 = m.iter().sum();
            let start: f64 = masses(&extension, &particles, excess + 0.5).iter().sum();
            assert!((total - start).abs() < 1e-12 * total, "total mass kept");
        }
    }

    #[test]
    fn density_axis_gradient_matches_finite_differences_and_turns_the_axis() {
        let particles = particles();
        let grad_mass: Vec<f64> = (0..particles.len()).map(|i| weight(i, 5.0)).collect();
        let axis = [0.8, 0.6, 0.0];
        for excess in [2.5, -1.7] {
            let extension = ModelExtension {
                density: Some(DensityGradient { axis, excess }),
                ..ModelExtension::default()
            };
            let loss = |n: [f64; 3]| -> f64 {
                let mut e = extension.clone();
                let mut density = 800.0;
                e.set_density_axis(&particles, n, &mut density);
                e.density_factors(&particles)
                    .expect("gradient")
                    .iter()
                    .zip(&grad_mass)
                    .map(|(f, g)| 1e-6 * density * f * g)
                    .sum()
            };
            let mut density = 800.0;
            let mut e = extension.clone();
            e.set_density_axis(&particles, axis, &mut density);
            let masses: Vec<f64> = e
                .density_factors(&particles)
                .expect("gradient")
                .iter()
                .map(|f| 1e-6 * density * f)
                .collect();
            let analytic = extension.density_axis_gradient(&particles, &masses, &grad_mass);
            let along: f64 = (0..3).map(|a| analytic[a] * axis[a]).sum();
            assert!(along.abs() < 1e-12, "turns only: {along:e}");
            // Probe in-plane and out of plane; the end particles stay the
            // ends over the step.
            for direction in [[-0.6, 0.8, 0.0], [0.0, 0.0, 1.0]] {
                let shifted =
                    |h: f64| -> [f64; 3] { std::array::from_fn(|a| axis[a] + h * direction[a]) };
                let numeric = (loss(shifted(FD_STEP)) - loss(shifted(-FD_STEP))) / (2.0 * FD_STEP);
                let value: f64 = (0..3).map(|a| analytic[a] * direction[a]).sum();
                assert_close(
                    &format!("axis along {direction:?}, excess {excess}"),
                    value,
                    numeric,
                );
            }
        }
    }

    #[test]
    fn stiff_ball_gradients_match_finite_differences() {
        let particles = particles();
        let n = particles.len();
        let youngs: Vec<f64> = (0..n).map(|i| 1e4 * (1.0 + weight(i, 3.0).abs())).collect();
        let base =
            ParticleMaterial::<f32>::from_fields(&youngs, &vec![0.3; n], &vec![[1.0, 0.0, 0.0]; n]);
        let ball = |factor: f64| ModelExtension {
            stiff_ball: Some(StiffBall {
                centre: particles[12],
                radius: 0.08,
                factor,
            }),
            ..ModelExtension::default()
        };
        let (gmu, glambda): (Vec<f32>, Vec<f32>) = (0..n)
            .map(|i| (weight(i, 1.0) as f32, weight(i, 2.0) as f32))
            .unzip();
        // L = Σ ḡμ μ + ḡλ λ over the scaled material, in f64.
        let loss = |extension: &ModelExtension, base: &ParticleMaterial<f32>| -> f64 {
            let mut scaled = base.clone();
            extension.apply_to_material(&particles, &mut scaled);
            (0..n)
                .map(|i| {
                    f64::from(gmu[i]) * f64::from(scaled.mu[i])
                        + f64::from(glambda[i]) * f64::from(scaled.lambda[i])
                })
                .sum()
        };
        let factor = 6.0f64;
        let extension = ball(factor);
        let analytic = extension.stiffness_log_factor_gradient(&particles, &base, &gmu, &glambda);
        // In ln(factor); the material is f32, so a relative step of 1e-3
        // keeps f32 rounding of μ (1e-7 relative) far below the difference,
        // and the central difference of e^{±step} leaves step²/6 ≈ 2e-7.
        const STIFF_FD_RTOL: f64 = 1e-4;
        let step = 1e-3;
        let numeric = (loss(&ball(factor * f64::exp(step)), &base)
            - loss(&ball(factor * f64::exp(-step)), &base))
            / (2.0 * step);
        let rel = (analytic - numeric).abs() / numeric.abs();
        assert!(
            rel < STIFF_FD_RTOL,
            "ln factor: {analytic:e} vs {numeric:e}"
        );
        assert!(analytic != 0.0, "the ball must hold particles");

        // Base-material adjoint: a particle inside the ball carries × factor.
        let (mut bmu, mut blambda) = (gmu.clone(), glambda.clone());
        extension.base_material_grads(&particles, &mut bmu, &mut blambda);
        let inside: Vec<bool> = extension.inside_ball(&particles).expect("ball").collect();
        for i in 0..n {
            let expected = if inside[i] { factor as f32 } else { 1.0 };
            assert_eq!(bmu[i], gmu[i] * expected);
            assert_eq!(blambda[i], glambda[i] * expected);
        }
        assert!(inside.iter().any(|b| *b) && !inside.iter().all(|b| *b));
    }
}
