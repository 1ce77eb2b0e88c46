//! Effects outside the diagnosis library (`wind`, `attractor`,
//! `anisotropic_drag`) hidden in dm-synth's truth: each moves the object
//! against its effect-free twin the way its parameters say, and the truth
//! file records what a diagnosis should recover.

use dm_bundle::Bundle;
use dm_synth::{EffectName, Preset, SynthConfig, TruthFile, generate};

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

/// Mean over tracked points of their last-frame shift against the twin.
fn mean_last_frame_shift(a: &Bundle, b: &Bundle) -> [f64; 3] {
    let (pa, pb) = (&a.tracks.object_points, &b.tracks.object_points);
    let last = pa.shape()[0] - 1;
    let n = pa.shape()[1];
    std::array::from_fn(|c| {
        (0..n)
            .map(|p| f64::from(pa[[last, p, c]] - pb[[last, p, c]]))
            .sum::<f64>()
            / n as f64
    })
}

fn param(truth: &TruthFile, key: &str) -> serde_json::Value {
    let effect = truth.effect.as_ref().expect("effect recorded");
    effect
        .params
        .get(key)
        .unwrap_or_else(|| panic!("{}: no `{key}` in {:?}", effect.name, effect.params))
        .clone()
}

#[test]
fn effects_outside_the_library_move_the_object_as_their_parameters_say() {
    let dir = tempfile::tempdir().expect("temp dir");
    let base = SynthConfig {
        action: Some(dm_synth::Action::Lift),
        ..SynthConfig::tiny(Preset::Toy, 9)
    };
    let (null, _) = scene(dir.path(), "null", &base);
    let hide = |spec: &str| SynthConfig {
        effect: Some(spec.parse().expect("effect")),
        ..base.clone()
    };

    let (wind, truth) = scene(dir.path(), "wind", &hide("wind:1.5"));
    assert_eq!(truth.effect.as_ref().map(|e| e.name.as_str()), Some("wind"));
    assert_eq!(param(&truth, "magnitude_m_s2"), serde_json::json!(1.5));
    let direction: [f64; 3] = serde_json::from_value(param(&truth, "direction")).expect("unit");
    let norm = direction.iter().map(|c| c * c).sum::<f64>().sqrt();
    assert!(
        (norm - 1.0).abs() < 1e-12 && direction[2] == 0.0,
        "{direction:?}"
    );
    let uniform = truth.physics.effects.force_field.uniform;
    assert!((0..3).all(|a| (uniform[a] - 1.5 * direction[a]).abs() < 1e-12));
    // The object drifts downwind: its mean shift points along the wind.
    let shift = mean_last_frame_shift(&wind, &null);
    let along: f64 = (0..3).map(|a| shift[a] * direction[a]).sum();
    let size = shift.iter().map(|c| c * c).sum::<f64>().sqrt();
    assert!(
        along > 0.002 && along > 0.7 * size,
        "wind shift {shift:?} against {direction:?}"
    );

    let (attracted, truth) = scene(dir.path(), "attractor", &hide("attractor:15"));
    assert_eq!(param(&truth, "stiffness_per_s2"), serde_json::json!(15.0));
    let point: [f64; 3] = serde_json::from_value(param(&truth, "point_m")).expect("point");
    assert_eq!(truth.physics.effects.force_field.attractor_point, point);
    // Pulled towards the point: the shift has a positive component towards
    // it from the object's centre.
    let (lo, hi) = Preset::Toy.bounds();
    let towards: [f64; 3] = std::array::from_fn(|a| point[a] - 0.5 * (lo[a] + hi[a]));
    let shift = mean_last_frame_shift(&attracted, &null);
    let along: f64 = (0..3).map(|a| shift[a] * towards[a]).sum();
    assert!(along > 0.0, "attractor shift {shift:?} against {towards:?}");

    let (dragged, truth) = scene(dir.path(), "drag", &hide("anisotropic_drag:30"));
    assert_eq!(param(&truth, "rate_per_s"), serde_json::json!(30.0));
    let axis = param(&truth, "axis").as_u64().expect("axis") as usize;
    let drag = truth.physics.effects.force_field.axis_drag;
    assert!(
        (0..3).all(|a| drag[a] == if a == axis { 30.0 } else { 0.0 }),
        "{drag:?}"
    );
    assert!(
        mean_last_frame_shift(&dragged, &null)
            .iter()
            .any(|c| c.abs() > 1e-4),
        "the drag changes the motion"
    );

    for name in EffectName::OUTSIDE_LIBRARY {
        assert!(!name.in_library(), "{}", name.name());
    }
}
