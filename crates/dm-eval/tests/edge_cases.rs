//! Empty and mismatched inputs: the documented NaN results and clear errors.

use dm_bundle::Tracks;
use dm_eval::image_metrics::{ImageMetricError, benchmark_pair, iou, psnr, ssim, without_hand};
use dm_eval::lpips::{LpipsError, LpipsPaths, MODEL_FILE};
use dm_eval::{FrameMetrics, SplitMetrics, SplitName};
use dm_model::metrics::{frame_errors, split_mean};
use image::{GrayImage, Luma, Rgb, RgbImage};
use ndarray::{Array2, Array3};

#[test]
fn iou_of_two_empty_masks_is_nan_and_of_disjoint_masks_zero() {
    let empty = GrayImage::new(20, 10);
    assert!(iou(&empty, &empty).expect("same size").is_nan());
    let mut left = GrayImage::new(20, 10);
    left.put_pixel(1, 1, Luma([255]));
    let mut right = GrayImage::new(20, 10);
    right.put_pixel(15, 5, Luma([255]));
    assert_eq!(iou(&left, &right).expect("same size"), 0.0);
    assert_eq!(iou(&left, &left).expect("same size"), 1.0);
}

#[test]
fn identical_images_have_infinite_psnr_and_unit_ssim() {
    let image = RgbImage::from_fn(24, 16, |x, y| Rgb([(x * 10) as u8, (y * 15) as u8, 7]));
    assert_eq!(psnr(&image, &image).expect("psnr"), f64::INFINITY);
    assert!((ssim(&image, &image).expect("ssim") - 1.0).abs() < 1e-12);
    // All black (an empty object mask and an empty render): SSIM is 1, not NaN.
    let black = RgbImage::new(24, 16);
    assert!((ssim(&black, &black).expect("ssim") - 1.0).abs() < 1e-12);
}

#[test]
fn mismatched_or_tiny_images_are_errors() {
    let a = RgbImage::new(20, 20);
    let b = RgbImage::new(20, 21);
    assert!(matches!(
        psnr(&a, &b),
        Err(ImageMetricError::SizeMismatch { .. })
    ));
    assert!(matches!(
        ssim(&a, &b),
        Err(ImageMetricError::SizeMismatch { .. })
    ));
    let tiny = RgbImage::new(10, 30);
    let err = ssim(&tiny, &tiny).expect_err("smaller than the window");
    assert!(err.to_string().contains("11x11"), "{err}");
    assert!(matches!(
        psnr(&RgbImage::new(0, 0), &RgbImage::new(0, 0)),
        Err(ImageMetricError::Empty { .. })
    ));
    let mask = GrayImage::new(20, 20);
    assert!(benchmark_pair(&a, &mask, &GrayImage::new(5, 5), &a).is_err());
    assert!(without_hand(&mask, &GrayImage::new(5, 5)).is_err());
}

#[test]
fn masking_blackens_background_and_hand_in_both_images() {
    let observed = RgbImage::from_pixel(4, 1, Rgb([200, 100, 50]));
    let rendered = RgbImage::from_pixel(4, 1, Rgb([10, 20, 30]));
    // pixel 0: object; 1: object under the hand; 2: hand only; 3: neither.
    let object = GrayImage::from_raw(4, 1, vec![255, 255, 0, 0]).expect("mask");
    let hand = GrayImage::from_raw(4, 1, vec![0, 255, 255, 0]).expect("mask");
    let (truth, prediction) = benchmark_pair(&observed, &object, &hand, &rendered).expect("pair");
    let black = Rgb([0, 0, 0]);
    assert_eq!(
        truth.pixels().copied().collect::<Vec<_>>(),
        vec![Rgb([200, 100, 50]), black, black, black]
    );
    assert_eq!(
        prediction.pixels().copied().collect::<Vec<_>>(),
        vec![Rgb([10, 20, 30]), black, black, Rgb([10, 20, 30])]
    );
}

#[test]
fn frames_without_visible_points_give_nan_and_are_left_out_of_means() {
    let frames = 3;
    let tracks = Tracks {
        object_points: Array3::zeros((frames, 2, 3)),
        object_visibility: Array2::from_shape_fn((frames, 2), |(t, _)| t != 1),
        object_motion_valid: Array2::from_elem((frames, 2), true),
        hand_points: Array3::zeros((frames, 0, 3)),
        hand_visibility: Array2::from_elem((frames, 0), false),
    };
    let rollout = vec![vec![[0.0f32, 0.0, 0.01]]; frames];
    let errors = frame_errors(&rollout, 1, &tracks);
    assert!(errors.chamfer[1].is_nan() && errors.track[1].is_nan());
    assert!((errors.chamfer[0] - 0.01).abs() < 1e-9);
    assert!((split_mean(&errors.chamfer, [0, 3]) - 0.01).abs() < 1e-9);
    assert!(split_mean(&errors.chamfer, [1, 2]).is_nan());

    // A rollout without particles: NaN, not a panic.
    let nothing = frame_errors(&vec![Vec::new(); frames], 0, &tracks);
    assert!(
        nothing
            .chamfer
            .iter()
            .chain(&nothing.track)
            .all(|v| v.is_nan())
    );
}

#[test]
fn split_means_skip_undefined_frames_and_keep_skipped_lpips_null() {
    let frame = |t: usize, iou: f64| FrameMetrics {
        frame: t,
        split: Some(SplitName::Train),
        chamfer: 0.01,
        track: 0.02,
        iou,
        psnr: 20.0,
        ssim: 0.9,
        lpips: None,
    };
    let frames = vec![frame(0, 0.5), frame(1, f64::NAN), frame(2, 0.7)];
    let means = SplitMetrics::mean_over(&frames, [0, 3]);
    assert!((means.iou - 0.6).abs() < 1e-12);
    assert_eq!(means.lpips, None);
    let json = serde_json::to_value(&means).expect("json");
    assert!(json["lpips"].is_null());
    let nan_json = serde_json::to_value(frame(1, f64::NAN)).expect("json");
    assert!(nan_json["iou"].is_null(), "NaN is written as null");
}

#[test]
fn a_missing_lpips_cache_names_the_file_and_the_make_target() {
    let dir = tempfile::tempdir().expect("temp dir");
    let err = LpipsPaths::in_dir(dir.path()).expect_err("empty cache");
    assert!(matches!(err, LpipsError::MissingCache { .. }));
    let message = err.to_string();
    assert!(
        message.contains(MODEL_FILE) && message.contains("make lpips"),
        "{message}"
    );
}
