//! Issue 9: the playground session through its API (no browser): grabbing
//! and moving a hand moves the object, a soft material under a strong
//! two-hand pull tears it, a recording is a valid scene bundle, and the
//! frame message carries the sprites.

mod common;

use dm_play::{
    FRAME_HEADER_WORDS, FRAME_MAGIC, MaterialControl, PlayOptions, Session, component_sizes,
    encode_frame, open_session,
};

/// Pieces of fewer particles than this are strays, not a torn-off part.
const MIN_PIECE: usize = 20;

fn link(session: &Session) -> f64 {
    2.0 * session.view().particle_spacing
}

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

/// The two ends of the object along the main view's right direction.
fn ends(session: &Session) -> ([f64; 3], [f64; 3]) {
    let right = session.view().main_right();
    let along = |p: &[f32; 3]| (0..3).map(|a| f64::from(p[a]) * right[a]).sum::<f64>();
    let positions = session.positions();
    let lo = positions
        .iter()
        .min_by(|a, b| along(a).total_cmp(&along(b)))
        .expect("particles");
    let hi = positions
        .iter()
        .max_by(|a, b| along(a).total_cmp(&along(b)))
        .expect("particles");
    let c = session.view().centre;
    // Halfway between the centre and each end: well inside the object.
    let mid = |p: &[f32; 3]| [0, 1, 2].map(|a| 0.5 * (c[a] + f64::from(p[a])));
    (mid(lo), mid(hi))
}

#[test]
fn grab_and_move_a_hand_moves_the_object() {
    let tiny = common::tiny_model(false);
    let mut session = open_session(&tiny.model_dir, &PlayOptions::interactive()).expect("session");
    let up = session.view().up;
    let start = session.state().centroid;
    let centre = session.view().centre;
    grab_near(&mut session, 0, centre);
    session
        .set_hand_velocity(0, up.map(|c| 0.3 * c))
        .expect("velocity");
    for _ in 0..12 {
        session.step().expect("step");
    }
    let state = session.state();
    assert!(state.grasped_particles[0] > 0, "{state:?}");
    assert_eq!(state.grasped_particles[1], 0);
    let lift: f64 = (0..3).map(|a| (state.centroid[a] - start[a]) * up[a]).sum();
    // The hand rose 0.3 m/s × 12 frames × 33.6 ms ≈ 12 cm; the object, held
    // at one point, must follow by a good part of that.
    assert!(lift > 0.02, "centroid rose only {lift} m: {state:?}");

    // Released, the object falls back (gravity) instead of following.
    session.release(0).expect("release");
    assert_eq!(session.state().grasped_particles[0], 0);
    session.reset().expect("reset");
    assert_eq!(session.state().frame, 0);
    assert_eq!(session.state().centroid, start);
}

#[test]
fn pick_misses_off_the_object() {
    let tiny = common::tiny_model(false);
    let session = open_session(&tiny.model_dir, &PlayOptions::interactive()).expect("session");
    let up = session.view().up;
    let right = session.view().main_right();
    let far = [0, 1, 2].map(|a| session.view().centre[a] + 3.0 * session.view().extent * right[a]);
    let origin = [0, 1, 2].map(|a| far[a] + up[a]);
    assert_eq!(session.pick(origin, up.map(|c| -c)), None);
    assert_eq!(session.pick(origin, [0.0; 3]), None);
}

/// Pulls the object apart with both hands at `speed` (m/s) for `frames`
/// frames at Young's-modulus scale `e_scale`; returns the piece sizes
/// before and after.
fn pull_apart(e_scale: f64, speed: f64, frames: usize) -> (Vec<usize>, Vec<usize>, Session) {
    let tiny = common::tiny_model(false);
    let mut session = open_session(&tiny.model_dir, &PlayOptions::interactive()).expect("session");
    let before = component_sizes(session.positions(), link(&session), MIN_PIECE);
    let damping = session.material().damping;
    session
        .set_material(MaterialControl {
            e_scale,
            nu: None,
            damping,
        })
        .expect("material");
    let (left, right_end) = ends(&session);
    grab_near(&mut session, 0, left);
    grab_near(&mut session, 1, right_end);
    let right = session.view().main_right();
    session
        .set_hand_velocity(0, right.map(|c| -speed * c))
        .expect("velocity");
    session
        .set_hand_velocity(1, right.map(|c| speed * c))
        .expect("velocity");
    for _ in 0..frames {
        session.step().expect("the pull must stay stable");
    }
    let after = component_sizes(session.positions(), link(&session), MIN_PIECE);
    (before, after, session)
}

#[test]
fn a_strong_pull_tears_the_object() {
    // The same two-hand pull (each hand 0.3 m/s outwards for 10 frames,
    // 20 cm of stretch on a 22 cm toy) at E x0.3 and E x3. Under this much
    // stretch the rigid grip patches pull out of the object at any E (the
    // deformation gradient is clamped at 2x stretch, which caps the stress
    // a particle can carry): one piece at rest, three after, and the stiff
    // object's body stays whole: its main piece keeps every particle the
    // hands do not hold. (Measured since grid damping became a rate:
    // [708, 46, 42] at E x0.1, x0.3 and x1 and [709, 46, 42] at x3, for
    // pulls of 0.3-0.5 m/s and particle damping 0 or 5 /s; on the scene of
    // the truth with room to its walls (dm-synth TRUTH_VERSION 2), whose
    // fit grasps 69 + 57 particles, [675, 62, 51] at x0.3 and x3. With the
    // damping per CFL substep, which damped a soft object less, E x0.3 also
    // lost a 17-particle chunk of its body: [674, 63, 45] against
    // [737, 45] at E x3.)
    let (soft_before, soft, soft_session) = pull_apart(0.3, 0.3, 10);
    let (_, stiff, stiff_session) = pull_apart(3.0, 0.3, 10);
    eprintln!("pieces at rest {soft_before:?}; pulled: E x0.3 {soft:?}, E x3 {stiff:?}");
    assert_eq!(soft_before.len(), 1, "one piece at rest: {soft_before:?}");
    let n = soft_session.positions().len();
    let held: usize = stiff_session.state().grasped_particles.iter().sum();
    assert!(
        soft.len() >= 3 && stiff.len() >= 2,
        "both grips should pull out of the soft object, one at least out of the stiff one: \
         E x0.3 {soft:?}, E x3 {stiff:?}"
    );
    let main = |pieces: &[usize]| pieces.first().copied().unwrap_or(0);
    // Stray particles at the torn edges belong to no piece of MIN_PIECE or
    // more (12 of 800 here); a lost chunk of the body is more than this.
    let stray_allowance = n / 50;
    assert!(
        main(&stiff) + held + stray_allowance >= n && main(&soft) <= main(&stiff),
        "main piece: E x0.3 {soft:?}, E x3 {stiff:?}, {held} of {n} particles held ({:?})",
        soft_session.state()
    );
}

#[test]
fn recording_is_a_valid_bundle() {
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
fn frame_message_layout() {
    let tiny = common::tiny_model(true);
    let session = open_session(&tiny.model_dir, &PlayOptions::interactive()).expect("session");
    let sprites = session.sprites();
    assert_eq!(sprites.kind, "gaussian_splats");
    let bytes = encode_frame(&session);
    let word = |i: usize| u32::from_le_bytes(bytes[4 * i..4 * i + 4].try_into().expect("4 bytes"));
    assert_eq!(word(0), FRAME_MAGIC);
    assert_eq!(word(11) as usize, sprites.count);
    assert_eq!(bytes.len(), 4 * (FRAME_HEADER_WORDS + 3 * sprites.count));
    let x0 = f32::from_le_bytes(bytes[48..52].try_into().expect("4 bytes"));
    assert_eq!(x0, session.sprite_positions()[0]);
}

#[test]
fn bad_options_and_commands_are_errors() {
    let tiny = common::tiny_model(false);
    let bad = PlayOptions {
        grid: Some(4),
        ..PlayOptions::interactive()
    };
    let err = open_session(&tiny.model_dir, &bad).expect_err("grid 4 is refused");
    assert!(err.to_string().contains("--grid"), "{err}");
    let bad = PlayOptions {
        cfl: Some(0.0),
        ..PlayOptions::interactive()
    };
    let err = open_session(&tiny.model_dir, &bad).expect_err("cfl 0 is refused");
    assert!(err.to_string().contains("--cfl"), "{err}");
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
