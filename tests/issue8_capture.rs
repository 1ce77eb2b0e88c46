//! Issue 8 end to end, through the libraries: dm-synth writes a 3-camera
//! RGB-D capture (colour MP4 + millimetre depth PNGs + calibration.json)
//! beside an exact-truth bundle; dm-prep's classical stages turn the
//! capture into a bundle; its 3D object tracks are scored against the
//! truth. A rerun reuses every cached stage.

use dm_bundle::Bundle;
use dm_prep::capture::SynthCaptureSink;
use dm_prep::score::score_tracks;
use dm_prep::stages::{Prep, PrepOptions, Stage};
use dm_synth::{Preset, SynthConfig};

/// The issue's bound is 5 mm on full-size scenes (docs/RESULTS.md: rope
/// 3.5 mm, cloth 4.7 mm); this short scene with a coarse truth (3000
/// particles, so larger splats and a sparser reference) must stay within
/// ISSUE8_SMALL_SCENE_LIMIT_M.
const ISSUE8_SMALL_SCENE_LIMIT_M: f64 = 0.008;

#[test]
fn issue8_capture_to_bundle_tracks_match_the_truth() {
    let dir = tempfile::tempdir().expect("temp dir");
    let config = SynthConfig {
        frames: 10,
        truth_particles: 3000,
        tracks: 1500,
        bundle_particles: 500,
        exact_tracks: true,
        ..SynthConfig::new(Preset::Rope, 3)
    };
    let truth_bundle = dir.path().join("truth");
    let capture = dir.path().join("capture");
    let mut sink = SynthCaptureSink::new(&capture);
    dm_synth::generate_with_capture(
        &config,
        &truth_bundle,
        &dir.path().join("truth.json"),
        Some(&mut sink),
        &mut |_, _, _| {},
    )
    .expect("scene generates");
    sink.finish().expect("capture closes");
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
