//! Issue 4: `--residual-training after-physics` fits the physics exactly as
//! `--residual none` does, then trains the network alone on top of it.

mod common;

use dm_fit::material_fit::FitError;
use dm_fit::run::{FitOptions, FitOutcome, FitReport, run_fit};
use dm_model::WorldModel;
use std::path::Path;

const AFTER_PHYSICS: [&str; 6] = [
    "--residual",
    "pgnd",
    "--residual-training",
    "after-physics",
    "--residual-iters",
    "2",
];

fn fit(
    bundle: &dm_bundle::Bundle,
    flags: &[&str],
    out: &Path,
    resume: bool,
    stop_after: Option<usize>,
) -> FitOutcome {
    run_fit(
        bundle,
        &two_material_steps(flags),
        out,
        resume,
        stop_after,
        &mut |_| {},
    )
    .expect("fit")
}

/// The shortest fit with two material steps: the first sees a zero network
/// either way (its last layer starts at zero), so only the second can tell
/// joint training apart.
fn two_material_steps(flags: &[&str]) -> FitOptions {
    FitOptions {
        iters: 2,
        ..common::fit_options(flags)
    }
}

fn finished(outcome: FitOutcome) -> FitReport {
    match outcome {
        FitOutcome::Finished(report) => *report,
        FitOutcome::Paused { .. } => panic!("the fit paused"),
    }
}

fn saved(out: &Path) -> WorldModel {
    dm_bundle::read_json(&out.join("model.json")).expect("model.json")
}

#[test]
fn issue4_after_physics_fits_the_physics_of_residual_none_then_trains_the_network() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());
    let none_out = dir.path().join("none");
    let after_out = dir.path().join("after");
    finished(fit(
        &bundle,
        &["--residual", "none"],
        &none_out,
        false,
        None,
    ));
    let report = finished(fit(&bundle, &AFTER_PHYSICS, &after_out, false, None));
    let (physics_only, after) = (saved(&none_out), saved(&after_out));

    // The material stages never saw the network: their result is the
    // physics-only fit's, bit for bit (the residual stage freezes it).
    assert_eq!(after.params, physics_only.params, "material differs");
    assert_eq!(after.actuator, physics_only.actuator, "gains differ");
    assert_eq!(after.physics, physics_only.physics, "physics differs");

    // The network was trained afterwards: the stage ran its two steps and
    // the untrained network's zero last layer has moved.
    let history = report.loss["history"].as_array().expect("history");
    assert_eq!(
        history.len(),
        2 + 2,
        "two material steps, two residual steps"
    );
    let network = after
        .residual_network()
        .expect("network")
        .expect("a network");
    let untrained = WorldModel::from_bundle(&bundle, &common::fit_options(&AFTER_PHYSICS).model)
        .expect("model")
        .residual_network()
        .expect("network")
        .expect("a network");
    assert_ne!(
        network.parameters().expect("weights"),
        untrained.parameters().expect("weights"),
        "the network never trained"
    );
}

#[test]
fn issue4_after_physics_resumes_with_the_network_held_back() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());
    let whole = dir.path().join("whole");
    let resumed = dir.path().join("resumed");
    finished(fit(&bundle, &AFTER_PHYSICS, &whole, false, None));
    // Paused after the material step, while the network waits in the checkpoint.
    assert!(matches!(
        fit(&bundle, &AFTER_PHYSICS, &resumed, false, Some(1)),
        FitOutcome::Paused { .. }
    ));
    finished(fit(&bundle, &AFTER_PHYSICS, &resumed, true, None));
    assert_eq!(
        saved(&resumed),
        saved(&whole),
        "the resumed fit differs from the uninterrupted one"
    );
}

#[test]
fn issue4_after_physics_without_residual_steps_is_refused() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());
    let flags = [
        "--residual",
        "pgnd",
        "--residual-training",
        "after-physics",
        "--residual-iters",
        "0",
    ];
    let out = dir.path().join("refused");
    let error = run_fit(
        &bundle,
        &common::fit_options(&flags),
        &out,
        false,
        None,
        &mut |_| {},
    )
    .expect_err("a network that would never train was accepted");
    assert!(
        matches!(&error, FitError::InvalidOption { option, .. } if option == "--residual-training"),
        "{error}"
    );
    assert!(!out.exists(), "a refused fit left {}", out.display());
}
