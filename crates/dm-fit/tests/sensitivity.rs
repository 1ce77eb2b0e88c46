//! Issue 3: `fit_report.json` says how sharply the clip pins the fitted E
//! and ν (`material.sensitivity`), and where the fit's time went.

mod common;

use dm_fit::run::run_fit;
use dm_fit::sensitivity::moved_material;
use dm_model::WorldModel;

#[test]
fn moved_material_scales_e_and_shifts_nu_inside_the_bounds() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());
    let options = common::fit_options(&["--residual", "none"]);
    let model = WorldModel::from_bundle(&bundle, &options.model).expect("model");
    let (e, nu) = model.material_medians();

    // The identity move is a round trip through the bounded activations
    // (f64 logit/sigmoid: 1e-9 relative is far above their rounding).
    let same = moved_material(&model, 1.0, 0.0);
    let (e_same, nu_same) = same.material_medians();
    assert!((e_same / e - 1.0).abs() < 1e-9 && (nu_same - nu).abs() < 1e-9);

    let (e_up, nu_kept) = moved_material(&model, 1.25, 0.0).material_medians();
    assert!((e_up / e - 1.25).abs() < 1e-9, "{e_up} vs {e}");
    assert!((nu_kept - nu).abs() < 1e-9);
    let (_, nu_down) = moved_material(&model, 1.0, -0.05).material_medians();
    assert!((nu_down - (nu - 0.05)).abs() < 1e-9, "{nu_down} vs {nu}");

    // Past the upper bound: clamped inside it, never beyond.
    let (e_huge, _) = moved_material(&model, 1e6, 0.0).material_medians();
    assert!(e_huge <= model.bounds.youngs_pa[1] && e_huge > 0.99 * model.bounds.youngs_pa[1]);
}

#[test]
fn fit_report_has_the_material_sensitivity() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());
    let options = common::fit_options(&["--residual", "none"]);
    let out = dir.path().join("model");
    run_fit(&bundle, &options, &out, false, None, &mut |_| {}).expect("fit");
    let report: serde_json::Value =
        dm_bundle::read_json(&out.join("fit_report.json")).expect("report");
    let moved = &report["material"]["sensitivity"];
    for key in ["E_x0.75", "E_x1.25", "nu_minus_0.05", "nu_plus_0.05"] {
        let change = moved[key]
            .as_f64()
            .unwrap_or_else(|| panic!("{key}: {moved}"));
        // A finite relative change, and not the identity: every move
        // alters the rollout of this stretched rope somewhat.
        assert!(change.is_finite() && change != 0.0, "{key}: {change}");
    }
    // Where the time went: the steps' parts sum to `seconds` (a part's
    // time is taken out of its step's, so only round-off differs), and
    // the report's own time is apart.
    let by_stage = report["seconds_by_stage"]
        .as_object()
        .unwrap_or_else(|| panic!("seconds_by_stage: {report}"));
    let steps: f64 = by_stage
        .iter()
        .filter(|(part, _)| part.as_str() != "report")
        .map(|(_, seconds)| seconds.as_f64().unwrap_or(f64::NAN))
        .sum();
    let seconds = report["seconds"].as_f64().expect("seconds");
    assert!(
        (steps - seconds).abs() <= 1e-9 * seconds.max(1.0),
        "{steps} vs {seconds}"
    );
    assert!(by_stage.contains_key("material1") && by_stage.contains_key("report"));
    // A report written without the split still reads (dm-diagnose reads
    // the fit_report.json of models fitted before).
    let mut older = report.clone();
    older
        .as_object_mut()
        .expect("object")
        .remove("seconds_by_stage");
    let read: dm_fit::run::FitReport = serde_json::from_value(older).expect("older report");
    assert!(read.seconds_by_stage.is_empty());
}
