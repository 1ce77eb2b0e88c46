//! Gradient clipping (method.md §2: "gradient clips: 1.0 per physics
//! parameter, 10.0 global").
//!
//! # Semantics
//!
//! A *physics parameter* is one named group of a [`ParamSet`] — e.g.
//! `youngs_raw` holding the raw Young's modulus of every material patch — not
//! a single scalar. Clipping is norm clipping (direction preserving), done in
//! two passes by [`clip_physics_gradients`]:
//!
//! 1. **Per parameter group:** each group's gradient vector g_k is rescaled
//!    to `g_k * min(1, c_group / ||g_k||_2)` with c_group = 1.0, so no single
//!    physical quantity can dominate an update however many patches it has.
//! 2. **Global:** the concatenation of all (already group-clipped) groups
//!    g = [g_1, …, g_K] is rescaled to `g * min(1, c_global / ||g||_2)` with
//!    c_global = 10.0.
//!
//! We read "per parameter" as per group rather than per scalar because
//! per-scalar value clipping would change the gradient direction and make the
//! result depend on how finely a field is discretised into patches.
//!
//! [`clip_global_norm`] is the plain global-norm clip alone (the residual
//! network uses it with 5.0).
//!
//! Non-finite gradients are an error naming the group; the gradients are then
//! left untouched (checked before any rescaling), never partly scaled with NaN.

use serde::{Deserialize, Serialize};

use super::{OptimError, ParamSet};

/// Norm limits of [`clip_physics_gradients`]. `f64::INFINITY` disables a pass.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClipConfig {
    /// Maximum L2 norm of each group's gradient (method: 1.0).
    pub per_group_max_norm: f64,
    /// Maximum L2 norm of all groups' gradients together (method: 10.0).
    pub global_max_norm: f64,
}

impl Default for ClipConfig {
    fn default() -> Self {
        Self {
            per_group_max_norm: 1.0,
            global_max_norm: 10.0,
        }
    }
}

/// What the clipping saw and did (for training logs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClipReport {
    /// L2 norm of each group's gradient before any clipping, in group order.
    pub group_norms: Vec<f64>,
    /// L2 norm of the concatenated gradient entering the global pass (after
    /// the per-group pass, if any).
    pub global_norm: f64,
    /// Factor the global pass multiplied every gradient by (1.0 = unclipped).
    pub global_scale: f64,
}

/// L2 norm computed with a max-abs prescale so that large finite gradients
/// (|g| ~ 1e200) do not overflow to infinity and get clipped to zero.
pub fn l2_norm(values: &[f64]) -> f64 {
    scaled_norm(values.iter().copied())
}

fn scaled_norm(values: impl Iterator<Item = f64> + Clone) -> f64 {
    let max_abs = values.clone().fold(0.0_f64, |acc, v| acc.max(v.abs()));
    if max_abs == 0.0 || !max_abs.is_finite() {
        return max_abs;
    }
    let sum_sq: f64 = values.map(|v| (v / max_abs) * (v / max_abs)).sum();
    max_abs * sum_sq.sqrt()
}

/// Scale factor that brings `norm` down to `max_norm` (1.0 if already within).
fn clip_scale(norm: f64, max_norm: f64) -> f64 {
    if norm > max_norm {
        max_norm / norm
    } else {
        1.0
    }
}

fn check_max_norm(option: &'static str, max_norm: f64) -> Result<(), OptimError> {
    // NaN fails `> 0.0`, so it is refused too.
    if max_norm > 0.0 {
        Ok(())
    } else {
        Err(OptimError::InvalidOption {
            option,
            problem: format!("must be positive (infinity disables), got {max_norm}"),
        })
    }
}

/// Per-group clip then global clip, as described in the module docs.
pub fn clip_physics_gradients(
    grads: &mut ParamSet,
    config: &ClipConfig,
) -> Result<ClipReport, OptimError> {
    check_max_norm("per_group_max_norm", config.per_group_max_norm)?;
    check_max_norm("global_max_norm", config.global_max_norm)?;
    grads.check_finite_gradients()?;
    let group_norms = clip_group_norms_unchecked(grads, config.per_group_max_norm);
    let (global_norm, global_scale) = clip_global_unchecked(grads, config.global_max_norm);
    Ok(ClipReport {
        group_norms,
        global_norm,
        global_scale,
    })
}

/// Rescales each group's gradient to L2 norm ≤ `max_norm`; returns each
/// group's norm before clipping.
pub fn clip_group_norms(grads: &mut ParamSet, max_norm: f64) -> Result<Vec<f64>, OptimError> {
    check_max_norm("per_group_max_norm", max_norm)?;
    grads.check_finite_gradients()?;
    Ok(clip_group_norms_unchecked(grads, max_norm))
}

/// Rescales the concatenation of all groups to L2 norm ≤ `max_norm`; returns
/// the norm before clipping.
pub fn clip_global_norm(grads: &mut ParamSet, max_norm: f64) -> Result<f64, OptimError> {
    check_max_norm("global_max_norm", max_norm)?;
    grads.check_finite_gradients()?;
    Ok(clip_global_unchecked(grads, max_norm).0)
}

fn clip_group_norms_unchecked(grads: &mut ParamSet, max_norm: f64) -> Vec<f64> {
    grads
        .groups_mut()
        .map(|(_, values)| {
            let norm = l2_norm(values);
            let scale = clip_scale(norm, max_norm);
            if scale < 1.0 {
                values.iter_mut().for_each(|v| *v *= scale);
            }
            norm
        })
        .collect()
}

fn clip_global_unchecked(grads: &mut ParamSet, max_norm: f64) -> (f64, f64) {
    let norm = scaled_norm(
        grads
            .groups()
            .iter()
            .flat_map(|group| group.values.iter().copied()),
    );
    let scale = clip_scale(norm, max_norm);
    if scale < 1.0 {
        for (_, values) in grads.groups_mut() {
            values.iter_mut().for_each(|v| *v *= scale);
        }
    }
    (norm, scale)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grads(groups: &[(&str, Vec<f64>)]) -> ParamSet {
        let mut set = ParamSet::new();
        for (name, values) in groups {
            set.push(*name, values.clone()).expect("unique names");
        }
        set
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-12 * b.abs().max(1.0)
    }

    #[test]
    fn group_clip_preserves_direction_and_small_groups() {
        let mut g = grads(&[
            ("youngs_raw", vec![3.0, 4.0]),
            ("poisson_raw", vec![0.1, -0.2]),
        ]);
        let report = clip_physics_gradients(&mut g, &ClipConfig::default()).expect("finite");
        assert_eq!(report.group_norms, vec![5.0, l2_norm(&[0.1, -0.2])]);
        let youngs = g.get("youngs_raw").expect("group");
        assert!(close(youngs[0], 0.6) && close(youngs[1], 0.8));
        assert_eq!(g.get("poisson_raw").expect("group"), &[0.1, -0.2]);
        assert_eq!(report.global_scale, 1.0);
    }

    #[test]
    fn global_clip_applies_after_group_clip() {
        // 400 groups of norm 1 after group clipping → global norm 20 → scale 0.5.
        let groups: Vec<(String, Vec<f64>)> = (0..400)
            .map(|i| (format!("g{i}"), vec![0.0, 7.0]))
            .collect();
        let mut g = ParamSet::new();
        for (name, values) in groups {
            g.push(name, values).expect("unique");
        }
        let report = clip_physics_gradients(&mut g, &ClipConfig::default()).expect("finite");
        assert!(close(report.global_norm, 20.0));
        assert!(close(report.global_scale, 0.5));
        assert!(close(l2_norm(&g.flatten()), 10.0));
        assert!(g.groups().iter().all(|group| close(group.values[1], 0.5)));
    }

    #[test]
    fn plain_global_clip() {
        let mut g = grads(&[("w1", vec![30.0]), ("w2", vec![40.0])]);
        let before = clip_global_norm(&mut g, 5.0).expect("finite");
        assert_eq!(before, 50.0);
        assert!(close(g.get("w1").expect("w1")[0], 3.0));
        assert!(close(g.get("w2").expect("w2")[0], 4.0));
    }

    #[test]
    fn huge_finite_gradients_do_not_overflow_to_zero() {
        let mut g = grads(&[("a", vec![1e200, 1e200])]);
        clip_global_norm(&mut g, 1.0).expect("finite");
        let values = g.get("a").expect("a");
        assert!(
            close(values[0], std::f64::consts::FRAC_1_SQRT_2),
            "{values:?}"
        );
    }

    #[test]
    fn non_finite_gradient_is_an_error_naming_the_group_and_leaves_grads() {
        let mut g = grads(&[
            ("youngs_raw", vec![1e3]),
            ("poisson_raw", vec![0.0, f64::NAN]),
        ]);
        let before = g.clone();
        let err = clip_physics_gradients(&mut g, &ClipConfig::default()).expect_err("NaN");
        match err {
            OptimError::NonFiniteGradient { group, index, .. } => {
                assert_eq!((group.as_str(), index), ("poisson_raw", 1));
            }
            other => panic!("unexpected error {other}"),
        }
        assert_eq!(g.get("youngs_raw"), before.get("youngs_raw"));
        let mut inf = grads(&[("w", vec![f64::INFINITY])]);
        assert!(clip_global_norm(&mut inf, 5.0).is_err());
    }

    #[test]
    fn invalid_limits_are_refused() {
        let mut g = grads(&[("a", vec![1.0])]);
        assert!(clip_global_norm(&mut g, 0.0).is_err());
        assert!(clip_global_norm(&mut g, f64::NAN).is_err());
        assert!(clip_global_norm(&mut g, f64::INFINITY).is_ok());
    }
}
