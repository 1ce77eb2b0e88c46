//! `--exact-hands`: the bundle's hand tracks are the scripted
//! anchors, every frame seen, and nothing else in the scene changes, so an
//! experiment with and without it isolates what the noisy drive costs.

use dm_bundle::Bundle;
use dm_synth::{Preset, SynthConfig, generate};

fn scene(dir: &std::path::Path, exact_hands: bool) -> (Bundle, dm_synth::TruthFile) {
    let config = SynthConfig {
        exact_hands,
        ..SynthConfig::tiny(Preset::Cloth, 11)
    };
    let name = if exact_hands { "exact" } else { "noisy" };
    let truth = generate(
        &config,
        &dir.join(name),
        &dir.join(format!("{name}.truth.json")),
        &mut |_, _, _| {},
    )
    .expect("scene");
    (Bundle::open(dir.join(name)).expect("bundle"), truth)
}

#[test]
fn exact_hands_records_the_scripted_anchors_and_changes_nothing_else() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (noisy, _) = scene(dir.path(), false);
    let (exact, truth) = scene(dir.path(), true);
    let fps = exact.meta.fps;
    let mut largest_noise: f64 = 0.0;
    for t in 0..exact.frame_count() {
        let scripted: Vec<[f64; 3]> = truth
            .hands
            .iter()
            .flat_map(|h| h.anchors_at(t as f64 / fps))
            .collect();
        for (j, anchor) in scripted.iter().enumerate() {
            assert!(exact.tracks.hand_visibility[[t, j]], "frame {t} anchor {j}");
            for a in 0..3 {
                // f32 storage of metre coordinates.
                let stored = f64::from(exact.tracks.hand_points[[t, j, a]]);
                assert!((stored - anchor[a]).abs() < 1e-6, "frame {t} anchor {j}");
                let noisy_value = f64::from(noisy.tracks.hand_points[[t, j, a]]);
                largest_noise = largest_noise.max((noisy_value - anchor[a]).abs());
            }
        }
    }
    // The default hands carry 3 mm of jitter per axis: the exact ones must
    // differ from them, or the option did nothing.
    assert!(largest_noise > 3e-3, "largest hand noise {largest_noise} m");
    assert_eq!(exact.tracks.object_points, noisy.tracks.object_points);
    assert_eq!(
        exact.tracks.object_visibility,
        noisy.tracks.object_visibility
    );
    assert_eq!(
        exact.particles.surface_points,
        noisy.particles.surface_points
    );
    assert_eq!(
        exact.particles.interior_points,
        noisy.particles.interior_points
    );
}
