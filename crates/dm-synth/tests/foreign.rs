//! Foreign-physics scenes (`--engine mujoco`): MuJoCo simulates the truth,
//! the sensor model films it, and the bundle and truth file follow the
//! same contract as dm-synth's own scenes. Needs the Python named by
//! DM_MUJOCO_PYTHON (`make test` sets it to the setup venv's).

use dm_bundle::Bundle;
use dm_synth::{Engine, Preset, SynthConfig, TruthFile, generate};
use ndarray::Array3;

fn foreign(preset: Preset, seed: u64) -> SynthConfig {
    SynthConfig {
        engine: Engine::Mujoco,
        ..SynthConfig::tiny(preset, seed)
    }
}

fn scene(dir: &std::path::Path, name: &str, config: &SynthConfig) -> (Bundle, TruthFile) {
    let truth = generate(
        config,
        &dir.join(name),
        &dir.join(format!("{name}.truth.json")),
        &mut |_, _, _| {},
    )
    .unwrap_or_else(|e| panic!("{name}: {e}"));
    (Bundle::open(dir.join(name)).expect("bundle"), truth)
}

/// Largest distance between two point arrays of the same shape.
fn largest_difference(a: &Array3<f32>, b: &Array3<f32>) -> f32 {
    a.iter()
        .zip(b.iter())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn foreign_scenes_validate_move_and_repeat_bitwise() {
    let dir = tempfile::tempdir().expect("temp dir");
    for (preset, seed) in [(Preset::Rope, 3), (Preset::Cloth, 4), (Preset::Toy, 5)] {
        let config = foreign(preset, seed);
        let (bundle, truth) = scene(dir.path(), preset.name(), &config);
        bundle.validate_images().expect("images valid");
        assert_eq!(bundle.frame_count(), config.frames);
        let engine = truth.engine.as_ref().expect("engine record");
        assert_eq!(engine.engine, "mujoco");
        let dim = match preset {
            Preset::Rope => 1,
            Preset::Cloth => 2,
            Preset::Toy => 3,
        };
        assert_eq!(engine.flex_dim, dim);
        assert_eq!(truth.config.engine, Engine::Mujoco);
        assert!(truth.effect_displacement_m.is_none(), "no effect hidden");
        // The hand moves the object: the tracked points' mean travel over
        // the clip is well above the tracker's noise.
        let points = &bundle.tracks.object_points;
        let last = config.frames - 1;
        let travel: f64 = (0..points.shape()[1])
            .map(|n| {
                (0..3)
                    .map(|a| f64::from(points[[last, n, a]] - points[[0, n, a]]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .sum::<f64>()
            / points.shape()[1] as f64;
        assert!(travel > 0.005, "{preset:?}: tracks travel {travel} m");
    }
    // Seeded and deterministic: the same configuration gives the same bundle.
    let (first, _) = scene(dir.path(), "rope-again", &foreign(Preset::Rope, 3));
    let rope = Bundle::open(dir.path().join("rope")).expect("bundle");
    assert_eq!(
        largest_difference(&first.tracks.object_points, &rope.tracks.object_points),
        0.0
    );
}

#[test]
fn a_hidden_effect_reports_how_far_it_moves_the_object() {
    let dir = tempfile::tempdir().expect("temp dir");
    let null = foreign(Preset::Rope, 7);
    let tilted = SynthConfig {
        effect: Some("ground_tilt:10".parse().expect("effect")),
        ..null.clone()
    };
    let (null_bundle, _) = scene(dir.path(), "null", &null);
    let (tilted_bundle, truth) = scene(dir.path(), "tilted", &tilted);
    let effect = truth.effect.as_ref().expect("effect recorded");
    assert_eq!(effect.name, "ground_tilt");
    assert!(effect.params.contains_key("azimuth_deg"));
    let shift = truth.effect_displacement_m.expect("displacement reported");
    assert!(shift > 1e-4, "tilt moved the rope by {shift} m");
    assert!(
        largest_difference(
            &null_bundle.tracks.object_points,
            &tilted_bundle.tracks.object_points
        ) > 0.0
    );
}

#[test]
fn effects_the_engine_cannot_express_are_refused_before_anything_runs() {
    let dir = tempfile::tempdir().expect("temp dir");
    // A configuration MuJoCo cannot express is refused before anything runs.
    let plastic = SynthConfig {
        effect: Some("plasticity:0.03".parse().expect("effect")),
        ..foreign(Preset::Cloth, 1)
    };
    let err = generate(
        &plastic,
        &dir.path().join("plastic"),
        &dir.path().join("plastic.truth.json"),
        &mut |_, _, _| {},
    )
    .expect_err("plasticity is refused");
    assert!(err.to_string().contains("--effect"), "{err}");
    assert!(!dir.path().join("plastic").exists());
}

/// Mean of `points` over the particles marked in `which`.
fn centre_of(points: &[[f32; 3]], which: &[bool]) -> [f64; 3] {
    let chosen: Vec<&[f32; 3]> = points
        .iter()
        .zip(which)
        .filter(|(_, w)| **w)
        .map(|(p, _)| p)
        .collect();
    let n = chosen.len().max(1) as f64;
    std::array::from_fn(|a| chosen.iter().map(|p| f64::from(p[a])).sum::<f64>() / n)
}

#[test]
fn a_foreign_scene_is_a_plant_that_replays_its_clip_and_follows_a_planned_hand() {
    use dm_synth::foreign_plant::MujocoPlant;
    let dir = tempfile::tempdir().expect("temp dir");
    let config = foreign(Preset::Cloth, 6);
    let (_, truth) = scene(dir.path(), "cloth", &config);

    // Settled with no grip: at rest, on the floor.
    let mut plant = MujocoPlant::start(&truth, 1).expect("plant");
    let rest = plant.state().expect("state");
    assert_eq!(rest.x.len(), truth.truth_particles);
    let fastest = rest
        .v
        .iter()
        .map(|v| v.iter().map(|c| c * c).sum::<f32>().sqrt())
        .fold(0.0, f32::max);
    assert!(
        fastest < 0.05,
        "settled, yet a particle moves at {fastest} m/s"
    );

    // A planned hand grips a corner and lifts it 6 cm over 8 frames: the
    // particles near it rise with it, the far side stays down.
    let everywhere = vec![true; rest.x.len()];
    let centre = centre_of(&rest.x, &everywhere);
    let corner = rest
        .x
        .iter()
        .max_by(|a, b| (a[0] + a[1]).total_cmp(&(b[0] + b[1])))
        .map(|p| p.map(f64::from))
        .expect("a particle");
    let near = |p: &[f32; 3], to: [f64; 3], r: f64| {
        (0..3)
            .map(|a| (f64::from(p[a]) - to[a]).powi(2))
            .sum::<f64>()
            < r * r
    };
    let held: Vec<bool> = rest.x.iter().map(|p| near(p, corner, 0.015)).collect();
    let far_corner: [f64; 3] = std::array::from_fn(|a| 2.0 * centre[a] - corner[a]);
    let far: Vec<bool> = rest.x.iter().map(|p| near(p, far_corner, 0.03)).collect();
    assert!(held.iter().any(|h| *h) && far.iter().any(|f| *f));
    let frames = 8;
    for t in 0..frames {
        let at = |s: f64| [corner[0], corner[1], corner[2] + 0.06 * s / frames as f64];
        plant
            .step(&[at(t as f64)], &[at(t as f64 + 1.0)], &[t == 0])
            .expect("step");
    }
    let lifted = plant.state().expect("state");
    let rise = |which: &[bool]| centre_of(&lifted.x, which)[2] - centre_of(&rest.x, which)[2];
    assert!(
        (rise(&held) - 0.06).abs() < 0.015,
        "the gripped corner rose {} m for the hand's 0.06",
        rise(&held)
    );
    assert!(
        rise(&far).abs() < 0.01,
        "the far corner rose {} m",
        rise(&far)
    );

    // Let go, it falls back; a step with the wrong hand count is refused.
    plant.release().expect("release");
    for _ in 0..10 {
        plant.step_free().expect("free frame");
    }
    let dropped = plant.state().expect("state");
    assert!(centre_of(&dropped.x, &held)[2] < centre_of(&lifted.x, &held)[2] - 0.03);
    let error = plant
        .step(&[corner, corner], &[corner, corner], &[true, true])
        .expect_err("two hands in a one-hand plant");
    assert!(error.to_string().contains("hands"), "{error}");

    // Replaying the clip moves the object as the clip did (a fresh plant:
    // the scripted hands grip at the first replay).
    let mut replay = MujocoPlant::start(&truth, 1).expect("plant");
    for t in 0..config.frames - 1 {
        replay.replay(t).expect("replay");
    }
    let replayed = replay.state().expect("state");
    assert!(replayed.x.iter().flatten().all(|c| c.is_finite()));
    let moved = centre_of(&replayed.x, &everywhere);
    let travel = (0..3)
        .map(|a| (moved[a] - centre[a]).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(
        travel > 0.005,
        "the replayed clip moved the cloth {travel} m"
    );
}
