//! Issue 8 end to end, through the libraries: dm-synth writes a 3-camera
//! RGB-D capture (colour MP4 + millimetre depth PNGs + calibration.json)
//! beside an exact-truth bundle; dm-prep's classical stages turn the
//! capture into a bundle; its 3D object tracks are scored against the
//! truth. A rerun reuses every cached stage.

use std::path::{Path, PathBuf};

use dm_bundle::Bundle;
use dm_capture::Calibration;
use dm_prep::monocular::{DepthSource, MonocularOptions, write_monocular_capture};
use dm_prep::score::{ScoreFrame, score_tracks, score_tracks_in};
use dm_prep::stages::{Prep, PrepOptions, Stage};
use dm_synth::{Preset, SynthConfig};
use dm_synth_capture::SynthCaptureSink;

/// The issue's bound is 5 mm on full-size scenes (docs/RESULTS.md: rope
/// 3.5 mm, cloth 4.7 mm); this short scene with a coarse truth (3000
/// particles, so larger splats and a sparser reference) must stay within
/// ISSUE8_SMALL_SCENE_LIMIT_M.
const ISSUE8_SMALL_SCENE_LIMIT_M: f64 = 0.008;
/// The sensor model's depth noise (a few mm at 0.6 m) and the object on the
/// floor (excluded as outliers) leave the fitted camera height this close.
const ISSUE8_MONOCULAR_FLOOR_TOLERANCE_M: f64 = 0.005;

/// dm-synth's rope seed 7 (`frames` frames) as an exact-truth bundle and
/// its 3-camera capture under `dir`: (config, truth bundle, capture).
fn synth_rope_capture(dir: &Path, frames: usize) -> (SynthConfig, PathBuf, PathBuf) {
    let config = SynthConfig {
        frames,
        truth_particles: 3000,
        tracks: 1500,
        bundle_particles: 500,
        exact_tracks: true,
        ..SynthConfig::new(Preset::Rope, 7)
    };
    let truth_bundle = dir.join("truth");
    let capture = dir.join("capture");
    let mut sink = SynthCaptureSink::new(&capture);
    dm_synth::generate_with_capture(
        &config,
        &truth_bundle,
        &dir.join("truth.json"),
        Some(&mut sink),
        &mut |_, _, _| {},
    )
    .expect("scene generates");
    sink.finish().expect("capture closes");
    (config, truth_bundle, capture)
}

#[test]
fn capture_to_bundle_tracks_match_the_truth() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (config, truth_bundle, capture) = synth_rope_capture(dir.path(), 10);
    assert!(capture.join("cam0/color.mp4").is_file());
    assert!(capture.join("cam2/depth/00009.png").is_file());
    assert!(!capture.join("cam0/mask_object").exists());

    let work = dir.path().join("work");
    let prep = Prep::new(&capture, &work, PrepOptions::default()).expect("capture opens");
    let out = dir.path().join("prepared");
    let bundle = prep
        .write_bundle(&out, false, &mut |_, _, _| {})
        .expect("bundle written");
    bundle.validate_images().expect("images valid");
    assert_eq!(bundle.meta.category, dm_bundle::Category::Linear);
    assert!(
        bundle.tracks.object_point_count() >= 100,
        "{}",
        bundle.tracks.object_point_count()
    );

    let score = score_tracks(&out, &truth_bundle).expect("scores");
    assert!(
        score.median_m <= ISSUE8_SMALL_SCENE_LIMIT_M,
        "median track error {} m",
        score.median_m
    );

    // The prepared hands move with the true ones. The synthetic hands are
    // untextured: their point tracks stick in place, and the anchors
    // follow the hand-mask centroid instead (dm_prep::lift).
    let truth = Bundle::open(&truth_bundle).expect("truth bundle");
    let last = config.frames - 1;
    let displacement = |b: &Bundle, range: [usize; 2]| {
        let mean = |t: usize| {
            let n = (range[1] - range[0]) as f64;
            [0, 1, 2].map(|a| {
                (range[0]..range[1])
                    .map(|k| f64::from(b.tracks.hand_points[[t, k, a]]))
                    .sum::<f64>()
                    / n
            })
        };
        let (start, end) = (mean(0), mean(last));
        (start, [0, 1, 2].map(|a| end[a] - start[a]))
    };
    let norm = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    assert!(!bundle.meta.hands.is_empty(), "no hand found");
    for hand in &bundle.meta.hands {
        let (start, moved) = displacement(&bundle, hand.anchor_range);
        let (_, truly) = truth
            .meta
            .hands
            .iter()
            .map(|h| displacement(&truth, h.anchor_range))
            .min_by(|a, b| {
                let d = |p: [f64; 3]| norm([0, 1, 2].map(|i| p[i] - start[i]));
                d(a.0).total_cmp(&d(b.0))
            })
            .expect("truth hands");
        let cosine = (0..3).map(|a| moved[a] * truly[a]).sum::<f64>() / (norm(moved) * norm(truly));
        assert!(
            cosine > 0.8 && norm(moved) > 0.5 * norm(truly),
            "{}: moved {moved:?}, truth {truly:?}",
            hand.name
        );
    }

    // Everything is cached: a second run runs nothing.
    for stage in Stage::ALL {
        assert!(prep.is_current(stage), "{} stale", stage.name());
    }
    let outcomes = prep.run(Stage::Fill, &mut |_, _, _| {}).expect("rerun");
    assert!(outcomes.iter().all(|o| !o.ran), "{outcomes:?}");
    let again = dir.path().join("again");
    prep.write_bundle(&again, false, &mut |_, _, _| {})
        .expect("rewritten");
    let a = Bundle::open(&out).expect("first");
    let b = Bundle::open(&again).expect("second");
    assert_eq!(a.tracks, b.tracks);
}

/// One camera of the rig as a phone clip with depth frames (`dm-prep
/// VIDEO --depth DIR`): the floor fit must find the true camera height,
/// and the tracks, compared in the camera's frame (the clip's world is its
/// own), must match the truth within the small-scene bound.
#[test]
fn monocular_clip_with_depth_frames_tracks_match_the_truth() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (_, truth_bundle, capture) = synth_rope_capture(dir.path(), 10);
    let rig = Calibration::read(&capture).expect("calibration");
    let camera = &rig.cameras[0];
    let clip = capture.join(&camera.name).join("color.mp4");
    let frames = dm_capture::video::decode_video(&clip).expect("clip decodes");
    let options = MonocularOptions {
        intrinsics: Some([camera.fx, camera.fy, camera.cx, camera.cy]),
        ..MonocularOptions::default()
    };
    let mono_capture = dir.path().join("mono-capture");
    let (_, floor) = write_monocular_capture(
        &clip,
        &frames,
        rig.fps,
        DepthSource::Frames(capture.join(&camera.name).join("depth")),
        &options,
        &mono_capture,
        &mut |_, _| {},
    )
    .expect("capture written");
    // The rig's floor is z = floor_height_m; camera 0's centre is −Rᵀt.
    let m = camera.world_to_camera;
    let eye_z = -(0..3).map(|r| m[r][2] * m[r][3]).sum::<f64>();
    let true_height = eye_z - rig.floor_height_m;
    assert!(
        (floor.offset_m - true_height).abs() < ISSUE8_MONOCULAR_FLOOR_TOLERANCE_M,
        "floor {} m below the camera, truth {true_height} m",
        floor.offset_m
    );

    let prep = Prep::new(
        &mono_capture,
        &dir.path().join("mono-work"),
        PrepOptions::default(),
    )
    .expect("capture opens");
    let out = dir.path().join("mono-bundle");
    let bundle = prep
        .write_bundle(&out, false, &mut |_, _, _| {})
        .expect("bundle written");
    assert_eq!(bundle.meta.cameras.len(), 1);
    assert!(
        bundle.tracks.object_point_count() >= 100,
        "{}",
        bundle.tracks.object_point_count()
    );
    let score = score_tracks_in(&out, &truth_bundle, ScoreFrame::Camera0).expect("scores");
    assert!(
        score.median_m <= ISSUE8_SMALL_SCENE_LIMIT_M,
        "median track error {} m",
        score.median_m
    );
}
