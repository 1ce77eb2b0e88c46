//! Issue 3: `--search-grasp-radius` lets the CMA-ES gain search choose the
//! grip's width with its gains; without it the width stays the model's.

mod common;

use dm_fit::run::{GRASP_RADIUS_SEARCH_M, run_fit};
use dm_model::WorldModel;

/// Fits the tiny rope with a 7-rollout gain search and `flags`; returns
/// the report and the saved model.
fn fit(
    bundle: &dm_bundle::Bundle,
    out: &std::path::Path,
    flags: &[&str],
) -> (serde_json::Value, WorldModel) {
    let mut options = common::fit_options(&[&["--residual", "none"], flags].concat());
    options.gain_evals = 7;
    run_fit(bundle, &options, out, false, None, &mut |_| {}).expect("fit");
    (
        dm_bundle::read_json(&out.join("fit_report.json")).expect("report"),
        dm_bundle::read_json(&out.join("model.json")).expect("model"),
    )
}

#[test]
fn gain_search_chooses_the_grasp_radius_only_when_asked() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());
    let default_radius = dm_mpm::ActuatorConfig::default().grasp_radius;

    let (report, model) = fit(&bundle, &dir.path().join("gains"), &[]);
    assert_eq!(model.actuator.grasp_radius, default_radius);
    assert_eq!(
        report["dca"]["grasp_radius_m"].as_f64(),
        Some(default_radius)
    );
    let trials = report["gain_search"].as_array().expect("trials");
    assert!(trials.len() > 1, "{report}");
    assert!(
        trials.iter().all(|t| t.get("grasp_radius").is_none()),
        "{report}"
    );

    let (report, model) = fit(
        &bundle,
        &dir.path().join("radius"),
        &["--search-grasp-radius"],
    );
    let trials = report["gain_search"].as_array().expect("trials");
    let radii: Vec<f64> = trials
        .iter()
        .map(|t| t["grasp_radius"].as_f64().expect("each trial has a radius"))
        .collect();
    let [lo, hi] = GRASP_RADIUS_SEARCH_M;
    assert!(radii.iter().all(|r| (lo..=hi).contains(r)), "{radii:?}");
    assert!(
        radii.iter().any(|&r| (r - radii[0]).abs() > 1e-6),
        "the search never moved the radius: {radii:?}"
    );
    // The model keeps the lowest-loss trial's grip.
    let best = trials
        .iter()
        .min_by(|a, b| {
            let loss = |t: &serde_json::Value| t["loss"].as_f64().unwrap_or(f64::INFINITY);
            loss(a).total_cmp(&loss(b))
        })
        .expect("a trial");
    assert_eq!(
        best["grasp_radius"].as_f64(),
        Some(model.actuator.grasp_radius)
    );
    assert_eq!(best["kp"].as_f64(), Some(model.actuator.kp));
    assert_eq!(
        report["dca"]["grasp_radius_m"].as_f64(),
        Some(model.actuator.grasp_radius)
    );
}
