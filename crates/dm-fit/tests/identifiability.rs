//! Issue 3: `dm-fit --identifiability` bounds how precisely the clip's
//! training tracks determine ln E, ν and the actuator gains
//! (`material.identifiability`, the Cramér–Rao bound).

mod common;

use dm_fit::identifiability::{TrackNoise, identifiability_at};
use dm_fit::run::run_fit;
use dm_model::WorldModel;

#[test]
fn fit_report_bounds_the_parameters_only_when_asked() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());

    let plain = dir.path().join("plain");
    let options = common::fit_options(&["--residual", "none"]);
    run_fit(&bundle, &options, &plain, false, None, &mut |_| {}).expect("fit");
    let report: serde_json::Value =
        dm_bundle::read_json(&plain.join("fit_report.json")).expect("report");
    assert!(report["material"]["identifiability"].is_null(), "{report}");

    let bounded = dir.path().join("bounded");
    let options = common::fit_options(&["--residual", "none", "--identifiability"]);
    run_fit(&bundle, &options, &bounded, false, None, &mut |_| {}).expect("fit");
    let report: serde_json::Value =
        dm_bundle::read_json(&bounded.join("fit_report.json")).expect("report");
    let bound = &report["material"]["identifiability"];
    assert_eq!(bound["noise"]["sigma_m"].as_f64(), Some(1.5e-3), "{bound}");
    assert!(bound["observations"].as_u64().unwrap_or(0) > 0, "{bound}");
    let rows = bound["parameters"].as_array().expect("parameters");
    let names: Vec<&str> = rows.iter().filter_map(|r| r["name"].as_str()).collect();
    assert_eq!(names, ["ln_E", "nu", "ln_kp", "ln_kd"]);
    for row in rows {
        let all = row["std_all_estimated"].as_f64().expect("bound");
        assert!(all.is_finite() && all > 0.0, "{row}");
        // Knowing the gains can only tighten a material bound.
        if let Some(known) = row["std_gains_known"].as_f64() {
            assert!(known > 0.0 && known <= all * (1.0 + 1e-9), "{row}");
        }
    }
    let correlation = bound["correlation"].as_array().expect("correlation");
    assert_eq!(correlation.len(), 4);
}

#[test]
fn bound_scales_with_the_track_noise() {
    // Without offsets the information is J^T J / σ²: twice the noise,
    // twice every bound (the same rollouts, so only rounding differs).
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());
    let options = common::fit_options(&["--residual", "none"]);
    let model = WorldModel::from_bundle(&bundle, &options.model).expect("model");
    let frames = bundle.meta.split.train[1];
    let at = |sigma_m: f64| {
        identifiability_at(
            &model,
            &bundle,
            frames,
            TrackNoise {
                sigma_m,
                offset_sigma_m: 0.0,
            },
            &mut |_| {},
        )
        .expect("bound")
    };
    let (one, two) = (at(1e-3), at(2e-3));
    const RELATIVE_TOLERANCE: f64 = 1e-9;
    for (a, b) in one.parameters.iter().zip(&two.parameters) {
        let ratio = b.std_all_estimated / a.std_all_estimated;
        assert!(
            (ratio - 2.0).abs() < 2.0 * RELATIVE_TOLERANCE,
            "{}: {ratio}",
            a.name
        );
    }
}
