//! Issue 6: `run_fit_from` runs dm-fit's stages from a given starting
//! model (dm-diagnose fits each candidate effect from the start).

mod common;

use dm_fit::run::{run_fit, run_fit_from};
use dm_model::WorldModel;

fn saved(dir: &std::path::Path) -> WorldModel {
    dm_bundle::read_json(&dir.join("model.json")).expect("model.json")
}

#[test]
fn issue6_fit_from_a_starting_model_keeps_its_effect_and_matches_run_fit_from_the_default() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());
    let flags = ["--residual", "none"];
    let options = common::fit_options(&flags);

    let plain = dir.path().join("plain");
    run_fit(&bundle, &options, &plain, false, None, &mut |_| {}).expect("fit");
    let default_start = WorldModel::from_bundle(&bundle, &options.model).expect("start");
    let from_default = dir.path().join("from_default");
    run_fit_from(
        &bundle,
        &options,
        default_start.clone(),
        &from_default,
        &mut |_| {},
    )
    .expect("fit from the default start");
    // Same start, same deterministic stages: the same model, bit for bit.
    assert_eq!(saved(&plain), saved(&from_default));

    let mut with_drag = default_start;
    with_drag.physics.effects.air_drag_linear = 25.0;
    let dragged = dir.path().join("dragged");
    run_fit_from(&bundle, &options, with_drag, &dragged, &mut |_| {})
        .expect("fit from a start with drag");
    let fitted = saved(&dragged);
    assert_eq!(fitted.physics.effects.air_drag_linear, 25.0);
    // The drag changed what the material step saw.
    assert_ne!(fitted.params, saved(&plain).params);
}
