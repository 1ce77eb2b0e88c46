//! How the recorded hands drive the model. Issue 3: `--hand-smoothing`
//! drives the actuators by a smoothed hand track (a synthetic scene's
//! recorded hands carry 3 mm jitter and 10 % dropped frames; the truth
//! file keeps the scripted hands). Issue 6: `--grasp-radius` sets how wide
//! each anchor grips.

use dm_bundle::Bundle;
use dm_model::{ModelError, ModelOptions, ResidualKind, WorldModel};
use dm_synth::{Preset, SynthConfig, TruthFile};

fn scene(dir: &std::path::Path) -> (Bundle, TruthFile) {
    let mut config = SynthConfig::tiny(Preset::Rope, 4);
    config.frames = 30;
    let out = dir.join("scene");
    let truth = dm_synth::generate(&config, &out, &dir.join("truth.json"), &mut |_, _, _| {})
        .expect("scene");
    (Bundle::open(&out).expect("bundle"), truth)
}

fn model(bundle: &Bundle, hand_smoothing: f64) -> Result<WorldModel, ModelError> {
    let options = ModelOptions {
        residual: ResidualKind::None,
        hand_smoothing,
        ..ModelOptions::default()
    };
    WorldModel::from_bundle(bundle, &options)
}

/// RMS distance (m) of the anchors that drive `model` from the scripted
/// hands, over every frame.
fn drive_error(model: &WorldModel, bundle: &Bundle, truth: &TruthFile) -> f64 {
    let frames = bundle.frame_count();
    let mut sum = 0.0;
    let mut count = 0.0;
    for t in 0..frames - 1 {
        let (from, _, _) = model.hand_step(bundle, t);
        let exact: Vec<[f64; 3]> = truth
            .hands
            .iter()
            .flat_map(|h| h.anchors_at(t as f64 / bundle.meta.fps))
            .collect();
        for (p, q) in from.iter().zip(&exact) {
            sum += (0..3).map(|a| (p[a] - q[a]).powi(2)).sum::<f64>();
            count += 1.0;
        }
    }
    (sum / count).sqrt()
}

#[test]
fn hand_smoothing_brings_the_drive_closer_to_the_scripted_hands() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (bundle, truth) = scene(dir.path());
    let raw = model(&bundle, 0.0).expect("model");
    let smoothed = model(&bundle, 2.0).expect("model");
    // Off, the model reads the recorded track as the free function does.
    for t in 0..bundle.frame_count() - 1 {
        assert_eq!(raw.hand_step(&bundle, t), dm_model::hand_step(&bundle, t));
    }
    let (before, after) = (
        drive_error(&raw, &bundle, &truth),
        drive_error(&smoothed, &bundle, &truth),
    );
    // 3 mm of independent jitter per axis: a 2-frame kernel averages about
    // five frames, so at least a third of the error must go.
    assert!(
        after < 0.67 * before,
        "drive error {:.2} mm → {:.2} mm",
        1e3 * before,
        1e3 * after
    );
}

#[test]
fn bad_hand_smoothing_is_refused_naming_the_flag() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (bundle, _) = scene(dir.path());
    for sigma in [-1.0, f64::NAN, 1e3] {
        let error = model(&bundle, sigma).expect_err("refused").to_string();
        assert!(error.contains("--hand-smoothing"), "{error}");
    }
}

#[test]
fn grasp_radius_sets_the_grip_and_bad_values_are_refused() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (bundle, _) = scene(dir.path());
    let with_radius = |grasp_radius| {
        WorldModel::from_bundle(
            &bundle,
            &ModelOptions {
                residual: ResidualKind::None,
                grasp_radius,
                ..ModelOptions::default()
            },
        )
    };
    let default = with_radius(None).expect("default grip");
    assert_eq!(default.actuator.grasp_radius, 0.03);
    let narrow = with_radius(Some(0.014)).expect("narrow grip");
    assert_eq!(narrow.actuator.grasp_radius, 0.014);
    for bad in [0.0, -0.01, f64::NAN, 5.0] {
        let error = with_radius(Some(bad)).expect_err("refused").to_string();
        assert!(error.contains("--grasp-radius"), "{error}");
    }
}
