//! A term outside the library: on a tiny toy hiding a steady wind
//! (`dm-synth --effect wind`, which no library candidate is), the
//! diagnosis's discovered body force is a push along the wind, and the
//! model carrying it predicts the held-out frames better than the fitted
//! one. Its magnitude is not checked here: the tiny model's grip, wider
//! than the truth's, needs about 2.5 times the truth's push (measured at
//! the evaluation's settings instead, docs/diagnose.md).

mod common;

use dm_bundle::Bundle;
use dm_diagnose::{DiagnoseOptions, diagnose};
use dm_synth::{Action, Preset, SynthConfig};

/// The direction bar of the out-of-library evaluation (docs/diagnose.md).
const MAX_DIRECTION_ERROR_DEG: f64 = 20.0;

#[test]
fn a_hidden_wind_is_discovered_along_its_direction() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = dir.path().join("scene");
    let truth_path = dir.path().join("truth.json");
    let config = SynthConfig {
        action: Some(Action::Lift),
        effect: Some("wind:1.2".parse().expect("effect")),
        ..SynthConfig::tiny(Preset::Toy, 9)
    };
    let truth = dm_synth::generate(&config, &scene, &truth_path, &mut |_, _, _| {}).expect("scene");
    let bundle = Bundle::open(&scene).expect("bundle");
    let model_dir = common::fit_physics_only(&bundle, 8, &dir.path().join("model"));

    let out = dir.path().join("diagnosis");
    // The discovery starts from the fitted model, whatever the detection
    // limits find (tests/detectability.rs): skipped.
    let options = DiagnoseOptions {
        detect_steps: 0,
        ..DiagnoseOptions::default()
    };
    let d = diagnose(
        &model_dir,
        &scene,
        &out,
        Some(&truth_path),
        &options,
        &mut |_, _, _| {},
    )
    .expect("diagnosis");
    let found = d.discovered.as_ref().expect("discovery runs by default");
    let force = found
        .force
        .as_ref()
        .unwrap_or_else(|| panic!("a push discovered: {found:?}"));
    let wind = truth.physics.effects.force_field.uniform;
    let magnitude = wind.iter().map(|c| c * c).sum::<f64>().sqrt();
    let cos = (0..3)
        .map(|a| force.direction[a] * wind[a] / magnitude)
        .sum::<f64>();
    let angle = cos.clamp(-1.0, 1.0).acos().to_degrees();
    assert!(
        angle <= MAX_DIRECTION_ERROR_DEG,
        "direction {:?} is {angle:.1}° off the wind {wind:?}: {found:?}",
        force.direction
    );
    assert!(
        force
            .magnitude_std_m_s2
            .is_some_and(|s| s > 0.0 && s < 0.2 * force.magnitude_m_s2),
        "{found:?}"
    );
    assert!(found.held_out_reduction > 0.0, "{found:?}");
    assert!(out.join("discovered_model/model.json").is_file());
    let report = std::fs::read_to_string(out.join("report.md")).expect("report");
    assert!(report.contains("## Discovered term"), "{report}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("diagnosis.json")).expect("json"))
            .expect("parses");
    let direction = &json["discovered"]["force"]["direction"];
    assert_eq!(direction.as_array().map(Vec::len), Some(3), "{json}");
    assert!(json["discovered"]["force"]["magnitude_m_s2"].is_f64());
}
