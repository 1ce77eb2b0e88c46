//! Detection limits: on a tiny lifted toy without a hidden effect the
//! diagnosis says `none`, reports the weakest ground tilt this clip
//! reveals, and every limit's scan brackets the `none` threshold where it
//! says (revealed at the limit's scan point, not at the one before; a
//! missing limit never reached it). Whether a hidden effect at a multiple
//! of the limit is then named in a fresh clip is measured by
//! `detection_limits_eval` (docs/diagnose.md: the clip's own fit absorbs
//! part of an effect, and a directed effect's visibility depends on its
//! direction, so the limits do not predict it). And the action variants
//! tried for an effect the clip cannot show replay the recorded hands as
//! they say.

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
fn every_limit_brackets_the_threshold_in_its_scan() {
    let dir = tempfile::tempdir().expect("temp dir");
    let null = diagnose_scene(
        &dir.path().join("null"),
        None,
        dm_diagnose::detectability::DEFAULT_DETECT_STEPS,
    );
    assert_eq!(null.cause, "none", "{:?}", null.candidates);
    let tilt = &null.detectability["ground_tilt"];
    assert!(
        tilt.min_magnitude.is_some(),
        "a lifted toy reveals a tilt: {tilt:?}"
    );
    assert_eq!(tilt.unit, "deg");
    assert_eq!(null.detectability.len(), 8, "every library effect");
    for (name, l) in &null.detectability {
        let scanned: Vec<f64> = l.scan.iter().map(|p| p[1]).collect();
        let last = *scanned.last().expect("a scan");
        match l.min_magnitude {
            // Revealed at the last scan point, not before (bisection then
            // moved the limit into that bracket).
            Some(m) => {
                assert!(l.score >= null.threshold, "{name}: {l:?}");
                assert!(last >= null.threshold, "{name}: {l:?}");
                assert!(
                    scanned[..scanned.len() - 1]
                        .iter()
                        .all(|s| *s < null.threshold),
                    "{name}: {l:?}"
                );
                let at = l.scan[scanned.len() - 1][0];
                let before = l.scan.get(scanned.len().wrapping_sub(2)).map(|p| p[0]);
                let inside =
                    |a: f64, b: f64| m >= a.min(b) * (1.0 - 1e-9) && m <= a.max(b) * (1.0 + 1e-9);
                assert!(
                    before.map_or(m == at, |b| inside(b, at)),
                    "{name}: limit {m} outside its bracket {:?}",
                    l.scan
                );
            }
            None => assert!(scanned.iter().all(|s| *s < null.threshold), "{name}: {l:?}"),
        }
    }
    let report =
        std::fs::read_to_string(dir.path().join("null/diagnosis/report.md")).expect("report");
    assert!(report.contains("**Ruled out**"), "{report}");
    assert!(report.contains("## What this clip can show"), "{report}");
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
