//! Detection limits that mean something: on a tiny lifted toy without a
//! hidden effect the diagnosis says `none` and reports the weakest ground
//! tilt this clip reveals; the same scene synthesised with the tilt hidden
//! at twice that limit is named `ground_tilt`, at half of it is not. And
//! the action variants tried for an effect the clip cannot show replay the
//! recorded hands as they say.

mod common;

use dm_bundle::Bundle;
use dm_diagnose::detectability::ActionVariant;
use dm_diagnose::{DiagnoseOptions, Diagnosis, diagnose};
use dm_synth::{Action, Preset, SynthConfig};
use std::path::Path;

/// The scene synthesised with `effect`, fitted briefly and diagnosed with
/// `detect_steps` (no discovery, no refit: the naming and the limits are
/// under test).
fn diagnose_scene(dir: &Path, effect: Option<String>, detect_steps: usize) -> Diagnosis {
    let scene = dir.join("scene");
    let config = SynthConfig {
        action: Some(Action::Lift),
        effect: effect.map(|e| e.parse().expect("effect")),
        ..SynthConfig::tiny(Preset::Toy, 11)
    };
    dm_synth::generate(&config, &scene, &dir.join("truth.json"), &mut |_, _, _| {}).expect("scene");
    let bundle = Bundle::open(&scene).expect("bundle");
    let model_dir = common::fit_physics_only(&bundle, 4, &dir.join("model"));
    let options = DiagnoseOptions {
        refit_iters: 0,
        discover_iters: 0,
        detect_steps,
        ..DiagnoseOptions::default()
    };
    diagnose(
        &model_dir,
        &scene,
        &dir.join("diagnosis"),
        None,
        &options,
        &mut |_, _, _| {},
    )
    .expect("diagnosis")
}

#[test]
fn an_effect_at_twice_the_reported_limit_is_named_and_at_half_is_not() {
    let dir = tempfile::tempdir().expect("temp dir");
    let null = diagnose_scene(
        &dir.path().join("null"),
        None,
        dm_diagnose::detectability::DEFAULT_DETECT_STEPS,
    );
    assert_eq!(null.cause, "none", "{:?}", null.candidates);
    let tilt = &null.detectability["ground_tilt"];
    let limit = tilt
        .min_magnitude
        .unwrap_or_else(|| panic!("a lifted toy reveals a tilt: {tilt:?}"));
    assert_eq!(tilt.unit, "deg");
    assert!(
        tilt.score >= null.threshold,
        "the limit's own score clears the threshold: {tilt:?}"
    );
    let report =
        std::fs::read_to_string(dir.path().join("null/diagnosis/report.md")).expect("report");
    assert!(report.contains("**Ruled out**"), "{report}");
    assert!(report.contains("## What this clip can show"), "{report}");

    let strong = diagnose_scene(
        &dir.path().join("strong"),
        Some(format!("ground_tilt:{}", 2.0 * limit)),
        0,
    );
    assert_eq!(
        strong.cause,
        "ground_tilt",
        "tilt {:.2}° (limit {limit:.2}°): {:?}",
        2.0 * limit,
        strong.candidates
    );
    let weak = diagnose_scene(
        &dir.path().join("weak"),
        Some(format!("ground_tilt:{}", 0.5 * limit)),
        0,
    );
    assert_ne!(
        weak.cause,
        "ground_tilt",
        "tilt {:.2}° (limit {limit:.2}°): {:?}",
        0.5 * limit,
        weak.candidates
    );
}

#[test]
fn action_variants_replay_the_recorded_hands_faster_or_wider() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = dir.path().join("scene");
    let config = SynthConfig {
        action: Some(Action::Push),
        ..SynthConfig::tiny(Preset::Rope, 3)
    };
    dm_synth::generate(
        &config,
        &scene,
        &dir.path().join("truth.json"),
        &mut |_, _, _| {},
    )
    .expect("scene");
    let bundle = Bundle::open(&scene).expect("bundle");
    let recorded = &bundle.tracks.hand_points;
    let frames = recorded.shape()[0];
    let faster = ActionVariant::TwiceAsFast.bundle(&bundle);
    let wider = ActionVariant::TwiceTheTravel.bundle(&bundle);
    for t in 0..frames {
        for m in 0..recorded.shape()[1] {
            for a in 0..3 {
                let at = |t: usize| recorded[[t, m, a]];
                assert_eq!(
                    faster.tracks.hand_points[[t, m, a]],
                    at((2 * t).min(frames - 1))
                );
                let travel = wider.tracks.hand_points[[t, m, a]] - at(0);
                assert!((travel - 2.0 * (at(t) - at(0))).abs() < 1e-6);
            }
        }
    }
    // The object's tracks are the recorded ones: only the hands change.
    assert_eq!(faster.tracks.object_points, bundle.tracks.object_points);
    assert_eq!(wider.tracks.object_points, bundle.tracks.object_points);
}
