//! The evaluation of terms outside the diagnosis library: scenes hiding
//! `wind`, `attractor` or `anisotropic_drag` (dm-synth), fitted and
//! diagnosed as the library evaluation's are, and the discovered body
//! force compared with the truth's: its direction (the push, the pull
//! from the object's centre towards the point, the drag's axis) and its
//! magnitude (m/s², 1/s², 1/s).

use crate::diagnosis_evaluation::prepare_scene;
use dm_diagnose::discover::Discovered;
use dm_diagnose::{DiagnoseError, DiagnoseOptions, diagnose};
use dm_fit::run::FitOptions;
use dm_synth::{EffectName, EffectSpec, SynthConfig, draw_hidden_effect_among};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// One scene's result (a line of `results.jsonl`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct OutsideResult {
    pub seed: u64,
    pub preset: String,
    pub effect: String,
    pub magnitude: f64,
    /// Angle between the discovered and the true direction, degrees
    /// (`None`: the discovered term has no such direction).
    pub direction_error_deg: Option<f64>,
    /// Discovered / true magnitude − 1 (`None`: not comparable).
    pub magnitude_relative_error: Option<f64>,
    pub formula: String,
    pub train_reduction: f64,
    pub held_out_reduction: f64,
    pub track_before: f64,
    pub track_after: f64,
    /// What the library named.
    pub cause: String,
}

/// The scene of `seed` hiding `effect` (preset and magnitude drawn from
/// the seed within the effect's test range), filmed with the seed's action.
pub fn outside_scene(seed: u64, effect: EffectName) -> (SynthConfig, EffectSpec) {
    let (preset, spec) = draw_hidden_effect_among(seed, &[effect]);
    let mut config = SynthConfig::diagnosis(preset, seed);
    config.effect = Some(spec);
    (config, spec)
}

fn unit(v: [f64; 3]) -> Option<[f64; 3]> {
    let n = v.iter().map(|c| c * c).sum::<f64>().sqrt();
    (n > 0.0).then(|| v.map(|c| c / n))
}

fn angle_deg(a: [f64; 3], b: [f64; 3]) -> Option<f64> {
    let (a, b) = (unit(a)?, unit(b)?);
    let cos: f64 = (0..3).map(|i| a[i] * b[i]).sum();
    Some(cos.clamp(-1.0, 1.0).acos().to_degrees())
}

fn param3(params: &serde_json::Value, key: &str) -> Option<[f64; 3]> {
    serde_json::from_value(params.get(key)?.clone()).ok()
}

/// Direction and magnitude errors of `found` against the truth effect
/// `name` with truth-file parameters `params` and the object's centre
/// `centre`.
pub fn compare(
    found: &Discovered,
    name: EffectName,
    magnitude: f64,
    params: &serde_json::Value,
    centre: [f64; 3],
) -> (Option<f64>, Option<f64>) {
    let field_drags: [f64; 3] = std::array::from_fn(|a| {
        found
            .terms
            .iter()
            .find(|t| t.name == ["drag_x", "drag_y", "drag_z"][a])
            .map_or(0.0, |t| t.coefficient)
    });
    match name {
        EffectName::Wind => {
            let Some(force) = &found.force else {
                return (None, None);
            };
            let truth = param3(params, "direction").unwrap_or([0.0; 3]);
            (
                angle_deg(force.direction, truth),
                Some(force.magnitude_m_s2 / magnitude - 1.0),
            )
        }
        EffectName::Attractor => {
            let truth_point = param3(params, "point_m").unwrap_or(centre);
            let truth_pull: [f64; 3] = std::array::from_fn(|a| truth_point[a] - centre[a]);
            match (&found.spring, &found.force) {
                (Some(spring), _) => {
                    let pull = std::array::from_fn(|a| spring.point_m[a] - centre[a]);
                    (
                        angle_deg(pull, truth_pull),
                        Some(spring.stiffness_per_s2 / magnitude - 1.0),
                    )
                }
                (None, Some(force)) => (angle_deg(force.direction, truth_pull), None),
                (None, None) => (None, None),
            }
        }
        EffectName::AnisotropicDrag => {
            let axis = param3(params, "direction").unwrap_or([0.0; 3]);
            let along: f64 = (0..3).map(|a| field_drags[a] * axis[a]).sum();
            (
                angle_deg(field_drags, axis),
                (along > 0.0).then(|| along / magnitude - 1.0),
            )
        }
        _ => (None, None),
    }
}

/// Synthesises, fits and diagnoses the scene of `seed` hiding `effect`
/// under `dir`, and compares the discovered term with the truth.
pub fn run_outside_scene(
    seed: u64,
    effect: EffectName,
    dir: &Path,
    fit: &FitOptions,
    options: &DiagnoseOptions,
) -> Result<OutsideResult, DiagnoseError> {
    let (config, spec) = outside_scene(seed, effect);
    prepare_scene(&config, dir, fit)?;
    let truth_path = dir.join("scene.truth.json");
    let d = diagnose(
        &dir.join("model"),
        &dir.join("scene"),
        &dir.join("diagnosis"),
        Some(&truth_path),
        options,
        &mut |_, _, _| {},
    )?;
    let truth: dm_synth::TruthFile = dm_bundle::read_json(&truth_path)?;
    let params = truth
        .effect
        .as_ref()
        .map(|e| serde_json::to_value(&e.params).unwrap_or_default())
        .unwrap_or_default();
    let (lo, hi) = config.preset.bounds();
    let centre = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]));
    let found = d.discovered.as_ref();
    let (direction_error_deg, magnitude_relative_error) = found
        .map(|f| compare(f, effect, spec.magnitude, &params, centre))
        .unwrap_or((None, None));
    Ok(OutsideResult {
        seed,
        preset: config.preset.name().into(),
        effect: effect.name().into(),
        magnitude: spec.magnitude,
        direction_error_deg,
        magnitude_relative_error,
        formula: found.map_or("—".into(), |f| f.formula.clone()),
        train_reduction: found.map_or(0.0, |f| f.train_reduction),
        held_out_reduction: found.map_or(0.0, |f| f.held_out_reduction),
        track_before: found.map_or(d.gain.track_before, |f| f.track_test_before),
        track_after: found.map_or(d.gain.track_before, |f| f.track_test_after),
        cause: d.cause,
    })
}
