//! The oracle fit: a scene's base fit repeated with the hidden
//! effect's *true* term in place from the start, scored against the base
//! fit as the diagnosis scores a candidate fitted from the start
//! (`--fit-candidates`). It is what the right candidate shows when its
//! parameter search has found the truth. An effect whose oracle score stays
//! under the naming threshold cannot be named in that scene by this score,
//! however good the search: the fitted material and gains have absorbed it,
//! or it is small beside the model's other error.

use dm_bundle::{Bundle, write_json_atomic};
use dm_diagnose::candidates::{Candidate, apply, with_learnt_parameters};
use dm_diagnose::{DiagnoseError, split_track_error};
use dm_model::WorldModel;
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::Path;

/// `oracle.json`: the base fit against the fit with the true effect.
#[derive(Clone, Debug, Serialize)]
pub struct OracleResult {
    /// The hidden effect as dm-synth names it.
    pub effect: String,
    /// The library candidate carrying it.
    pub candidate: String,
    /// Whether the effect was held at the truth (`true`) or learnt from it
    /// beside the material, as a candidate's fit learns it.
    pub effect_frozen: bool,
    /// The truth in the candidate's terms (the fit starts there).
    pub truth_parameters: BTreeMap<String, f64>,
    /// Where the fit left the terms it learns beside the material.
    pub learnt_parameters: BTreeMap<String, f64>,
    /// Track error of the base fit and of the oracle fit, train and test
    /// split means, metres.
    pub base_track_train: f64,
    pub base_track_test: f64,
    pub oracle_track_train: f64,
    pub oracle_track_test: f64,
    pub train_reduction: f64,
    pub held_out_reduction: f64,
    /// min(fit, validation) reduction: the diagnosis's score
    /// (`dm_diagnose::selection_frames`).
    pub score: f64,
}

/// The hidden effect of a dm-synth truth file (`effect.name`,
/// `effect.params`) as a library candidate with its parameters in the
/// candidate's terms, for a model built like `model` (its floor's up
/// direction orients the tilt) on a clip at `fps`.
pub fn truth_candidate(
    truth: &serde_json::Value,
    model: &WorldModel,
    fps: f64,
    path: &Path,
) -> Result<(Candidate, BTreeMap<String, f64>), DiagnoseError> {
    let problem = |what: String| DiagnoseError::Input {
        path: path.to_path_buf(),
        problem: what,
    };
    let effect = truth
        .get("effect")
        .filter(|e| !e.is_null())
        .ok_or_else(|| problem("`effect`: the scene has no hidden effect".into()))?;
    let name = effect
        .get("name")
        .and_then(|n| n.as_str())
        .ok_or_else(|| problem("`effect.name` is missing".into()))?;
    let params = effect.get("params");
    let number = |key: &str| {
        params
            .and_then(|p| p.get(key))
            .and_then(|v| v.as_f64())
            .ok_or_else(|| problem(format!("`effect.params.{key}` is missing or not a number")))
    };
    let vector = |key: &str| {
        params
            .and_then(|p| p.get(key))
            .and_then(|v| serde_json::from_value::<[f64; 3]>(v.clone()).ok())
            .ok_or_else(|| problem(format!("`effect.params.{key}` is not three numbers")))
    };
    let pairs = |kv: &[(&str, f64)]| -> BTreeMap<String, f64> {
        kv.iter().map(|(k, v)| (k.to_string(), *v)).collect()
    };
    // Effects of one parameter: dm-synth's name, the candidate, the truth's
    // key, the candidate's key, and the factor to the candidate's unit.
    #[rustfmt::skip]
    let single: [(&str, Candidate, &str, &str, f64); 6] = [
        ("air_drag", Candidate::AirDrag, "linear_per_s", "linear_per_s", 1.0),
        ("air_drag_quadratic", Candidate::AirDrag, "quadratic_per_m", "quadratic_per_m", 1.0),
        ("floor_friction", Candidate::FloorFriction, "coefficient", "coefficient", 1.0),
        ("plasticity", Candidate::Plasticity, "yield_stretch", "yield_stretch", 1.0),
        ("viscous_damping", Candidate::ViscousDamping, "viscosity_pa_s", "viscosity_pa_s", 1.0),
        ("actuator_lag", Candidate::ActuatorLag, "lag_s", "lag_frames", fps),
    ];
    if let Some(&(_, candidate, truth_key, key, scale)) = single.iter().find(|s| s.0 == name) {
        return Ok((candidate, pairs(&[(key, number(truth_key)? * scale)])));
    }
    Ok(match name {
        "stiff_inclusion" => {
            let centre = vector("centre_m")?;
            (
                Candidate::StiffInclusion,
                pairs(&[
                    ("centre_x_m", centre[0]),
                    ("centre_y_m", centre[1]),
                    ("centre_z_m", centre[2]),
                    ("radius_m", number("radius_m")?),
                    ("stiffness_factor", number("stiffness_factor")?),
                ]),
            )
        }
        "density_variation" => {
            // dm-synth grades along a coordinate axis, heavy at its maximum or
            // its minimum; the candidate's gradient points to its heavy end.
            let axis = params
                .and_then(|p| p.get("axis"))
                .and_then(|a| a.as_u64())
                .filter(|&a| a < 3)
                .ok_or_else(|| problem("`effect.params.axis` is not 0, 1 or 2".into()))?;
            let heavy_at_max = params
                .and_then(|p| p.get("heavy_at_max"))
                .and_then(|h| h.as_bool())
                .ok_or_else(|| problem("`effect.params.heavy_at_max` is not a boolean".into()))?;
            let sign = if heavy_at_max { 1.0 } else { -1.0 };
            let mut direction = [0.0; 3];
            direction[axis as usize] = sign;
            (
                Candidate::DensityVariation,
                pairs(&[
                    ("axis_x", direction[0]),
                    ("axis_y", direction[1]),
                    ("axis_z", direction[2]),
                    ("heavy_end_excess", number("heavy_end_excess")?),
                ]),
            )
        }
        "ground_tilt" => {
            // The truth's gravity, read back in the candidate's tilt and
            // azimuth about this model's floor.
            let gravity = vector("gravity")?;
            let mut tilted = model.clone();
            tilted.physics.gravity = gravity;
            let keys = pairs(&[("tilt_deg", 0.0), ("azimuth_deg", 0.0)]);
            (
                Candidate::GroundTilt,
                with_learnt_parameters(Candidate::GroundTilt, &keys, &tilted),
            )
        }
        other => return Err(problem(format!("`effect.name`: unknown effect `{other}`"))),
    })
}

/// Fits `bundle_dir`'s scene from the start with the truth's effect in
/// place, with the dm-fit options `model_dir`'s model was fitted with
/// (and the effect held at the truth when `freeze_effect`), writes the fit
/// and `oracle.json` under `out`, and scores it against `model_dir`'s
/// model.
pub fn oracle_fit(
    bundle_dir: &Path,
    truth_path: &Path,
    model_dir: &Path,
    out: &Path,
    freeze_effect: bool,
) -> Result<OracleResult, DiagnoseError> {
    let bundle = Bundle::open(bundle_dir)?;
    let truth: serde_json::Value = dm_bundle::read_json(truth_path)?;
    let base: WorldModel = dm_bundle::read_json(&model_dir.join("model.json"))?;
    let report: dm_fit::run::FitReport = dm_bundle::read_json(&model_dir.join("fit_report.json"))?;
    let options = dm_fit::run::FitOptions {
        freeze_effects: freeze_effect || report.options.freeze_effects,
        ..report.options
    };
    let start = WorldModel::from_bundle(&bundle, &options.model)?;
    let (candidate, truth_parameters) =
        truth_candidate(&truth, &start, bundle.meta.fps, truth_path)?;
    let start = apply(&start, candidate, &truth_parameters);
    dm_fit::run::run_fit_from(&bundle, &options, start, out, &mut |_| {})?;
    let fitted: WorldModel = dm_bundle::read_json(&out.join("model.json"))?;
    let before = split_track_error(&base, &bundle);
    let after = split_track_error(&fitted, &bundle);
    let relative = |b: f64, a: f64| if a.is_finite() { (b - a) / b } else { -1.0 };
    let train_reduction = relative(before.train, after.train);
    let held_out_reduction = relative(before.test, after.test);
    let result = OracleResult {
        effect: truth["effect"]["name"].as_str().unwrap_or_default().into(),
        candidate: candidate.name().into(),
        effect_frozen: options.freeze_effects,
        learnt_parameters: with_learnt_parameters(candidate, &truth_parameters, &fitted),
        truth_parameters,
        base_track_train: before.train,
        base_track_test: before.test,
        oracle_track_train: after.train,
        oracle_track_test: after.test,
        train_reduction,
        held_out_reduction,
        score: after.score_against(&before),
    };
    write_json_atomic(&out.join("oracle.json"), &result)?;
    Ok(result)
}
