//! Issue 8: the ONNX model adapters end to end on the fixture models of
//! `fixtures/models` (scripts/make_model_fixtures.py), which have the
//! manifest's signatures and simple, checkable behaviour.
//!
//! They need ONNX Runtime (`make lpips` installs it; `make test` runs that
//! first); a missing runtime fails them.

use std::path::PathBuf;

use dm_prep_models::depth::{
    DEPTH_ANYTHING_ID, DepthEstimator, MOGE_ID, apply_scale, fit_metric_scale,
};
use dm_prep_models::scale::DepthModel;
use dm_prep_models::segment::{Prompt, Segmenter};
use dm_prep_models::track::PointTracker;
use dm_prep_models::{Manifest, ModelError, OnnxModel, VerifyStatus, verify_dir};
use image::{Rgb, RgbImage};

fn fixture_models() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/models")
}

/// Fails the test, naming the fix, where ONNX Runtime is absent.
fn require_runtime() {
    if let Err(error) = dm_ort::dylib_path(&dm_ort::default_cache_dir()) {
        panic!("{error} (run `make lpips`, which installs ONNX Runtime)");
    }
}

fn manifest() -> Manifest {
    Manifest::builtin().expect("built-in manifest parses")
}

/// Dark frame with bright squares (x0, y0, side).
fn frame(width: u32, height: u32, squares: &[(u32, u32, u32)], level: u8) -> RgbImage {
    let mut image = RgbImage::from_pixel(width, height, Rgb([10, 10, 10]));
    for &(x0, y0, side) in squares {
        for y in y0..y0 + side {
            for x in x0..x0 + side {
                image.put_pixel(x, y, Rgb([level, level, level]));
            }
        }
    }
    image
}

#[test]
fn builtin_manifest_names_every_model_with_signature_and_source() {
    let manifest = manifest();
    let ids: Vec<&str> = manifest.entries.iter().map(|e| e.id.as_str()).collect();
    for id in [
        "sam2_image_encoder",
        "sam2_prompt_decoder",
        "cotracker3",
        "depth_anything3",
        "moge2",
    ] {
        assert!(ids.contains(&id), "{id} missing from {ids:?}");
        let entry = manifest.entry(id).expect("entry");
        assert!(
            !entry.inputs.is_empty()
                && !entry.outputs.is_empty()
                && entry.obtain.contains("https://")
        );
        assert!(entry.file.ends_with(".onnx"));
    }
}

#[test]
fn missing_model_names_the_model_its_entry_and_where_to_put_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let error = Segmenter::load(&manifest(), dir.path(), 1).expect_err("no files");
    let message = error.to_string();
    assert!(matches!(error, ModelError::Missing { .. }));
    for needle in [
        "SAM 2.1",
        "sam2_image_encoder",
        "models_manifest/sam2_image_encoder.json",
        "sam2.1_hiera_tiny.encoder.onnx",
        "https://github.com/facebookresearch/sam2",
    ] {
        assert!(message.contains(needle), "{needle:?} not in {message}");
    }
    assert!(
        message.contains(&dir.path().display().to_string()),
        "{message}"
    );
}

#[test]
fn verify_checks_signatures_and_pinned_digests() {
    require_runtime();
    let manifest = manifest();
    let reports = verify_dir(&manifest, &fixture_models());
    assert_eq!(reports.len(), manifest.entries.len());
    for report in &reports {
        assert!(
            matches!(
                report.status,
                VerifyStatus::Ok {
                    sha256_pinned: false,
                    ..
                }
            ),
            "{report:?}"
        );
    }
    // A pinned digest that differs fails, naming the entry.
    let mut pinned = manifest.clone();
    pinned.entries[0].sha256 = Some("0".repeat(64));
    let reports = verify_dir(&pinned, &fixture_models());
    match &reports[0].status {
        VerifyStatus::Failed(message) => assert!(
            message.contains(&pinned.entries[0].id) && message.contains("sha256"),
            "{message}"
        ),
        other => panic!("{other:?}"),
    }
    // The right digest passes as pinned.
    let digest = dm_prep_models::sha256_file(&fixture_models().join(&manifest.entries[0].file))
        .expect("digest");
    pinned.entries[0].sha256 = Some(digest);
    assert!(matches!(
        verify_dir(&pinned, &fixture_models())[0].status,
        VerifyStatus::Ok {
            sha256_pinned: true,
            ..
        }
    ));
    // An empty directory: everything absent, nothing failed.
    let empty = tempfile::tempdir().expect("tempdir");
    assert!(
        verify_dir(&manifest, empty.path())
            .iter()
            .all(|r| r.status == VerifyStatus::Absent)
    );
}

#[test]
fn a_model_with_the_wrong_signature_is_refused_with_the_entry_named() {
    require_runtime();
    // The depth fixture placed under the tracker's file name.
    let dir = tempfile::tempdir().expect("tempdir");
    let manifest = manifest();
    let tracker = manifest.entry("cotracker3").expect("entry").file.clone();
    std::fs::copy(
        fixture_models().join("da3_small.onnx"),
        dir.path().join(&tracker),
    )
    .expect("copy");
    let error =
        OnnxModel::load(&manifest, "cotracker3", dir.path(), 1).expect_err("wrong signature");
    let message = error.to_string();
    assert!(matches!(error, ModelError::Signature { .. }), "{message}");
    for needle in [
        "cotracker3",
        "models_manifest/cotracker3.json",
        "no input `video`",
        "unexpected input `image`",
        "no output `tracks`",
    ] {
        assert!(message.contains(needle), "{needle:?} not in {message}");
    }
}

#[test]
fn segmenter_keeps_the_prompted_object_through_the_clip() {
    require_runtime();
    let mut segmenter =
        Segmenter::load(&manifest(), &fixture_models(), 1).expect("fixture models load");
    // Two bright squares; the box prompt holds the left one, which moves
    // right by 6 px per frame. 320 × 240 exercises the longest-side padding.
    let frames: Vec<RgbImage> = (0..4)
        .map(|t| frame(320, 240, &[(40 + 6 * t, 80, 60), (230, 60, 50)], 230))
        .collect();
    let prompt = Prompt::Box {
        min: [30.0, 70.0],
        max: [110.0, 150.0],
    };
    let masks = segmenter.segment_clip(&frames, &prompt).expect("segment");
    assert_eq!(masks.len(), 4);
    for (t, mask) in masks.iter().enumerate() {
        let x0 = 40 + 6 * t as u32;
        let inside = |x: u32, y: u32| mask.get_pixel(x, y).0[0] == 255;
        // Interior of the moving square (2 px in from its edges: the mask is
        // upsampled from 256² logits of a 1024² input, 1.25 px per cell here).
        let mut missed = 0;
        for y in 82..138 {
            for x in x0 + 2..x0 + 58 {
                missed += usize::from(!inside(x, y));
            }
        }
        assert_eq!(missed, 0, "frame {t}: {missed} object pixels missed");
        // Nothing of the other square, nothing of the background far away.
        assert!(
            !inside(255, 85) && !inside(10, 10) && !inside(x0 + 75, 110),
            "frame {t}"
        );
    }
}

#[test]
fn tracker_maps_queries_and_tracks_between_frame_and_model_pixels() {
    require_runtime();
    let mut tracker =
        PointTracker::load(&manifest(), &fixture_models(), 1).expect("fixture model loads");
    // Uniform frames of rising brightness: the fixture moves every track by
    // (mean(t) − mean(0)) model pixels along x and hides frames brighter than 200.
    let levels = [50u8, 60, 80, 250];
    let frames: Vec<RgbImage> = levels
        .iter()
        .map(|&l| RgbImage::from_pixel(256, 192, Rgb([l, l, l])))
        .collect();
    let queries = [[10.0, 20.0], [200.5, 100.25]];
    let tracks = tracker.track(&frames, &queries).expect("track");
    assert_eq!(tracks.positions.dim(), (4, 2, 2));
    // 256 × 192 → 512 × 384: model pixels are half frame pixels.
    for (t, &level) in levels.iter().enumerate() {
        let shift_frame_px = (f64::from(level) - 50.0) / 2.0;
        for (n, query) in queries.iter().enumerate() {
            let x = f64::from(tracks.positions[[t, n, 0]]);
            let y = f64::from(tracks.positions[[t, n, 1]]);
            assert!(
                (x - (query[0] + shift_frame_px)).abs() < 1e-3,
                "t {t} n {n}: x {x}"
            );
            assert!((y - query[1]).abs() < 1e-3, "t {t} n {n}: y {y}");
        }
        assert_eq!(tracks.visible[[t, 0]], level < 200, "t {t}");
    }
}

#[test]
fn depth_adapters_return_frame_resolution_maps_made_metric_by_the_scale_fit() {
    require_runtime();
    let manifest = manifest();
    let image = frame(200, 150, &[(50, 40, 70)], 200);
    // Depth Anything fixture: 2 + mean over channels of the ImageNet-normalised input.
    let mut depth_anything =
        DepthEstimator::load(&manifest, DEPTH_ANYTHING_ID, &fixture_models(), 1).expect("load");
    let relative = depth_anything.estimate(&image).expect("depth");
    assert_eq!(relative.dim(), (150, 200));
    let preprocess = &manifest.entry(DEPTH_ANYTHING_ID).expect("entry").preprocess;
    let expected =
        |level: u8| 2.0 + (0..3).map(|c| preprocess.normalise(level, c)).sum::<f32>() / 3.0;
    assert!(
        (relative[[80, 80]] - expected(200)).abs() < 1e-4,
        "{} vs {}",
        relative[[80, 80]],
        expected(200)
    );
    assert!((relative[[5, 5]] - expected(10)).abs() < 1e-4);
    // MoGe fixture: z = 2 − mean of the [0, 1] image.
    let mut moge = DepthEstimator::load(&manifest, MOGE_ID, &fixture_models(), 1).expect("load");
    let z = moge.estimate(&image).expect("depth");
    assert!(
        (z[[80, 80]] - (2.0 - 200.0 / 255.0)).abs() < 1e-4,
        "{}",
        z[[80, 80]]
    );
    // Metric scale from a reference of 0.5 · relative + 0.1 m on the object.
    let mask = relative.mapv(|d| d > 2.0);
    let reference = relative.mapv(|d| 0.5 * d + 0.1);
    let masked_mono = relative.clone();
    // Two distinct values on the object would leave the fit underdetermined
    // for a shift; give the object a gradient.
    let mono = ndarray::Array2::from_shape_fn(masked_mono.dim(), |(y, x)| {
        masked_mono[[y, x]] + 0.001 * x as f32
    });
    let reference_gradient = ndarray::Array2::from_shape_fn(reference.dim(), |(y, x)| {
        reference[[y, x]] + 0.0005 * x as f32
    });
    let fit = fit_metric_scale(
        mono.view(),
        reference_gradient.view(),
        mask.view(),
        DepthModel::ScaleShift,
    )
    .expect("fit");
    assert!(
        (fit.scale - 0.5).abs() < 1e-3 && (fit.shift_m - 0.1).abs() < 1e-3,
        "{fit:?}"
    );
    let metric = apply_scale(mono.view(), &fit);
    assert!((metric[[80, 80]] - reference_gradient[[80, 80]]).abs() < 1e-3);
}
