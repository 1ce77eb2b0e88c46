//! Reverse mode of the LBS bridge's means (the twin of [`crate::lbs`]), for
//! the RGB-guided refinement (method.md §6, stage 3): the photometric
//! gradient on the Gaussian means goes back to the particle positions.
//!
//! Differentiated function: [`skin_means`](crate::lbs::skin_means) with
//! respect to the current particle positions x', with the bones, weights,
//! per-particle rotations, previous positions and previous means held
//! fixed: ∂μ_g/∂x'_b = w_gb I. The Procrustes rotations' own dependence on
//! x' and the chain through earlier frames are not differentiated (stop
//! gradient): a frame's photometric error then moves the particles that
//! carry the misplaced Gaussians, in proportion to their skinning weights,
//! which is the signal the refinement needs; the rotation terms scale with
//! the Gaussian-to-bone offsets (a few millimetres) and would cost a
//! Kabsch-SVD adjoint per particle and frame.

use nalgebra::Vector3;

use crate::lbs::SkinBinding;

/// `∂L/∂x'` for the particles, given `∂L/∂μ` for the Gaussians of one
/// frame's skinning. Summed in Gaussian order, so the result does not
/// depend on the thread count.
pub fn skin_means_vjp(
    binding: &SkinBinding,
    grad_means: &[Vector3<f64>],
    particle_count: usize,
) -> Vec<[f64; 3]> {
    let mut grad = vec![[0.0; 3]; particle_count];
    for (bones, g) in binding.bones.iter().zip(grad_means) {
        for &(b, w) in bones {
            for c in 0..3 {
                grad[b as usize][c] += w * g[c];
            }
        }
    }
    grad
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lbs::{LbsBridge, skin_means};
    use nalgebra::{Matrix3, Rotation3};

    /// skin_means is linear in x' for fixed rotations, so central
    /// differences are exact up to round-off: step 1e-6 m on coordinates
    /// of ~0.1 m leaves ~1e-10 relative error in f64.
    const FD_STEP: f64 = 1e-6;
    const FD_REL_TOL: f64 = 1e-8;

    fn pseudo(seed: &mut u64) -> f64 {
        *seed ^= *seed << 13;
        *seed ^= *seed >> 7;
        *seed ^= *seed << 17;
        (*seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    }

    #[test]
    fn skin_means_vjp_matches_central_differences() {
        let mut seed = 0x5eed_u64;
        let previous: Vec<[f64; 3]> = (0..40)
            .map(|_| {
                [
                    0.1 * pseudo(&mut seed),
                    0.1 * pseudo(&mut seed),
                    0.1 * pseudo(&mut seed),
                ]
            })
            .collect();
        let current: Vec<[f64; 3]> = previous
            .iter()
            .map(|p| {
                [
                    p[0] + 0.01 * pseudo(&mut seed),
                    p[1] + 0.02,
                    p[2] - 0.005 * pseudo(&mut seed),
                ]
            })
            .collect();
        let means: Vec<Vector3<f64>> = (0..25)
            .map(|_| {
                Vector3::new(
                    0.1 * pseudo(&mut seed),
                    0.1 * pseudo(&mut seed),
                    0.1 * pseudo(&mut seed),
                )
            })
            .collect();
        let rotations: Vec<Matrix3<f64>> = (0..previous.len())
            .map(|i| *Rotation3::from_euler_angles(0.1 * i as f64, -0.05, 0.02 * i as f64).matrix())
            .collect();
        let bridge = LbsBridge::new(&previous, 6).expect("particles are valid");
        let binding = bridge.bind(&means);
        let cotangent: Vec<Vector3<f64>> = means
            .iter()
            .map(|_| Vector3::new(pseudo(&mut seed), pseudo(&mut seed), pseudo(&mut seed)))
            .collect();
        let objective = |x: &[[f64; 3]]| -> f64 {
            skin_means(&binding, &means, &previous, x, &rotations)
                .iter()
                .zip(&cotangent)
                .map(|(m, c)| m.dot(c))
                .sum()
        };
        let analytic = skin_means_vjp(&binding, &cotangent, previous.len());
        let scale = analytic
            .iter()
            .flatten()
            .map(|g| g.abs())
            .fold(0.0, f64::max);
        assert!(scale > 0.1, "the test must exercise non-zero gradients");
        for p in 0..previous.len() {
            for c in 0..3 {
                let mut plus = current.clone();
                plus[p][c] += FD_STEP;
                let mut minus = current.clone();
                minus[p][c] -= FD_STEP;
                let numeric = (objective(&plus) - objective(&minus)) / (2.0 * FD_STEP);
                let error = (numeric - analytic[p][c]).abs() / scale;
                assert!(
                    error < FD_REL_TOL,
                    "particle {p} axis {c}: fd {numeric} vs {}",
                    analytic[p][c]
                );
            }
        }
    }
}
