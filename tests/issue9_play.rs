//! Issue 9: the playground session through its API (no browser): picking,
//! a recording is a valid scene bundle, the frame message carries the
//! sprites, bad options and commands are errors. (The grab-and-lift and
//! tearing tests are on branch issue9-play-wip: they fail so far — the
//! grasped particles do not carry the object yet.)

mod common {

    use std::path::PathBuf;

    use dm_appearance::{AppearanceOptions, fit_appearance, save_appearance};
    use dm_bundle::{Bundle, write_json_atomic};
    use dm_model::{ModelOptions, ResidualKind, WorldModel};
    use dm_synth::{Preset, SynthConfig};

    pub struct TinyModel {
        pub dir: tempfile::TempDir,
        pub model_dir: PathBuf,
    }

    pub fn tiny_model(with_splats: bool) -> TinyModel {
        let dir = tempfile::tempdir().expect("temp dir");
        let scene = dir.path().join("scene");
        dm_synth::generate(
            &SynthConfig::tiny(Preset::Toy, 9),
            &scene,
            &dir.path().join("truth.json"),
            &mut |_, _, _| {},
        )
        .expect("scene generates");
        let bundle = Bundle::open(&scene).expect("bundle");
        let options = ModelOptions {
            residual: ResidualKind::None,
            ..ModelOptions::default()
        };
        let model = WorldModel::from_bundle(&bundle, &options).expect("model");
        let model_dir = dir.path().join("model");
        std::fs::create_dir_all(&model_dir).expect("model dir");
        write_json_atomic(&model_dir.join("model.json"), &model).expect("model.json");
        if with_splats {
            let appearance = AppearanceOptions {
                iterations: 3,
                ..AppearanceOptions::for_cameras(bundle.meta.cameras.len())
            };
            let (gaussians, record) =
                fit_appearance(&model, &bundle, &appearance, &mut |_| {}).expect("splat fit");
            save_appearance(&model_dir, &gaussians, &record).expect("splats saved");
        }
        TinyModel { dir, model_dir }
    }
}

use dm_play::{FRAME_HEADER_WORDS, FRAME_MAGIC, PlayOptions, Session, encode_frame, open_session};

/// Grabs the particle nearest to `target` with `hand` (through the pick ray
/// from straight above, as a click would).
fn grab_near(session: &mut Session, hand: usize, target: [f64; 3]) {
    let up = session.view().up;
    let origin = [0, 1, 2].map(|a| target[a] + up[a]);
    let particle = session
        .pick(origin, up.map(|c| -c))
        .expect("the ray from above hits the object");
    session.grab(hand, particle).expect("grab");
}

#[test]
fn issue9_pick_misses_off_the_object() {
    let tiny = common::tiny_model(false);
    let session = open_session(&tiny.model_dir, &PlayOptions::interactive()).expect("session");
    let up = session.view().up;
    let right = session.view().main_right();
    let far = [0, 1, 2].map(|a| session.view().centre[a] + 3.0 * session.view().extent * right[a]);
    let origin = [0, 1, 2].map(|a| far[a] + up[a]);
    assert_eq!(session.pick(origin, up.map(|c| -c)), None);
    assert_eq!(session.pick(origin, [0.0; 3]), None);
}

#[test]
fn issue9_recording_is_a_valid_bundle() {
    let tiny = common::tiny_model(false);
    let mut session = open_session(&tiny.model_dir, &PlayOptions::interactive()).expect("session");
    let centre = session.view().centre;
    grab_near(&mut session, 0, centre);
    session.start_recording();
    let up = session.view().up;
    session
        .set_hand_velocity(0, up.map(|c| 0.2 * c))
        .expect("velocity");
    for _ in 0..4 {
        session.step().expect("step");
    }
    let recording = session.take_recording().expect("recording");
    assert_eq!(recording.positions.len(), 5);
    let out = tiny.dir.path().join("recordings");
    let bundle_dir = dm_play::record::write_recording(
        &out,
        session.model(),
        session.body(),
        session.view(),
        &recording,
        session.frame_dt(),
    )
    .expect("bundle written");
    let bundle =
        dm_bundle::Bundle::open(&bundle_dir).expect("the recording reads back as a bundle");
    assert_eq!(bundle.frame_count(), 5);
    assert_eq!(bundle.meta.cameras.len(), 3);
    assert_eq!(bundle.meta.hands.len(), 2);
    assert_eq!(
        bundle.particles.surface_points.nrows() + bundle.particles.interior_points.nrows(),
        session.body().particles.len()
    );
    // The hand track is the recorded anchor path: hand 1 rose.
    let hands = &bundle.tracks.hand_points;
    let rise: f64 = (0..3)
        .map(|a| f64::from(hands[[4, 0, a]] - hands[[0, 0, a]]) * up[a])
        .sum();
    assert!(rise > 0.01, "hand 1 rose {rise} m in the recording");
    // A world model can be built from it (what dm-fit / dm-sim start from).
    dm_model::WorldModel::from_bundle(&bundle, &dm_model::ModelOptions::default())
        .expect("model from the recorded bundle");
}

#[test]
fn issue9_frame_message_layout() {
    let tiny = common::tiny_model(true);
    let session = open_session(&tiny.model_dir, &PlayOptions::interactive()).expect("session");
    let sprites = session.sprites();
    assert_eq!(sprites.kind, "gaussian_splats");
    let bytes = encode_frame(&session);
    let word = |i: usize| u32::from_le_bytes(bytes[4 * i..4 * i + 4].try_into().expect("4 bytes"));
    assert_eq!(word(0), FRAME_MAGIC);
    assert_eq!(word(10), 2);
    assert_eq!(word(11) as usize, sprites.count);
    assert_eq!(bytes.len(), 4 * (FRAME_HEADER_WORDS + 3 * sprites.count));
    let x0 = f32::from_le_bytes(bytes[48..52].try_into().expect("4 bytes"));
    assert_eq!(x0, session.sprite_positions()[0]);
}

#[test]
fn issue9_bad_options_and_commands_are_errors() {
    let tiny = common::tiny_model(false);
    let bad = PlayOptions {
        grid: Some(4),
        ..PlayOptions::interactive()
    };
    let err = open_session(&tiny.model_dir, &bad).expect_err("grid 4 is refused");
    assert!(err.to_string().contains("--grid"), "{err}");
    let mut session = open_session(&tiny.model_dir, &PlayOptions::interactive()).expect("session");
    assert!(session.set_hand_velocity(2, [0.0; 3]).is_err());
    assert!(session.set_hand_velocity(0, [f64::NAN, 0.0, 0.0]).is_err());
    assert!(session.grab(0, usize::MAX).is_err());
    let missing = open_session(
        &tiny.dir.path().join("nothing"),
        &PlayOptions::interactive(),
    )
    .expect_err("missing model dir");
    assert!(missing.to_string().contains("model.json"), "{missing}");
}
