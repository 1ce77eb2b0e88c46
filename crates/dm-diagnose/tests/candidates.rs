//! Issue 6: the density candidate redistributes the fitted mass (a uniform
//! fit has already matched the mean stiffness-to-density ratio) and tries
//! two orthogonal axes (a square cloth's first axis is arbitrary).

use dm_diagnose::candidates::{Candidate, apply, trials, with_learnt_parameters};
use dm_diagnose::signatures::Signatures;
use dm_model::{ModelOptions, ResidualKind, WorldModel};
use dm_synth::{Preset, SynthConfig};

/// Relative mismatch allowed between total masses: the factors are summed
/// in f64 over ~800 particles, so only rounding separates them.
const MASS_RTOL: f64 = 1e-9;

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|i| a[i] * b[i]).sum()
}

/// A tiny cloth scene under `dir` (`scene/`, `truth.json`) and the model
/// `--residual none` would start from.
fn tiny_cloth_model(dir: &std::path::Path) -> WorldModel {
    let scene = dir.join("scene");
    let config = SynthConfig::tiny(Preset::Cloth, 7);
    dm_synth::generate(&config, &scene, &dir.join("truth.json"), &mut |_, _, _| {}).expect("scene");
    let bundle = dm_bundle::Bundle::open(&scene).expect("bundle");
    let options = ModelOptions {
        residual: ResidualKind::None,
        ..ModelOptions::default()
    };
    WorldModel::from_bundle(&bundle, &options).expect("model")
}

fn total_mass(model: &WorldModel) -> f64 {
    let factors = model
        .extension
        .density_factors(&model.particles)
        .unwrap_or_else(|| vec![1.0; model.particles.len()]);
    model.physics.density * model.particle_volume * factors.iter().sum::<f64>()
}

#[test]
fn density_candidate_keeps_the_fitted_mass_on_two_axes() {
    let dir = tempfile::tempdir().expect("temp dir");
    let model = tiny_cloth_model(dir.path());
    let quiet = Signatures {
        drag_rate_per_s: 0.0,
        drag_t: 0.0,
        floor_rate_per_s: 0.0,
        floor_t: 0.0,
        horizontal_accel: [0.0; 3],
        horizontal_t: 0.0,
        hand_shift_frames: 0.0,
        sag_slope: 0.0,
        sag_t: 0.0,
    };
    let density = trials(Candidate::DensityVariation, &model, &quiet);
    assert_eq!(density.len(), 4, "two axes, both ends");
    let base_mass = total_mass(&model);
    let mut axes = Vec::new();
    for trial in &density {
        let mass = total_mass(&trial.model);
        assert!(
            ((mass - base_mass) / base_mass).abs() < MASS_RTOL,
            "{:?}: total mass {mass} vs fitted {base_mass}",
            trial.parameters
        );
        let factors = trial
            .model
            .extension
            .density_factors(&trial.model.particles)
            .expect("a gradient");
        let (lo, hi) = factors
            .iter()
            .fold((f64::INFINITY, 0.0_f64), |(l, h), f| (l.min(*f), h.max(*f)));
        assert!((hi / lo - 3.5).abs() < 1e-9, "heavy end 3.5× the light one");
        let p = &trial.parameters;
        axes.push([p["axis_x"], p["axis_y"], p["axis_z"]]);
    }
    for axis in &axes {
        assert!((dot(*axis, *axis) - 1.0).abs() < 1e-6, "unit axis {axis:?}");
    }
    assert!(
        dot(axes[0], axes[2]).abs() < 1e-6,
        "second axis {:?} not orthogonal to the first {:?}",
        axes[2],
        axes[0]
    );
}

/// Issue 6: what a candidate's fit learnt is read back from the fitted
/// model in the trial's own terms (a tilt's angle and azimuth, a drag's
/// coefficient, a stiff ball's factor, a density gradient's excess and
/// axis), so
/// `effect_parameters` reports the learnt values.
#[test]
fn learnt_parameters_read_back_in_the_trials_terms() {
    let dir = tempfile::tempdir().expect("temp dir");
    let model = tiny_cloth_model(dir.path());
    let tried = |pairs: &[(&str, f64)]| -> std::collections::BTreeMap<String, f64> {
        pairs.iter().map(|(k, v)| (k.to_string(), *v)).collect()
    };
    let tilt = tried(&[("tilt_deg", 7.5), ("azimuth_deg", 200.0)]);
    let as_tried = with_learnt_parameters(
        Candidate::GroundTilt,
        &tried(&[("tilt_deg", 6.0), ("azimuth_deg", 180.0)]),
        &apply(&model, Candidate::GroundTilt, &tilt),
    );
    for key in ["tilt_deg", "azimuth_deg"] {
        assert!(
            (as_tried[key] - tilt[key]).abs() < 1e-9,
            "{key}: {as_tried:?}"
        );
    }
    let drag = tried(&[("quadratic_per_m", 150.0)]);
    let mut fitted = apply(&model, Candidate::AirDrag, &drag);
    fitted.physics.effects.air_drag_quadratic = 97.0;
    let learnt = with_learnt_parameters(Candidate::AirDrag, &drag, &fitted);
    assert_eq!(learnt, tried(&[("quadratic_per_m", 97.0)]), "no key added");
    // The extension's terms: a stiff ball's factor, a density excess.
    let ball = tried(&[("stiffness_factor", 8.0), ("radius_m", 0.02)]);
    let mut fitted = apply(&model, Candidate::StiffInclusion, &ball);
    fitted.extension.stiff_ball.as_mut().expect("ball").factor = 11.5;
    let learnt = with_learnt_parameters(Candidate::StiffInclusion, &ball, &fitted);
    assert_eq!(learnt["stiffness_factor"], 11.5);
    assert_eq!(learnt["radius_m"], 0.02);
    let density = tried(&[
        ("heavy_end_excess", -2.5),
        ("axis_x", 1.0),
        ("axis_y", 0.0),
        ("axis_z", 0.0),
    ]);
    let mut fitted = apply(&model, Candidate::DensityVariation, &density);
    let gradient = fitted.extension.density.as_mut().expect("gradient");
    gradient.excess = -3.4;
    gradient.axis = [0.6, -0.8, 0.0];
    let learnt = with_learnt_parameters(Candidate::DensityVariation, &density, &fitted);
    assert_eq!(learnt["heavy_end_excess"], -3.4);
    assert_eq!((learnt["axis_x"], learnt["axis_y"]), (0.6, -0.8));
}
