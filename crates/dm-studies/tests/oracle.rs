//! The oracle reads a dm-synth truth file's hidden effect as the library
//! candidate carrying it, in the candidate's terms.

use dm_diagnose::candidates::{Candidate, apply};
use dm_model::{ModelOptions, ResidualKind, WorldModel};
use dm_studies::oracle::truth_candidate;
use dm_synth::{Preset, SynthConfig};

/// A tiny cloth scene under `dir` (`scene/`, `truth.json`), with `effect`
/// hidden in its truth, and the model `--residual none` would start from.
fn tiny_cloth_model_with(dir: &std::path::Path, effect: Option<&str>) -> WorldModel {
    let scene = dir.join("scene");
    let mut config = SynthConfig::tiny(Preset::Cloth, 7);
    config.effect = effect.map(|e| e.parse().expect("effect spec"));
    dm_synth::generate(&config, &scene, &dir.join("truth.json"), &mut |_, _, _| {}).expect("scene");
    let bundle = dm_bundle::Bundle::open(&scene).expect("bundle");
    let options = ModelOptions {
        residual: ResidualKind::None,
        ..ModelOptions::default()
    };
    WorldModel::from_bundle(&bundle, &options).expect("model")
}

/// Gravity read back through the candidate's tilt and azimuth: acos and
/// atan2 round-trips in f64 lose a few ulps of a 9.8 m/s² vector.
const GRAVITY_RTOL: f64 = 1e-9;
/// The density factors against dm-synth's formula evaluated on the same
/// particles: both are 1 + a·s in f64, s the normalised coordinate, so only
/// rounding separates them.
const DENSITY_FACTOR_ATOL: f64 = 1e-9;

/// The oracle fit starts from the truth's effect in the
/// candidate's terms: the tilt gives back the truth's gravity, the density
/// gradient its axis and heavy end, the lag its frames; a scene without an
/// effect is refused, naming the field.
#[test]
fn oracle_reads_the_truth_effect_as_its_candidate() {
    let fps = 30.0;
    // A tiny cloth with `effect` hidden: its model, its truth file, and
    // what the oracle reads from the truth.
    let read = |effect: Option<&str>| {
        let dir = tempfile::tempdir().expect("temp dir");
        let model = tiny_cloth_model_with(dir.path(), effect);
        let path = dir.path().join("truth.json");
        let truth: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&path).expect("truth"))
                .expect("truth JSON");
        let read = truth_candidate(&truth, &model, fps, &path);
        (model, truth, read)
    };

    let (model, truth, read_back) = read(Some("ground_tilt:7.5"));
    let (candidate, params) = read_back.expect("tilt");
    assert_eq!(candidate, Candidate::GroundTilt);
    assert!((params["tilt_deg"] - 7.5).abs() < 1e-9, "{params:?}");
    let tilted = apply(&model, candidate, &params);
    let g: Vec<f64> = truth["effect"]["params"]["gravity"]
        .as_array()
        .expect("gravity")
        .iter()
        .map(|v| v.as_f64().expect("number"))
        .collect();
    for a in 0..3 {
        assert!(
            (tilted.physics.gravity[a] - g[a]).abs() < GRAVITY_RTOL * 9.8,
            "gravity {:?} against the truth's {g:?}",
            tilted.physics.gravity
        );
    }

    let (model, truth, read_back) = read(Some("density_variation:3"));
    let (candidate, params) = read_back.expect("density");
    assert_eq!(candidate, Candidate::DensityVariation);
    assert_eq!(params["heavy_end_excess"], 3.0);
    let graded = apply(&model, candidate, &params);
    let factors = graded
        .extension
        .density_factors(&graded.particles)
        .expect("a gradient");
    // dm-synth's truth (truth.rs): factor 1 + a·s along coordinate `axis`,
    // s rising from 0 at the lowest particle to 1 at the highest, or the
    // reverse when the heavy end is at the minimum.
    let axis = truth["effect"]["params"]["axis"].as_u64().expect("axis") as usize;
    let heavy_at_max = truth["effect"]["params"]["heavy_at_max"]
        .as_bool()
        .expect("heavy end");
    let coords: Vec<f64> = graded.particles.iter().map(|p| p[axis]).collect();
    let lo = coords.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = coords.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    for (c, f) in coords.iter().zip(&factors) {
        let s = (c - lo) / (hi - lo);
        let expected = 1.0 + 3.0 * if heavy_at_max { s } else { 1.0 - s };
        assert!(
            (f - expected).abs() < DENSITY_FACTOR_ATOL,
            "factor {f} where dm-synth's formula gives {expected}"
        );
    }

    let (_, _, read_back) = read(Some("actuator_lag:0.1"));
    let (candidate, params) = read_back.expect("lag");
    assert_eq!(candidate, Candidate::ActuatorLag);
    assert!((params["lag_frames"] - 3.0).abs() < 1e-9, "{params:?}");

    let (_, _, read_back) = read(None);
    let error = read_back.expect_err("no effect to read").to_string();
    assert!(
        error.contains("truth.json") && error.contains("`effect`"),
        "{error}"
    );
}
