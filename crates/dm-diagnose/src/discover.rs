//! "Discover": a term outside the library. An open-ended body force on
//! the grid (`dm_mpm::ForceField`: a push a₀ along each world axis, a drag
//! along each, a spring κ towards the first frame's centroid c) is fitted
//! through the simulator's adjoint on the first part of the training
//! frames with the material held, and thinned:
//!
//! 1. as SINDy's sequential thresholding thins a regression: a term whose
//!    acceleration over the rollout is below [`MIN_TERM_ACCEL`] or below
//!    [`RELATIVE_TERM_ACCEL`] of the largest term's is dropped and the
//!    others refitted, until the set stops changing;
//! 2. on the training split's last [`VALIDATION_SHARE`], which no fit
//!    saw: each kept term, weakest first, is dropped if the track error
//!    there is no higher without it.
//!
//! The terms kept are refitted on the whole training split, the material
//! refitted with them learnt beside it, the terms reported in closed form
//! with a Gauss–Newton standard deviation (central-difference Jacobians of
//! the training tracks), and the extended model measured on the test
//! split, which no choice used.

use crate::analysis::{match_tracks, rollout};
use crate::{DiagnoseError, Progress, Scored, score_trial};
use dm_bundle::Bundle;
use dm_fit::learnt_effects::{
    FORCE_FIELD_SCALES, ForceFieldTerms, force_field_values, set_force_field_value,
};
use dm_fit::material_fit::{MaterialFitConfig, fit_material};
use dm_model::WorldModel;
use serde::Serialize;

/// A term is dropped when its RMS acceleration over the training rollout
/// is below this (m/s²): over a 1.2 s clip an unopposed 0.1 m/s² moves a
/// free body by 7 cm, a held one by a few millimetres.
pub const MIN_TERM_ACCEL: f64 = 0.1;
/// … or below this share of the largest term's.
pub const RELATIVE_TERM_ACCEL: f64 = 0.25;
/// Thresholding rounds at most (each a fit of the remaining terms).
pub const MAX_ROUNDS: usize = 3;
/// The share of the training frames held out of the thresholding fits to
/// validate each term (at least two frames).
pub const VALIDATION_SHARE: f64 = 0.25;
/// The effect rate of the body force's fits (dm-fit's default effect rate).
const DISCOVERY_LEARNING_RATE: f64 = 0.1;

/// One term kept.
#[derive(Clone, Debug, Serialize)]
pub struct DiscoveredTerm {
    /// `push_x`, `drag_z`, `spring`, … (`ForceFieldTerms::NAMES`).
    pub name: String,
    pub coefficient: f64,
    pub unit: String,
    /// Gauss–Newton standard deviation (`null` where the Jacobian is
    /// singular); tracks are treated as independent, so it is a floor.
    pub std: Option<f64>,
}

/// The push a₀ of the kept terms as a force field.
#[derive(Clone, Debug, Serialize)]
pub struct DiscoveredForce {
    /// World-frame unit direction of a₀.
    pub direction: [f64; 3],
    pub magnitude_m_s2: f64,
    pub magnitude_std_m_s2: Option<f64>,
    /// Angular standard deviation of the direction, degrees.
    pub direction_std_deg: Option<f64>,
}

/// The spring of the kept terms: a = −κ (x − p) with the push folded into
/// its point, p = c + a₀/κ.
#[derive(Clone, Debug, Serialize)]
pub struct DiscoveredSpring {
    pub stiffness_per_s2: f64,
    pub point_m: [f64; 3],
}

/// `discovered` in `diagnosis.json`.
#[derive(Clone, Debug, Serialize)]
pub struct Discovered {
    pub terms: Vec<DiscoveredTerm>,
    /// The terms thresholding dropped.
    pub dropped: Vec<String>,
    /// The kept terms as one acceleration, e.g. `a = (0.41, −1.38, 0.00)
    /// m/s² − 12.3 /s · v_x`.
    pub formula: String,
    pub force: Option<DiscoveredForce>,
    pub spring: Option<DiscoveredSpring>,
    /// The point the spring term was fitted about (the first frame's
    /// particle centroid), metres.
    pub fitted_about_m: [f64; 3],
    pub rounds: usize,
    pub iterations_per_round: usize,
    /// Relative reductions of the track error against the fitted model
    /// (train: what the terms were fitted on; held out: the test split).
    pub train_reduction: f64,
    pub held_out_reduction: f64,
    /// min(train, held-out), as a library candidate is scored.
    pub score: f64,
    pub track_test_before: f64,
    pub track_test_after: f64,
    /// Whether the material refit with the terms in place was kept (it is
    /// dropped when it raises the training track error).
    pub material_refit_kept: bool,
}

/// RMS acceleration of each of the seven terms at `field`'s values over
/// the training frames of `model`'s rollout.
fn term_accelerations(
    model: &WorldModel,
    bundle: &Bundle,
    about: [f64; 3],
) -> Result<[f64; 7], DiagnoseError> {
    let run = rollout(model, bundle)?;
    let frames = bundle.meta.split.train[1].min(run.positions.len());
    let fps = bundle.meta.fps;
    let (mut v2, mut r2, mut count) = ([0.0; 3], 0.0, 0usize);
    for t in 0..frames.saturating_sub(1) {
        for (a, b) in run.positions[t].iter().zip(&run.positions[t + 1]) {
            for c in 0..3 {
                let v = (f64::from(b[c]) - f64::from(a[c])) * fps;
                v2[c] += v * v;
                r2 += (f64::from(a[c]) - about[c]).powi(2);
            }
            count += 1;
        }
    }
    let n = count.max(1) as f64;
    let values = force_field_values(&model.physics.effects.force_field);
    let rms_v = v2.map(|s| (s / n).sqrt());
    let rms_r = (r2 / n).sqrt();
    Ok(std::array::from_fn(|i| match i {
        0..=2 => values[i].abs(),
        3..=5 => values[i].abs() * rms_v[i - 3],
        _ => values[i].abs() * rms_r,
    }))
}

/// The terms whose acceleration clears both thresholds.
fn kept_terms(accelerations: &[f64; 7], terms: ForceFieldTerms) -> ForceFieldTerms {
    let largest = terms
        .indices()
        .map(|i| accelerations[i])
        .fold(0.0, f64::max);
    let floor = MIN_TERM_ACCEL.max(RELATIVE_TERM_ACCEL * largest);
    ForceFieldTerms(std::array::from_fn(|i| {
        terms.0[i] && accelerations[i] >= floor
    }))
}

fn fit_config(
    iterations: usize,
    terms: ForceFieldTerms,
    material_rate: f64,
    frames: Option<usize>,
) -> MaterialFitConfig {
    MaterialFitConfig {
        iterations,
        frames,
        learning_rate: material_rate,
        effect_learning_rate: Some(DISCOVERY_LEARNING_RATE),
        learn_effects: material_rate > 0.0,
        force_field_terms: terms,
        ..MaterialFitConfig::default()
    }
}

/// Training-frame track positions of `model`'s rollout, flattened over the
/// tracks `valid` at each frame, and the matching observations.
fn training_tracks(
    model: &WorldModel,
    bundle: &Bundle,
) -> Result<(Vec<f64>, Vec<f64>), DiagnoseError> {
    let run = rollout(model, bundle)?;
    let matched = match_tracks(bundle, &run.positions);
    let frames = bundle.meta.split.train[1].min(matched.observed.len());
    let (mut simulated, mut observed) = (Vec::new(), Vec::new());
    for t in 0..frames {
        for (o, s) in matched.observed[t].iter().zip(&matched.simulated[t]) {
            if let Some(o) = o {
                simulated.extend_from_slice(s);
                observed.extend_from_slice(o);
            }
        }
    }
    Ok((simulated, observed))
}

/// Gauss–Newton covariance of the kept terms at `model`'s values:
/// σ² (JᵀJ)⁻¹ with J from central differences of the training tracks and
/// σ² the residual's mean square. `None` where JᵀJ is singular.
fn covariance(
    model: &WorldModel,
    bundle: &Bundle,
    terms: ForceFieldTerms,
    progress: Progress<'_>,
) -> Result<Option<nalgebra::DMatrix<f64>>, DiagnoseError> {
    let kept: Vec<usize> = terms.indices().collect();
    let (at, observed) = training_tracks(model, bundle)?;
    let mut columns = Vec::with_capacity(kept.len());
    for (j, &i) in kept.iter().enumerate() {
        progress("uncertainty of the discovered terms", j, kept.len());
        let step = 0.05 * FORCE_FIELD_SCALES[i];
        let value = force_field_values(&model.physics.effects.force_field)[i];
        let shifted = |sign: f64| {
            let mut m = model.clone();
            // Drags and the spring stay non-negative: step one-sided at 0.
            let v = if i >= 3 {
                (value + sign * step).max(0.0)
            } else {
                value + sign * step
            };
            set_force_field_value(&mut m.physics.effects.force_field, i, v);
            Ok::<_, DiagnoseError>((training_tracks(&m, bundle)?.0, v))
        };
        let ((plus, v_plus), (minus, v_minus)) = (shifted(1.0)?, shifted(-1.0)?);
        let width = v_plus - v_minus;
        if plus.len() != at.len() || minus.len() != at.len() || width <= 0.0 {
            return Ok(None);
        }
        columns.push(
            plus.iter()
                .zip(&minus)
                .map(|(p, m)| (p - m) / width)
                .collect::<Vec<f64>>(),
        );
    }
    let (n, k) = (at.len(), kept.len());
    if n <= k {
        return Ok(None);
    }
    let residual2: f64 = at.iter().zip(&observed).map(|(s, o)| (s - o).powi(2)).sum();
    let sigma2 = residual2 / (n - k) as f64;
    let jtj = nalgebra::DMatrix::from_fn(k, k, |a, b| {
        columns[a]
            .iter()
            .zip(&columns[b])
            .map(|(x, y)| x * y)
            .sum::<f64>()
    });
    Ok(jtj.try_inverse().map(|inverse| inverse * sigma2))
}

/// The closed form of the kept terms.
fn formula(field: &dm_mpm::ForceField, terms: ForceFieldTerms, about: [f64; 3]) -> String {
    let mut parts = Vec::new();
    let t = terms.0;
    if t[0] || t[1] || t[2] {
        let u = field.uniform;
        parts.push(format!("({:.3}, {:.3}, {:.3}) m/s²", u[0], u[1], u[2]));
    }
    for (axis, name) in ["x", "y", "z"].iter().enumerate() {
        if t[3 + axis] {
            parts.push(format!("− {:.2} /s · v_{name}", field.axis_drag[axis]));
        }
    }
    if t[6] {
        parts.push(format!(
            "− {:.2} /s² · (x − ({:.3}, {:.3}, {:.3}) m)",
            field.attractor_stiffness, about[0], about[1], about[2]
        ));
    }
    if parts.is_empty() {
        "a = 0".into()
    } else {
        format!("a = {}", parts.join(" ").trim_start_matches("+ "))
    }
}

/// What discovery found: the report and, when a term was kept, the model
/// carrying it.
#[derive(Debug)]
pub(crate) struct Discovery {
    pub discovered: Discovered,
    pub model: Option<WorldModel>,
}

/// Fits, thins and measures the body force on top of `model` (module docs).
pub(crate) fn discover(
    model: &WorldModel,
    bundle: &Bundle,
    base: &Scored,
    iterations: usize,
    refit_iterations: usize,
    progress: Progress<'_>,
) -> Result<Discovery, DiagnoseError> {
    let count = model.particles.len().max(1) as f64;
    let about: [f64; 3] =
        std::array::from_fn(|a| model.particles.iter().map(|p| p[a]).sum::<f64>() / count);
    let mut current = model.clone();
    current.physics.effects.force_field = dm_mpm::ForceField {
        attractor_point: about,
        ..dm_mpm::ForceField::default()
    };
    let train_end = bundle.meta.split.train[1];
    let validation = ((VALIDATION_SHARE * train_end as f64).round() as usize).max(2);
    let fit_end = train_end.saturating_sub(validation).max(2);
    let validation_error = |m: &WorldModel| {
        let s = score_trial(m, bundle);
        let frames = s
            .track_per_frame
            .get(fit_end..train_end)
            .unwrap_or_default();
        if frames.is_empty() {
            f64::INFINITY
        } else {
            frames.iter().sum::<f64>() / frames.len() as f64
        }
    };
    let mut terms = ForceFieldTerms::ALL;
    let mut rounds = 0;
    while rounds < MAX_ROUNDS && terms.any() {
        rounds += 1;
        let mut done = 0;
        let config = fit_config(iterations, terms, 0.0, Some(fit_end));
        fit_material(&mut current, bundle, &config, &mut |_| {
            done += 1;
            progress(
                &format!("discovering a body force, round {rounds}"),
                done,
                iterations,
            );
        })?;
        let accelerations = term_accelerations(&current, bundle, about)?;
        let kept = kept_terms(&accelerations, terms);
        for i in 0..7 {
            if !kept.0[i] {
                set_force_field_value(&mut current.physics.effects.force_field, i, 0.0);
            }
        }
        if kept == terms {
            break;
        }
        terms = kept;
    }
    // Validation: weakest first, a term goes if the frames no fit saw are
    // predicted at least as well without it.
    if terms.any() {
        let accelerations = term_accelerations(&current, bundle, about)?;
        let mut order: Vec<usize> = terms.indices().collect();
        order.sort_by(|&a, &b| accelerations[a].total_cmp(&accelerations[b]));
        let mut with = validation_error(&current);
        for (k, &i) in order.iter().enumerate() {
            progress("validating the discovered terms", k, order.len());
            let mut without = current.clone();
            set_force_field_value(&mut without.physics.effects.force_field, i, 0.0);
            let error = validation_error(&without);
            if error <= with {
                current = without;
                with = error;
                terms.0[i] = false;
            }
        }
    }
    if terms.any() {
        let mut done = 0;
        let config = fit_config(iterations, terms, 0.0, None);
        fit_material(&mut current, bundle, &config, &mut |_| {
            done += 1;
            progress("refitting the discovered terms", done, iterations);
        })?;
    }
    let dropped: Vec<String> = (0..7)
        .filter(|&i| !terms.0[i])
        .map(|i| ForceFieldTerms::NAMES[i].to_string())
        .collect();
    let relative = |before: f64, after: f64| {
        if after.is_finite() && before > 0.0 {
            (before - after) / before
        } else {
            -1.0
        }
    };
    let empty = |dropped: Vec<String>| Discovered {
        terms: Vec::new(),
        dropped,
        formula: "a = 0".into(),
        force: None,
        spring: None,
        fitted_about_m: about,
        rounds,
        iterations_per_round: iterations,
        train_reduction: 0.0,
        held_out_reduction: 0.0,
        score: 0.0,
        track_test_before: base.track_test,
        track_test_after: base.track_test,
        material_refit_kept: false,
    };
    if !terms.any() {
        return Ok(Discovery {
            discovered: empty(dropped),
            model: None,
        });
    }
    let mut scored = score_trial(&current, bundle);
    // The material refitted with the terms learnt beside it; kept only if
    // it lowers the training track error.
    let mut material_refit_kept = false;
    if refit_iterations > 0 {
        let mut refitted = current.clone();
        let mut done = 0;
        let config = fit_config(
            refit_iterations,
            terms,
            MaterialFitConfig::default().learning_rate,
            None,
        );
        let fitted = fit_material(&mut refitted, bundle, &config, &mut |_| {
            done += 1;
            progress(
                "refitting the material with the discovered terms",
                done,
                refit_iterations,
            );
        });
        if fitted.is_ok() {
            let s = score_trial(&refitted, bundle);
            if s.track_train < scored.track_train {
                current = refitted;
                scored = s;
                material_refit_kept = true;
            }
        }
    }
    let covariance = covariance(&current, bundle, terms, progress)?;
    let field = current.physics.effects.force_field;
    let values = force_field_values(&field);
    let kept: Vec<usize> = terms.indices().collect();
    let variance = |i: usize| {
        let j = kept.iter().position(|&k| k == i)?;
        covariance.as_ref().map(|c| c[(j, j)].max(0.0))
    };
    let discovered_terms = kept
        .iter()
        .map(|&i| DiscoveredTerm {
            name: ForceFieldTerms::NAMES[i].into(),
            coefficient: values[i],
            unit: ForceFieldTerms::UNITS[i].into(),
            std: variance(i).map(f64::sqrt),
        })
        .collect();
    let push = field.uniform;
    let magnitude = push.iter().map(|c| c * c).sum::<f64>().sqrt();
    let force = (magnitude > 0.0 && field.attractor_stiffness == 0.0).then(|| {
        let direction = push.map(|c| c / magnitude);
        // Var(|u|) ≈ ĝᵀ Σ ĝ; the direction's angular variance ≈ (tr Σ − ĝᵀ Σ ĝ)/|u|².
        let cov_u = |a: usize, b: usize| {
            let (ja, jb) = (
                kept.iter().position(|&k| k == a),
                kept.iter().position(|&k| k == b),
            );
            match (ja, jb, covariance.as_ref()) {
                (Some(ja), Some(jb), Some(c)) => Some(c[(ja, jb)]),
                (None, _, Some(_)) | (_, None, Some(_)) => Some(0.0),
                _ => None,
            }
        };
        let along = (0..3)
            .flat_map(|a| (0..3).map(move |b| (a, b)))
            .map(|(a, b)| cov_u(a, b).map(|c| direction[a] * c * direction[b]))
            .sum::<Option<f64>>();
        let trace = (0..3).map(|a| cov_u(a, a)).sum::<Option<f64>>();
        DiscoveredForce {
            direction,
            magnitude_m_s2: magnitude,
            magnitude_std_m_s2: along.map(|v| v.max(0.0).sqrt()),
            direction_std_deg: along
                .zip(trace)
                .map(|(along, trace)| ((trace - along).max(0.0).sqrt() / magnitude).to_degrees()),
        }
    });
    let spring = (field.attractor_stiffness > 0.0).then(|| DiscoveredSpring {
        stiffness_per_s2: field.attractor_stiffness,
        point_m: std::array::from_fn(|a| about[a] + push[a] / field.attractor_stiffness),
    });
    let train_reduction = relative(base.track_train, scored.track_train);
    let held_out_reduction = relative(base.track_test, scored.track_test);
    Ok(Discovery {
        discovered: Discovered {
            terms: discovered_terms,
            dropped,
            formula: formula(&field, terms, about),
            force,
            spring,
            fitted_about_m: about,
            rounds,
            iterations_per_round: iterations,
            train_reduction,
            held_out_reduction,
            score: train_reduction.min(held_out_reduction),
            track_test_before: base.track_test,
            track_test_after: scored.track_test,
            material_refit_kept,
        },
        model: Some(current),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thresholding_keeps_terms_above_both_floors() {
        let all = ForceFieldTerms::ALL;
        // Largest 2.0 m/s²: the relative floor 0.5 rules.
        let kept = kept_terms(&[2.0, 0.4, 0.6, 0.05, 0.0, 0.5, 0.2], all);
        assert_eq!(kept.0, [true, false, true, false, false, true, false]);
        // All small: the absolute floor rules.
        let kept = kept_terms(&[0.12, 0.09, 0.0, 0.0, 0.0, 0.0, 0.11], all);
        assert_eq!(kept.0, [true, false, false, false, false, false, true]);
        // A term already dropped stays dropped.
        let some = ForceFieldTerms([false, true, true, false, false, false, false]);
        let kept = kept_terms(&[5.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0], some);
        assert_eq!(kept.0, [false, true, true, false, false, false, false]);
    }

    #[test]
    fn the_formula_names_the_kept_terms_only() {
        let field = dm_mpm::ForceField {
            uniform: [0.5, -1.25, 0.0],
            axis_drag: [0.0, 0.0, 12.0],
            attractor_stiffness: 0.0,
            attractor_point: [0.0; 3],
        };
        let terms = ForceFieldTerms([true, true, false, false, false, true, false]);
        assert_eq!(
            formula(&field, terms, [0.0; 3]),
            "a = (0.500, -1.250, 0.000) m/s² − 12.00 /s · v_z"
        );
        assert_eq!(formula(&field, ForceFieldTerms::NONE, [0.0; 3]), "a = 0");
    }
}
