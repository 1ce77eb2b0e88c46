//! "Discover": a term outside the library. An open-ended body force on
//! the grid (`dm_mpm::ForceField`: a push a₀ along each world axis, a drag
//! along each, a spring κ towards the first frame's centroid c) is found
//! as SINDy finds a sparse model, by least squares and sequential
//! thresholding, on the simulator's own response:
//!
//! 1. The seven terms are regressed on the first part of the training
//!    frames with the material held: Levenberg–Marquardt steps on the
//!    tracks' residual, its Jacobian by central differences of rollouts
//!    (seven columns; the tracks respond to a small force almost
//!    linearly). Drags and the spring stay non-negative.
//! 2. A term whose effect on the tracks (|θ_j| ‖J_j‖ / √n, metres RMS) is
//!    below [`MIN_TERM_EFFECT_M`] or below [`RELATIVE_TERM_EFFECT`] of the
//!    largest is dropped and the rest regressed again, until the set stops
//!    changing.
//! 3. On the training split's last [`crate::VALIDATION_SHARE`], which no
//!    regression saw, each kept term, weakest first, is dropped if, with
//!    the others regressed again without it, the track error there is at
//!    most [`VALIDATION_MARGIN`] higher.
//!
//! The validated terms are scored as a library candidate is (the smaller
//! of the track error's reductions on the regression's frames and on the
//! validation frames). They are then regressed on the whole training split, learnt
//! through the adjoint with the material (`dm_fit`'s body-force group),
//! reported in closed form with Gauss–Newton standard deviations, and the
//! extended model is measured on the test split, which no choice used.
//! A body force runs on the CPU only, so discovery does not use the GPU.

use crate::analysis::{match_tracks, rollout};
use crate::{DiagnoseError, Progress, Scored, relative_reduction, score_trial, selection_frames};
use dm_bundle::Bundle;
use dm_fit::learnt_effects::{
    FORCE_FIELD_SCALES, ForceFieldTerms, admissible_force_field_value, force_field_values,
    set_force_field_value,
};
use dm_fit::material_fit::{MaterialFitConfig, fit_material};
use dm_model::WorldModel;
use dm_model::device::Device;
use serde::Serialize;

/// A term is dropped when it moves the tracks by less than this (m, RMS
/// over the fitted frames): a third of the trackers' noise.
pub const MIN_TERM_EFFECT_M: f64 = 0.001;
/// … or by less than this share of the largest term's effect.
pub const RELATIVE_TERM_EFFECT: f64 = 0.2;
/// Thresholding rounds at most (each a regression of the remaining terms).
pub const MAX_ROUNDS: usize = 4;
/// Levenberg–Marquardt steps per regression at most.
pub const MAX_LM_STEPS: usize = 4;
/// A term stays only if the validation frames' track error is more than
/// this share higher without it: the simpler force wins near-ties.
pub const VALIDATION_MARGIN: f64 = 0.03;
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
    /// Thresholding rounds (each a regression of the remaining terms).
    pub rounds: usize,
    /// Adam steps learning the kept terms with the material.
    pub adjoint_iterations: usize,
    /// Relative reductions of the track error against the fitted model by
    /// the validated terms regressed on the training frames before the
    /// validation frames: there (fit) and on the validation frames.
    pub fit_reduction: f64,
    pub validation_reduction: f64,
    /// min(fit, validation), as a library candidate is scored.
    pub score: f64,
    /// Relative reductions by the final terms: on the training split (what
    /// they were fitted on) and on the test split (reported, used for no
    /// choice).
    pub train_reduction: f64,
    pub held_out_reduction: f64,
    pub track_test_before: f64,
    pub track_test_after: f64,
    /// Whether the adjoint steps learning the terms with the material were
    /// kept (they are dropped when they raise the training track error).
    pub material_refit_kept: bool,
}

/// Central-difference step of each term, in its own units.
fn jacobian_step(i: usize) -> f64 {
    0.05 * FORCE_FIELD_SCALES[i]
}

/// The tracks' residual (simulated − observed) over frames `[0, frames)`
/// and, per term in `terms`, its column of the Jacobian (one-sided where a
/// drag or the spring sits at 0).
fn residual_and_jacobian(
    model: &WorldModel,
    bundle: &Bundle,
    terms: ForceFieldTerms,
    frames: usize,
) -> Result<(Vec<f64>, Vec<Vec<f64>>), DiagnoseError> {
    let at_model = tracks(model, bundle, frames)?;
    jacobian_at(model, bundle, terms, frames, at_model)
}

/// [`residual_and_jacobian`] given `model`'s own [`tracks`] over the frames.
fn jacobian_at(
    model: &WorldModel,
    bundle: &Bundle,
    terms: ForceFieldTerms,
    frames: usize,
    (at, observed): (Vec<f64>, Vec<f64>),
) -> Result<(Vec<f64>, Vec<Vec<f64>>), DiagnoseError> {
    let residual: Vec<f64> = at.iter().zip(&observed).map(|(s, o)| s - o).collect();
    let values = force_field_values(&model.physics.effects.force_field);
    let mut columns = Vec::new();
    for i in terms.indices() {
        let step = jacobian_step(i);
        let value = values[i];
        let shifted = |v: f64| {
            let mut m = model.clone();
            set_force_field_value(&mut m.physics.effects.force_field, i, v);
            tracks(&m, bundle, frames).map(|t| t.0)
        };
        // One-sided where a bound (a drag or the spring at 0 or at the
        // substep's limit) stops the step.
        let lo = admissible_force_field_value(&model.physics, i, value - step);
        let hi = admissible_force_field_value(&model.physics, i, value + step);
        if hi <= lo {
            columns.push(vec![0.0; at.len()]);
            continue;
        }
        let side = |v: f64| {
            if v == value {
                Ok(at.clone())
            } else {
                shifted(v)
            }
        };
        let (minus, plus) = (side(lo)?, side(hi)?);
        if plus.len() != at.len() || minus.len() != at.len() {
            return Err(DiagnoseError::Input {
                path: bundle.root.clone(),
                problem: "a perturbed rollout matched a different set of tracks".into(),
            });
        }
        columns.push(
            plus.iter()
                .zip(&minus)
                .map(|(p, m)| (p - m) / (hi - lo))
                .collect(),
        );
    }
    Ok((residual, columns))
}

fn squared(values: &[f64]) -> f64 {
    values.iter().map(|v| v * v).sum()
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// JᵀJ of the Jacobian's `columns`.
fn normal_matrix(columns: &[Vec<f64>]) -> nalgebra::DMatrix<f64> {
    let k = columns.len();
    nalgebra::DMatrix::from_fn(k, k, |a, b| dot(&columns[a], &columns[b]))
}

/// Each term's effect on the tracks, |θ_j| ‖J_j‖ / √n (m RMS over the `n`
/// residual components; 0 for terms not in `terms`), `columns` in the
/// order of `terms`.
fn term_effects(
    values: &[f64; 7],
    terms: ForceFieldTerms,
    columns: &[Vec<f64>],
    n: usize,
) -> [f64; 7] {
    let n = n.max(1) as f64;
    let mut effects = [0.0; 7];
    for (i, column) in terms.indices().zip(columns) {
        effects[i] = values[i].abs() * squared(column).sqrt() / n.sqrt();
    }
    effects
}

/// Levenberg–Marquardt on `terms` of `model`'s body force over frames
/// `[0, frames)`; returns each term's effect on the tracks (m RMS,
/// |θ_j| ‖J_j‖ / √n; 0 for terms not in `terms`).
fn regress(
    model: &mut WorldModel,
    bundle: &Bundle,
    terms: ForceFieldTerms,
    frames: usize,
    progress: &mut dyn FnMut(usize),
) -> Result<[f64; 7], DiagnoseError> {
    let kept: Vec<usize> = terms.indices().collect();
    let mut damping = 1e-3;
    let mut effects = [0.0; 7];
    // The model's tracks: rolled out once, then those of each accepted step.
    let mut at_model = tracks(model, bundle, frames)?;
    for step in 0..MAX_LM_STEPS {
        progress(step);
        let (residual, columns) = jacobian_at(model, bundle, terms, frames, at_model.clone())?;
        let values = force_field_values(&model.physics.effects.force_field);
        effects = term_effects(&values, terms, &columns, residual.len());
        let k = kept.len();
        let jtj = normal_matrix(&columns);
        let jtr = nalgebra::DVector::from_fn(k, |a, _| dot(&columns[a], &residual));
        let before = squared(&residual);
        let mut improved = false;
        for _ in 0..4 {
            let mut lhs = jtj.clone();
            for d in 0..k {
                lhs[(d, d)] += damping * jtj[(d, d)].max(1e-12);
            }
            let Some(delta) = lhs.lu().solve(&(-&jtr)) else {
                damping *= 10.0;
                continue;
            };
            let mut trial = model.clone();
            for (j, &i) in kept.iter().enumerate() {
                let v = admissible_force_field_value(&trial.physics, i, values[i] + delta[j]);
                set_force_field_value(&mut trial.physics.effects.force_field, i, v);
            }
            let at_trial = tracks(&trial, bundle, frames)?;
            let after: f64 = at_trial
                .0
                .iter()
                .zip(&at_trial.1)
                .map(|(s, o)| (s - o).powi(2))
                .sum();
            if after < before {
                *model = trial;
                at_model = at_trial;
                damping = (damping / 10.0).max(1e-6);
                improved = (before - after) > 1e-3 * before;
                break;
            }
            damping *= 10.0;
        }
        if !improved {
            break;
        }
    }
    Ok(effects)
}

/// The terms whose effect on the tracks clears both thresholds.
fn kept_terms(effects: &[f64; 7], terms: ForceFieldTerms) -> ForceFieldTerms {
    let largest = terms.indices().map(|i| effects[i]).fold(0.0, f64::max);
    let floor = MIN_TERM_EFFECT_M.max(RELATIVE_TERM_EFFECT * largest);
    ForceFieldTerms(std::array::from_fn(|i| terms.0[i] && effects[i] >= floor))
}

/// The adjoint steps learning `terms` with the material (dm-fit's material
/// rate, the effect rate for the terms, the whole training split).
fn fit_config(iterations: usize, terms: ForceFieldTerms) -> MaterialFitConfig {
    MaterialFitConfig {
        iterations,
        effect_learning_rate: Some(DISCOVERY_LEARNING_RATE),
        force_field_terms: terms,
        ..MaterialFitConfig::default()
    }
}

/// Track positions of `model`'s rollout over frames `[0, frames)`,
/// flattened over the tracks valid at each frame, and the matching
/// observations.
fn tracks(
    model: &WorldModel,
    bundle: &Bundle,
    frames: usize,
) -> Result<(Vec<f64>, Vec<f64>), DiagnoseError> {
    let run = rollout(model, bundle, Device::Cpu)?;
    let matched = match_tracks(bundle, &run.positions);
    let frames = frames.min(matched.observed.len());
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

/// Gauss–Newton covariance of the kept terms at `model`'s values over
/// the training frames: σ² (JᵀJ)⁻¹ with σ² the residual's mean square.
/// `None` where JᵀJ is singular.
fn covariance(
    model: &WorldModel,
    bundle: &Bundle,
    terms: ForceFieldTerms,
) -> Result<Option<nalgebra::DMatrix<f64>>, DiagnoseError> {
    let frames = bundle.meta.split.train[1];
    let (residual, columns) = residual_and_jacobian(model, bundle, terms, frames)?;
    let (n, k) = (residual.len(), columns.len());
    if n <= k {
        return Ok(None);
    }
    let sigma2 = squared(&residual) / (n - k) as f64;
    let jtj = normal_matrix(&columns);
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
    let frames = selection_frames(bundle.meta.split.train);
    let fit_end = frames.fit[1];
    let train_end = frames.validation[1];
    let mut terms = ForceFieldTerms::ALL;
    let mut rounds = 0;
    while rounds < MAX_ROUNDS && terms.any() {
        rounds += 1;
        let round = rounds;
        let effects = regress(&mut current, bundle, terms, fit_end, &mut |step| {
            progress(
                &format!("discovering a body force, round {round}"),
                step,
                MAX_LM_STEPS,
            )
        })?;
        let kept = kept_terms(&effects, terms);
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
    // The model the validation frames judge (the fitted model's own errors
    // until a term is kept).
    let mut selected = base.clone();
    // Validation: weakest first, a term goes if, with the others regressed
    // again without it, the frames no regression saw are predicted within
    // VALIDATION_MARGIN of as well.
    if terms.any() {
        let (residual, columns) = residual_and_jacobian(&current, bundle, terms, fit_end)?;
        let values = force_field_values(&current.physics.effects.force_field);
        let effects = term_effects(&values, terms, &columns, residual.len());
        let mut order: Vec<usize> = terms.indices().collect();
        order.sort_by(|&a, &b| effects[a].total_cmp(&effects[b]));
        selected = score_trial(&current, bundle, Device::Cpu);
        for (k, &i) in order.iter().enumerate() {
            progress("validating the discovered terms", k, order.len());
            let mut without = current.clone();
            set_force_field_value(&mut without.physics.effects.force_field, i, 0.0);
            let mut rest = terms;
            rest.0[i] = false;
            if rest.any() {
                regress(&mut without, bundle, rest, fit_end, &mut |_| {})?;
            }
            let scored = score_trial(&without, bundle, Device::Cpu);
            if scored.track_validation <= selected.track_validation * (1.0 + VALIDATION_MARGIN) {
                current = without;
                selected = scored;
                terms = rest;
            }
        }
    }
    if terms.any() {
        regress(&mut current, bundle, terms, train_end, &mut |step| {
            progress(
                "regressing the kept terms on the training split",
                step,
                MAX_LM_STEPS,
            )
        })?;
    }
    let dropped = |terms: ForceFieldTerms| -> Vec<String> {
        (0..7)
            .filter(|&i| !terms.0[i])
            .map(|i| ForceFieldTerms::NAMES[i].to_string())
            .collect()
    };
    let empty = || Discovered {
        terms: Vec::new(),
        dropped: dropped(ForceFieldTerms::NONE),
        formula: "a = 0".into(),
        force: None,
        spring: None,
        fitted_about_m: about,
        rounds,
        adjoint_iterations: iterations,
        fit_reduction: 0.0,
        validation_reduction: 0.0,
        score: 0.0,
        train_reduction: 0.0,
        held_out_reduction: 0.0,
        track_test_before: base.track_test,
        track_test_after: base.track_test,
        material_refit_kept: false,
    };
    if !terms.any() {
        return Ok(Discovery {
            discovered: empty(),
            model: None,
        });
    }
    let mut scored = score_trial(&current, bundle, Device::Cpu);
    // The material refitted with the terms learnt beside it; kept only if
    // it lowers the training track error.
    let mut material_refit_kept = false;
    if iterations > 0 {
        let mut refitted = current.clone();
        let mut done = 0;
        let config = fit_config(iterations, terms);
        let fitted = fit_material(&mut refitted, bundle, &config, &mut |_| {
            done += 1;
            progress(
                "learning the discovered terms with the material",
                done,
                iterations,
            );
        });
        if fitted.is_ok() {
            let s = score_trial(&refitted, bundle, Device::Cpu);
            if s.track_train < scored.track_train {
                current = refitted;
                scored = s;
                material_refit_kept = true;
            }
        }
    }
    // A term the adjoint steps took to its bound of 0 is dropped too.
    let learnt = force_field_values(&current.physics.effects.force_field);
    terms = ForceFieldTerms(std::array::from_fn(|i| terms.0[i] && learnt[i] != 0.0));
    if !terms.any() {
        return Ok(Discovery {
            discovered: empty(),
            model: None,
        });
    }
    progress("uncertainty of the discovered terms", 0, 1);
    let covariance = covariance(&current, bundle, terms)?;
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
    let fit_reduction = relative_reduction(base.track_fit, selected.track_fit);
    let validation_reduction = relative_reduction(base.track_validation, selected.track_validation);
    Ok(Discovery {
        discovered: Discovered {
            terms: discovered_terms,
            dropped: dropped(terms),
            formula: formula(&field, terms, about),
            force,
            spring,
            fitted_about_m: about,
            rounds,
            adjoint_iterations: iterations,
            fit_reduction,
            validation_reduction,
            score: fit_reduction.min(validation_reduction),
            train_reduction: relative_reduction(base.track_train, scored.track_train),
            held_out_reduction: relative_reduction(base.track_test, scored.track_test),
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
        // Largest 10 mm: the relative floor of 2 mm rules.
        let kept = kept_terms(&[0.010, 0.0015, 0.002, 0.0005, 0.0, 0.0025, 0.001], all);
        assert_eq!(kept.0, [true, false, true, false, false, true, false]);
        // All small: the absolute floor of 1 mm rules.
        let kept = kept_terms(&[0.0012, 0.0009, 0.0, 0.0, 0.0, 0.0, 0.0011], all);
        assert_eq!(kept.0, [true, false, false, false, false, false, true]);
        // A term already dropped stays dropped.
        let some = ForceFieldTerms([false, true, true, false, false, false, false]);
        let kept = kept_terms(&[0.05, 0.01, 0.01, 0.0, 0.0, 0.0, 0.0], some);
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
