//! The grid's body force learnt through the simulator's adjoint
//! (`MaterialFitConfig::force_field_terms`): on a scene hiding a steady
//! wind (`dm-synth --effect wind`), the learnt uniform push points along
//! the wind.

use dm_bundle::Bundle;
use dm_fit::learnt_effects::ForceFieldTerms;
use dm_fit::material_fit::{MaterialFitConfig, fit_material};
use dm_model::{ModelOptions, WorldModel};
use dm_synth::{Action, Preset, SynthConfig};

#[test]
fn a_hidden_wind_is_learnt_along_its_direction() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = dir.path().join("scene");
    let config = SynthConfig {
        action: Some(Action::Lift),
        effect: Some("wind:1.5".parse().expect("effect")),
        ..SynthConfig::tiny(Preset::Toy, 9)
    };
    let truth = dm_synth::generate(
        &config,
        &scene,
        &dir.path().join("truth.json"),
        &mut |_, _, _| {},
    )
    .expect("scene");
    let bundle = Bundle::open(&scene).expect("bundle");
    let wind = truth.physics.effects.force_field.uniform;
    let mut model = WorldModel::from_bundle(&bundle, &ModelOptions::default()).expect("model");
    let fit = MaterialFitConfig {
        iterations: 12,
        force_field_terms: ForceFieldTerms::ALL,
        ..MaterialFitConfig::default()
    };
    let mut losses = Vec::new();
    fit_material(&mut model, &bundle, &fit, &mut |r| losses.push(r.loss)).expect("fit");
    let learnt = model.physics.effects.force_field;
    let horizontal = |v: [f64; 3]| [v[0], v[1]];
    let (w, l) = (horizontal(wind), horizontal(learnt.uniform));
    let cos = (w[0] * l[0] + w[1] * l[1]) / (w[0].hypot(w[1]) * l[0].hypot(l[1]));
    assert!(
        cos > 20f64.to_radians().cos(),
        "learnt {learnt:?} against the wind {wind:?} (cos {cos:.3}; losses {losses:?})"
    );
    assert!(
        losses[losses.len() - 1] < 0.5 * losses[0],
        "losses {losses:?}"
    );
}
