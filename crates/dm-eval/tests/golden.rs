//! dm-eval's metrics against golden values computed once by independent
//! implementations (scripts/golden_image_metrics.py: scikit-image SSIM and
//! PSNR, numpy IoU, a float64 numpy forward pass of LPIPS, scipy k-d trees
//! for Chamfer and Track), on the fixture images of fixtures/golden/.

use dm_bundle::Tracks;
use dm_eval::image_metrics::{benchmark_pair, iou, psnr, ssim};
use dm_eval::lpips::{Lpips, LpipsPaths};
use dm_model::metrics::frame_errors;
use image::{GrayImage, RgbImage};
use ndarray::{Array2, Array3};
use serde_json::Value;
use std::path::PathBuf;

/// PSNR, SSIM and IoU are the same f64 formulas as the reference, summed in
/// another order: they agree to rounding.
const F64_FORMULA_TOLERANCE: f64 = 1e-9;
/// LPIPS runs in f32 through ONNX Runtime; the reference is f64. Measured
/// difference on the fixtures: < 1e-6; 1e-4 leaves room for other CPUs'
/// kernels while still catching any wrong layer, pooling or weight (those
/// move the value by > 1e-2).
const LPIPS_TOLERANCE: f64 = 1e-4;
/// Chamfer and Track: f32 positions widened to f64 on both sides.
const POINT_TOLERANCE: f64 = 1e-9;

fn golden_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/golden")
}

fn golden() -> Value {
    let path = golden_dir().join("image_metrics.json");
    let text =
        std::fs::read_to_string(&path).expect("golden values (scripts/golden_image_metrics.py)");
    serde_json::from_str(&text).expect("golden json")
}

fn rgb(name: &str) -> RgbImage {
    image::open(golden_dir().join(name))
        .expect("fixture image")
        .to_rgb8()
}

fn gray(name: &str) -> GrayImage {
    image::open(golden_dir().join(name))
        .expect("fixture mask")
        .to_luma8()
}

fn number(value: &Value, path: &[&str]) -> f64 {
    let mut v = value;
    for key in path {
        v = &v[*key];
    }
    v.as_f64()
        .unwrap_or_else(|| panic!("golden value {path:?} missing"))
}

fn assert_close(what: &str, actual: f64, expected: f64, tolerance: f64) {
    let diff = (actual - expected).abs();
    assert!(
        diff <= tolerance,
        "{what}: {actual} vs golden {expected} (diff {diff:.3e} > {tolerance:.1e})"
    );
    println!("{what}: {actual:.9} vs golden {expected:.9}, diff {diff:.2e}");
}

fn masked_pair() -> (RgbImage, RgbImage) {
    benchmark_pair(
        &rgb("image_a.png"),
        &gray("mask_object.png"),
        &gray("mask_hand.png"),
        &rgb("image_b.png"),
    )
    .expect("same sizes")
}

#[test]
fn psnr_matches_scikit_image() {
    let g = golden();
    let value = psnr(&rgb("image_a.png"), &rgb("image_b.png")).expect("psnr");
    assert_close(
        "PSNR raw",
        value,
        number(&g, &["raw", "psnr"]),
        F64_FORMULA_TOLERANCE,
    );
    let (truth, prediction) = masked_pair();
    let value = psnr(&truth, &prediction).expect("psnr");
    assert_close(
        "PSNR masked",
        value,
        number(&g, &["masked", "psnr"]),
        F64_FORMULA_TOLERANCE,
    );
}

#[test]
fn ssim_matches_scikit_image_gaussian_window() {
    let g = golden();
    let value = ssim(&rgb("image_a.png"), &rgb("image_b.png")).expect("ssim");
    assert_close(
        "SSIM raw",
        value,
        number(&g, &["raw", "ssim"]),
        F64_FORMULA_TOLERANCE,
    );
    let (truth, prediction) = masked_pair();
    let value = ssim(&truth, &prediction).expect("ssim");
    assert_close(
        "SSIM masked",
        value,
        number(&g, &["masked", "ssim"]),
        F64_FORMULA_TOLERANCE,
    );
}

#[test]
fn iou_matches_numpy() {
    let value = iou(&gray("mask_object.png"), &gray("alpha.png")).expect("iou");
    assert_close(
        "IoU",
        value,
        number(&golden(), &["iou_object_alpha"]),
        F64_FORMULA_TOLERANCE,
    );
}

#[test]
fn lpips_matches_numpy_forward_pass() {
    let paths = LpipsPaths::discover()
        .unwrap_or_else(|e| panic!("{e} (run `make lpips`, which builds the network)"));
    let mut network = Lpips::load(&paths, 0).expect("LPIPS network loads");
    let g = golden();
    let (a, b) = (rgb("image_a.png"), rgb("image_b.png"));
    let value = network.distance(&a, &b).expect("lpips");
    assert_close(
        "LPIPS raw",
        value,
        number(&g, &["raw", "lpips"]),
        LPIPS_TOLERANCE,
    );
    let (truth, prediction) = masked_pair();
    let value = network.distance(&truth, &prediction).expect("lpips");
    assert_close(
        "LPIPS masked",
        value,
        number(&g, &["masked", "lpips"]),
        LPIPS_TOLERANCE,
    );
    let same = network.distance(&a, &a).expect("lpips");
    assert_close("LPIPS identical", same, 0.0, 1e-6);
    // Symmetric by construction (squared differences).
    let swapped = network.distance(&b, &a).expect("lpips");
    assert_close(
        "LPIPS swapped",
        swapped,
        number(&g, &["raw", "lpips"]),
        LPIPS_TOLERANCE,
    );
}

/// The golden point sets as a rollout and observed tracks.
fn golden_points() -> (Vec<Vec<[f32; 3]>>, usize, Tracks, Value) {
    let g = golden()["points"].clone();
    let cloud = |v: &Value| -> Vec<Vec<[f32; 3]>> {
        v.as_array()
            .expect("frames")
            .iter()
            .map(|frame| {
                frame
                    .as_array()
                    .expect("points")
                    .iter()
                    .map(|p| std::array::from_fn(|a| p[a].as_f64().expect("coordinate") as f32))
                    .collect()
            })
            .collect()
    };
    let flags = |v: &Value| -> Vec<Vec<bool>> {
        v.as_array()
            .expect("frames")
            .iter()
            .map(|f| {
                f.as_array()
                    .expect("flags")
                    .iter()
                    .map(|b| b.as_bool().expect("bool"))
                    .collect()
            })
            .collect()
    };
    let rollout = cloud(&g["particles"]);
    let observed = cloud(&g["observed"]);
    let (visible, valid) = (flags(&g["visible"]), flags(&g["motion_valid"]));
    let (frames, n) = (observed.len(), observed[0].len());
    let tracks = Tracks {
        object_points: Array3::from_shape_fn((frames, n, 3), |(t, k, a)| observed[t][k][a]),
        object_visibility: Array2::from_shape_fn((frames, n), |(t, k)| visible[t][k]),
        object_motion_valid: Array2::from_shape_fn((frames, n), |(t, k)| valid[t][k]),
        hand_points: Array3::zeros((frames, 0, 3)),
        hand_visibility: Array2::from_elem((frames, 0), false),
    };
    let surface = g["surface_count"].as_u64().expect("surface_count") as usize;
    (rollout, surface, tracks, g)
}

#[test]
fn chamfer_and_track_match_scipy() {
    let (rollout, surface, tracks, g) = golden_points();
    let errors = frame_errors(&rollout, surface, &tracks);
    for (name, values) in [("chamfer", &errors.chamfer), ("track", &errors.track)] {
        let expected = g[name].as_array().expect("per-frame golden");
        assert_eq!(values.len(), expected.len());
        for (t, (actual, expected)) in values.iter().zip(expected).enumerate() {
            match expected.as_f64() {
                Some(e) => assert_close(&format!("{name}[{t}]"), *actual, e, POINT_TOLERANCE),
                None => assert!(
                    actual.is_nan(),
                    "{name}[{t}] = {actual}, expected NaN (no points)"
                ),
            }
        }
    }
}

/// The golden Chamfer tells the L1 definition from the Euclidean one (so
/// the test above fails if the metric reverts to Euclidean distances).
#[test]
fn golden_chamfer_discriminates_l1_from_euclidean() {
    let (rollout, surface, tracks, g) = golden_points();
    let t = 0;
    let surface_points = &rollout[t][..surface];
    let mut euclidean = 0.0;
    let mut count = 0;
    for k in 0..tracks.object_points.shape()[1] {
        if !tracks.object_visibility[[t, k]] {
            continue;
        }
        let q: [f64; 3] = std::array::from_fn(|a| f64::from(tracks.object_points[[t, k, a]]));
        euclidean += surface_points
            .iter()
            .map(|p| {
                (0..3)
                    .map(|a| (f64::from(p[a]) - q[a]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .fold(f64::INFINITY, f64::min);
        count += 1;
    }
    euclidean /= f64::from(count);
    let golden_l1 = g["chamfer"][t].as_f64().expect("chamfer[0]");
    assert!(
        (golden_l1 - euclidean).abs() > 1e3 * POINT_TOLERANCE,
        "L1 {golden_l1} and Euclidean {euclidean} Chamfer must differ"
    );
}
