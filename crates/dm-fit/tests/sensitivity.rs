//! Issue 3: `fit_report.json` says how sharply the clip pins the fitted E
//! and ν (`material.sensitivity`).

mod common;

use dm_fit::run::run_fit;
use dm_fit::sensitivity::moved_material;
use dm_model::WorldModel;

#[test]
fn issue3_moved_material_scales_e_and_shifts_nu_inside_the_bounds() {
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
fn issue3_fit_report_has_the_material_sensitivity() {
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
}
