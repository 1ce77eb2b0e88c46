//! Whether the diagnosis's detection limits mean something: for an
//! evaluation draw, the null twin (the draw's preset, seed and action
//! without its effect) is synthesised, fitted and diagnosed, and the
//! draw's effect is then hidden at multiples of the limit the diagnosis
//! reported there, each scene fitted and diagnosed in turn. At half the
//! limit the effect should rarely be named, at twice it nearly always
//! (`examples/detection_limits_eval.rs`, docs/diagnose.md).

use crate::diagnosis_evaluation::{prepare_scene, scene_config};
use dm_diagnose::detectability::Stronger;
use dm_diagnose::{DiagnoseError, DiagnoseOptions, diagnose};
use dm_fit::run::FitOptions;
use dm_synth::{EffectName, EffectSpec, Engine};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// One hidden scene of the check (`results.jsonl`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LimitCheck {
    pub seed: u64,
    pub preset: String,
    /// The library effect hidden (dm-synth's name; quadratic drag draws are
    /// hidden as linear drag, the unit of the drag limit).
    pub effect: String,
    /// The limit the diagnosis reported on the null twin (`null`: not
    /// revealed at any magnitude searched, and nothing hidden).
    pub limit: Option<f64>,
    pub unit: String,
    /// The hidden effect's strength as a multiple of the limit.
    pub factor: f64,
    /// The magnitude hidden (`factor × limit`; `limit / factor` for
    /// plasticity, whose smaller yield stretch is the stronger effect).
    pub magnitude: Option<f64>,
    pub cause: String,
    pub named: bool,
    pub best_score: f64,
}

/// The library effect of draw `seed` as dm-synth hides it with a
/// magnitude in the limit's units.
fn library_effect(name: EffectName) -> EffectName {
    match name {
        EffectName::AirDragQuadratic => EffectName::AirDrag,
        other => other,
    }
}

/// The check of draw `seed` under `out/limits{seed}/`: the null twin and
/// the effect hidden at each of `factors` times its limit. Scenes and fits
/// already there are reused.
pub fn check_limits(
    seed: u64,
    out: &Path,
    fit: &FitOptions,
    options: &DiagnoseOptions,
    factors: &[f64],
) -> Result<Vec<LimitCheck>, DiagnoseError> {
    let (config, drawn) = scene_config(seed, false, Engine::Mpm);
    let Some(drawn) = drawn else {
        return Ok(Vec::new());
    };
    let effect = library_effect(drawn.name);
    let dir = out.join(format!("limits{seed}"));
    let diagnosed = |name: &str, config: &dm_synth::SynthConfig, options: &DiagnoseOptions| {
        let scene_dir = dir.join(name);
        prepare_scene(config, &scene_dir, fit)?;
        diagnose(
            &scene_dir.join("model"),
            &scene_dir.join("scene"),
            &scene_dir.join("diagnosis"),
            None,
            options,
            &mut |_, _, _| {},
        )
    };
    let null_config = dm_synth::SynthConfig {
        effect: None,
        ..config.clone()
    };
    let null = diagnosed("null", &null_config, options)?;
    let limit = null.detectability.get(effect.library_name());
    let unit = limit.map_or(String::new(), |l| l.unit.clone());
    let stronger = limit.map_or(Stronger::Above, |l| l.stronger);
    let limit = limit.and_then(|l| l.min_magnitude);
    let hidden_options = DiagnoseOptions {
        detect_steps: 0,
        ..options.clone()
    };
    let mut checks = Vec::new();
    for &factor in factors {
        let magnitude = limit.map(|l| match stronger {
            Stronger::Above => l * factor,
            Stronger::Below => l / factor,
        });
        let d = match magnitude {
            Some(magnitude) => {
                let config = dm_synth::SynthConfig {
                    effect: Some(EffectSpec {
                        name: effect,
                        magnitude,
                    }),
                    ..config.clone()
                };
                Some(diagnosed(&format!("x{factor}"), &config, &hidden_options)?)
            }
            None => None,
        };
        checks.push(LimitCheck {
            seed,
            preset: config.preset.name().into(),
            effect: effect.name().into(),
            limit,
            unit: unit.clone(),
            factor,
            magnitude,
            cause: d.as_ref().map_or("-".into(), |d| d.cause.clone()),
            named: d.as_ref().is_some_and(|d| d.cause == effect.library_name()),
            best_score: d
                .as_ref()
                .and_then(|d| d.candidates.first())
                .map_or(0.0, |c| c.score),
        });
    }
    Ok(checks)
}
