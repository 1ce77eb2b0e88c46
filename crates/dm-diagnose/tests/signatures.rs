//! Issue 6: each candidate's signature recovers a planted effect from
//! synthetic residual accelerations / tracks and stays quiet on noise.

use dm_diagnose::analysis::{AccelSample, Matched, main_axis};
use dm_diagnose::candidates::horizontal_basis;
use dm_diagnose::confidence;
use dm_diagnose::signatures::{best_shift, opposing_rate, signatures};

/// Deterministic pseudo-noise in [−1, 1] (no RNG needed for a fixed table).
fn noise(i: usize) -> f64 {
    ((i as f64 * 12.9898).sin() * 43758.5453).rem_euclid(1.0) * 2.0 - 1.0
}

/// Velocities spread in every direction, residual = −k v + noise.
fn drag_samples(k: f64, noise_amp: f64, floor_z: f64) -> Vec<AccelSample> {
    (0..600)
        .map(|i| {
            let v = [noise(3 * i), noise(3 * i + 1), 0.3 * noise(3 * i + 2)];
            AccelSample {
                frame: i / 20,
                track: i % 20,
                velocity: v,
                residual: [0, 1, 2].map(|a| -k * v[a] + noise_amp * noise(7 * i + a + 1000)),
                position: [noise(5 * i), noise(5 * i + 1), floor_z],
            }
        })
        .collect()
}

fn empty_matched() -> Matched {
    Matched {
        observed: vec![vec![Some([0.0; 3])]; 10],
        simulated: vec![vec![[0.0; 3]]; 10],
    }
}

fn sig(samples: &[AccelSample]) -> dm_diagnose::signatures::Signatures {
    let hand = vec![[0.0; 3]; 10];
    signatures(
        samples,
        &empty_matched(),
        &[0],
        &hand,
        [0.0, 0.0, 1.0],
        0.0,
        [1.0, 0.0, 0.0],
    )
}

#[test]
fn drag_signature_recovers_the_rate_and_ignores_noise() {
    let (k, t) = opposing_rate(
        &drag_samples(3.0, 0.5, 1.0)
            .iter()
            .map(|s| (s.velocity, s.residual))
            .collect::<Vec<_>>(),
    );
    assert!((k - 3.0).abs() < 0.1, "k = {k}");
    assert!(t > 20.0, "t = {t}");
    let s = sig(&drag_samples(0.0, 0.5, 1.0));
    assert!(s.drag_t.abs() < 3.0, "noise alone gives t = {}", s.drag_t);
}

#[test]
fn floor_friction_signature_only_counts_points_on_the_floor() {
    // Horizontal drag on points at the floor: the floor rate sees it.
    let on_floor = sig(&drag_samples(4.0, 0.5, 0.005));
    assert!(
        (on_floor.floor_rate_per_s - 4.0).abs() < 0.3,
        "{}",
        on_floor.floor_rate_per_s
    );
    assert!(on_floor.floor_t > 10.0);
    // The same residual 20 cm up: no floor samples, no floor signature.
    let above = sig(&drag_samples(4.0, 0.5, 0.2));
    assert_eq!(above.floor_rate_per_s, 0.0);
}

#[test]
fn tilt_signature_finds_a_constant_horizontal_acceleration() {
    let g_h = [0.6, -0.8, 0.0];
    let samples: Vec<AccelSample> = (0..400)
        .map(|i| AccelSample {
            frame: i / 20,
            track: i % 20,
            velocity: [noise(i), noise(i + 1), 0.0],
            residual: [0, 1, 2].map(|a| g_h[a] + 2.0 * noise(3 * i + a + 77)),
            position: [0.0, 0.0, 0.1],
        })
        .collect();
    let s = sig(&samples);
    assert!((s.horizontal_accel[0] - 0.6).abs() < 0.2 && (s.horizontal_accel[1] + 0.8).abs() < 0.2);
    assert!(s.horizontal_t > 5.0, "t = {}", s.horizontal_t);
    assert!(sig(&drag_samples(0.0, 2.0, 0.1)).horizontal_t < 3.0);
}

#[test]
fn density_signature_sees_sag_growing_along_the_axis() {
    let samples: Vec<AccelSample> = (0..400)
        .map(|i| {
            let x = noise(i) * 0.25;
            AccelSample {
                frame: i / 20,
                track: i % 20,
                velocity: [0.0; 3],
                residual: [
                    0.3 * noise(i + 9),
                    0.3 * noise(i + 19),
                    -4.0 * x + 0.5 * noise(i + 29),
                ],
                position: [x, 0.0, 0.1],
            }
        })
        .collect();
    let s = sig(&samples);
    assert!((s.sag_slope + 4.0).abs() < 0.5, "slope {}", s.sag_slope);
    assert!(s.sag_t.abs() > 10.0);
}

#[test]
fn lag_signature_finds_the_shift_of_the_hand_track() {
    // The object follows the true hand; the record lags it by 3 frames:
    // recorded(t) = true(t − 3), so the object at t matches recorded(t + 3).
    let truth = |t: f64| [0.1 * (t / 6.0).sin(), 0.05 * t / 30.0, 0.0];
    let object: Vec<[f64; 3]> = (0..40).map(|t| truth(t as f64)).collect();
    let recorded: Vec<[f64; 3]> = (0..40).map(|t| truth(t as f64 - 3.0)).collect();
    assert!((best_shift(&object, &recorded, 6.0) - 3.0).abs() <= 0.25);
    assert!(best_shift(&object, &object, 6.0).abs() <= 0.25);
}

#[test]
fn confidence_and_geometry_helpers() {
    // Named: a clear winner far above the threshold is confident; a tie is not.
    assert!(confidence(0.5, 0.0, 0.1) > 0.9);
    assert!(confidence(0.5, 0.5, 0.1) <= 0.5);
    // None: nothing explained is a confident `none`.
    assert!(confidence(0.0, 0.0, 0.1) > 0.99);
    let (e, n) = horizontal_basis([0.0, 0.0, 1.0]);
    assert_eq!((e, n), ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]));
    let axis = main_axis(
        &(0..50)
            .map(|i| [i as f64 * 0.01, 0.001 * noise(i), 0.0])
            .collect::<Vec<_>>(),
    );
    assert!(axis[0].abs() > 0.99);
}
