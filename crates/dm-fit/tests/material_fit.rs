//! Issue 3, stage 1: learning the material through the differentiable
//! simulator lowers the train loss and moves E towards the truth.

use dm_bundle::Bundle;
use dm_fit::material_fit::{MaterialFitConfig, fit_material};
use dm_model::{ModelOptions, ResidualKind, WorldModel};
use dm_synth::{Action, Preset, SynthConfig};

#[test]
fn material_stage_lowers_loss_and_moves_youngs_towards_truth() {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = SynthConfig::tiny(Preset::Rope, 21);
    config.homogeneous = true;
    config.action = Some(Action::Lift);
    let out = dir.path().join("scene");
    let truth = dm_synth::generate(
        &config,
        &out,
        &dir.path().join("truth.json"),
        &mut |_, _, _| {},
    )
    .expect("scene");
    let bundle = Bundle::open(&out).expect("bundle");
    // Physics only (regression: a model without a residual must fit).
    let options = ModelOptions {
        residual: ResidualKind::None,
        ..ModelOptions::default()
    };
    let mut model = WorldModel::from_bundle(&bundle, &options).expect("model");
    let (youngs_start, _) = model.material_medians();
    let fit = MaterialFitConfig {
        iterations: 8,
        learning_rate: 0.15,
        ..MaterialFitConfig::default()
    };
    let reports = fit_material(&mut model, &bundle, &fit, &mut |_| {}).expect("fit runs");
    let first = reports.first().expect("iterations").loss;
    let last = reports.last().expect("iterations").loss;
    assert!(last < first, "loss {first:.3e} -> {last:.3e} did not drop");
    let (youngs_end, _) = model.material_medians();
    let gap = |e: f64| (e / truth.material.e_pa).ln().abs();
    assert!(
        gap(youngs_end) < gap(youngs_start),
        "E moved away from the truth {:.3e}: {youngs_start:.3e} -> {youngs_end:.3e}",
        truth.material.e_pa
    );
}
