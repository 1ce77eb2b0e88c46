//! Issue 4: `--residual-min-gain` keeps the residual network only where it
//! lowers the training split's Track error by the threshold, against the
//! same fit without it; below it the fit is the `--residual none` one.

mod common;

use dm_fit::residual_check::{CHECK_DIR, train_track};
use dm_fit::run::{FitOptions, FitOutcome, FitReport, run_fit};
use dm_model::WorldModel;
use std::path::Path;

/// Saved models are re-read from JSON (exact f64 round trip) and rolled out
/// again by the same deterministic code: only summation order could differ.
const SAME_ROLLOUT_RELATIVE: f64 = 1e-9;

/// Two residual-only steps; `last` so the stage's own keep rule does not
/// choose for the check.
const NETWORK: [&str; 6] = [
    "--residual",
    "pgnd",
    "--residual-iters",
    "2",
    "--residual-keep",
    "last",
];

fn fit(bundle: &dm_bundle::Bundle, options: &FitOptions, out: &Path) -> FitReport {
    match run_fit(bundle, options, out, false, None, &mut |_| {}).expect("fit") {
        FitOutcome::Finished(report) => *report,
        FitOutcome::Paused { .. } => panic!("the fit paused"),
    }
}

fn saved(dir: &Path) -> WorldModel {
    dm_bundle::read_json(&dir.join("model.json")).expect("model.json")
}

fn flags<'a>(extra: &[&'a str]) -> Vec<&'a str> {
    NETWORK
        .iter()
        .copied()
        .chain(extra.iter().copied())
        .collect()
}

/// A report's loss record less the steps' wall-clock seconds.
fn without_timings(mut loss: serde_json::Value) -> serde_json::Value {
    for step in loss["history"].as_array_mut().expect("history") {
        let step = step.as_object_mut().expect("step");
        step.remove("seconds");
        step.remove("phase_seconds");
    }
    loss
}

fn assert_close(recorded: f64, recomputed: f64, what: &str) {
    assert!(
        (recomputed - recorded).abs() <= SAME_ROLLOUT_RELATIVE * recorded,
        "{what}: recorded {recorded:.9e}, recomputed {recomputed:.9e}"
    );
}

#[test]
fn residual_check_drops_a_network_that_gains_too_little_and_keeps_one_that_gains_enough() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());

    // The check off: the network as the stages leave it.
    let unchecked_out = dir.path().join("unchecked");
    let unchecked_options = common::fit_options(&flags(&["--residual-min-gain", "0"]));
    let unchecked = fit(&bundle, &unchecked_options, &unchecked_out);
    assert!(
        unchecked.residual["check"].is_null(),
        "0 turns the check off"
    );
    assert!(!unchecked_out.join(CHECK_DIR).exists());
    let with_network = saved(&unchecked_out);
    assert!(with_network.residual.is_some());

    // Without the network, the physics-only fit.
    let plain_out = dir.path().join("plain_none");
    fit(
        &bundle,
        &common::fit_options(&["--residual", "none"]),
        &plain_out,
    );
    let plain = saved(&plain_out);

    // A threshold no network reaches on this clip: dropped. One stage-3
    // step after the check, so that the physics-only fit's Adam state and
    // history must be carried on as a plain fit carries them.
    let dropped_out = dir.path().join("dropped");
    let options = FitOptions {
        rgb_iters: 1,
        ..common::fit_options(&flags(&["--residual-min-gain", "0.99"]))
    };
    let dropped = fit(&bundle, &options, &dropped_out);
    let check = &dropped.residual["check"];
    eprintln!("check: {check}");
    let value = |key: &str| check[key].as_f64().unwrap_or_else(|| panic!("check.{key}"));
    // Each recorded Track is the train split's Track of the model it names:
    // the network's is the unchecked fit's (the same steps), the other the
    // physics-only fit saved under CHECK_DIR, itself a plain none fit.
    assert_close(
        value("track_with"),
        train_track(&with_network, &bundle, &options).expect("rollout"),
        "track_with",
    );
    let physics_only = saved(&dropped_out.join(CHECK_DIR));
    assert_eq!(physics_only, plain, "the check's fit is not the plain one");
    assert_close(
        value("track_without"),
        train_track(&plain, &bundle, &options).expect("rollout"),
        "track_without",
    );
    let gain = value("gain");
    assert_close(
        gain,
        1.0 - value("track_with") / value("track_without"),
        "gain",
    );
    assert_eq!(value("min_gain"), 0.99);
    assert_eq!(check["kept"], serde_json::json!(false));
    assert_eq!(dropped.residual["kind"], serde_json::json!("none"));
    assert_eq!(dropped.residual["parameters"].as_u64(), Some(0));
    // Dropped, the fit is the one `--residual none` makes with the same
    // options: model, history and all.
    let plain_rgb_out = dir.path().join("plain_none_rgb");
    let plain_rgb = fit(
        &bundle,
        &FitOptions {
            rgb_iters: 1,
            ..common::fit_options(&["--residual", "none"])
        },
        &plain_rgb_out,
    );
    assert_eq!(
        saved(&dropped_out),
        saved(&plain_rgb_out),
        "the dropped fit differs from a plain --residual none fit"
    );
    assert_eq!(
        without_timings(dropped.loss),
        without_timings(plain_rgb.loss),
        "the loss histories differ"
    );
    assert!(!dropped_out.join("residual.safetensors").exists());

    // A threshold below what the network gains: kept, and unchanged.
    assert!(
        gain > 0.0,
        "the network did not lower the training Track ({gain:+.4}): this scene no longer tests the keep"
    );
    let kept_out = dir.path().join("kept");
    let half = format!("{}", gain / 2.0);
    let kept = fit(
        &bundle,
        &common::fit_options(&flags(&["--residual-min-gain", &half])),
        &kept_out,
    );
    assert_eq!(kept.residual["check"]["kept"], serde_json::json!(true));
    assert_eq!(kept.residual["kind"], serde_json::json!("pgnd"));
    assert_eq!(
        saved(&kept_out),
        with_network,
        "a kept network differs from the unchecked fit's"
    );
}

#[test]
fn residual_min_gain_outside_0_to_1_is_refused() {
    for value in ["-0.1", "1", "1.5", "NaN", "a"] {
        let flag = format!("--residual-min-gain={value}");
        let error =
            common::try_fit_options(&[&flag]).expect_err("accepted a threshold outside [0, 1)");
        let message = error.to_string();
        assert!(
            message.contains("--residual-min-gain"),
            "{value}: {message}"
        );
    }
    assert_eq!(
        common::fit_options(&[]).residual_min_gain,
        dm_fit::run::DEFAULT_RESIDUAL_MIN_GAIN
    );
}
