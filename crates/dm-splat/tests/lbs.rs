//! The LBS bridge reproduces rigid motions exactly (to round-off).

mod common;

use common::{random_gaussians, random_quat, rng, uniform};
use dm_splat::SplatError;
use dm_splat::gaussians::{normalize_quat, quat_to_matrix};
use dm_splat::lbs::{LBS_NEIGHBORS, LbsBridge};
use nalgebra::{Matrix3, Vector3};

/// Procrustes by SVD recovers a rotation to ~1e-15 relative; the skinned
/// mean sums 16 terms of O(0.1 m): errors ~1e-15 m. Three chained frames
/// and an f64 quaternion product keep it far below this.
const RIGID_TOL: f64 = 1e-12;

fn particles(n: usize, seed: u64) -> Vec<[f64; 3]> {
    let mut r = rng(seed);
    (0..n)
        .map(|_| [0; 3].map(|_| uniform(&mut r, -0.15, 0.15)))
        .collect()
}

fn rigid(seed: u64) -> (Matrix3<f64>, Vector3<f64>) {
    let mut r = rng(seed);
    let (q, _) = normalize_quat(&random_quat(&mut r));
    let t = Vector3::from_fn(|_, _| uniform(&mut r, -0.3, 0.3));
    (quat_to_matrix(&q), t)
}

#[test]
fn lbs_reproduces_a_rigid_motion_exactly() {
    let mut positions = particles(600, 1);
    let mut gaussians = random_gaussians(&mut rng(2), 300, (0.3, 0.9));
    let original = gaussians.clone();
    let mut bridge = LbsBridge::new(&positions, LBS_NEIGHBORS).expect("bind");
    let (mut total_r, mut total_t) = (Matrix3::identity(), Vector3::zeros());
    for frame in 0..3 {
        let (r, t) = rigid(10 + frame);
        positions = positions
            .iter()
            .map(|p| {
                let q = r * Vector3::from(*p) + t;
                [q.x, q.y, q.z]
            })
            .collect();
        bridge.advance(&mut gaussians, &positions).expect("advance");
        total_r = r * total_r;
        total_t = r * total_t + t;
    }
    let mut worst = 0.0f64;
    for i in 0..gaussians.len() {
        let expected_mean = total_r * original.means[i] + total_t;
        worst = worst.max((gaussians.means[i] - expected_mean).amax());
        let (q0, _) = normalize_quat(&original.rotations[i]);
        let expected_rot = total_r * quat_to_matrix(&q0);
        let (q1, _) = normalize_quat(&gaussians.rotations[i]);
        worst = worst.max((quat_to_matrix(&q1) - expected_rot).amax());
        // Scales, opacities and colours are untouched.
        assert_eq!(gaussians.log_scales[i], original.log_scales[i]);
        assert_eq!(gaussians.opacity_logits[i], original.opacity_logits[i]);
        assert_eq!(gaussians.colors[i], original.colors[i]);
    }
    println!("LBS rigid motion: max error {worst:.2e}");
    assert!(worst <= RIGID_TOL, "max error {worst:e}");
}

#[test]
fn lbs_follows_a_stretch_smoothly() {
    // Non-rigid: stretch x by 10 %. Gaussians inside the cloud move by about
    // the local displacement (no exactness claim, just sanity).
    let positions = particles(800, 3);
    let mut gaussians = random_gaussians(&mut rng(4), 100, (0.3, 0.9));
    for m in gaussians.means.iter_mut() {
        *m *= 0.5; // well inside the particle cloud
    }
    let before = gaussians.clone();
    let mut bridge = LbsBridge::new(&positions, LBS_NEIGHBORS).expect("bind");
    let stretched: Vec<[f64; 3]> = positions.iter().map(|p| [1.1 * p[0], p[1], p[2]]).collect();
    bridge.advance(&mut gaussians, &stretched).expect("advance");
    for i in 0..gaussians.len() {
        let expected_x = 1.1 * before.means[i].x;
        assert!(
            (gaussians.means[i].x - expected_x).abs() < 2e-3,
            "Gaussian {i}"
        );
        // Procrustes of a stretched, irregular neighbourhood is a small
        // rotation, not exactly the identity: y moves a little too.
        assert!((gaussians.means[i].y - before.means[i].y).abs() < 2e-3);
    }
}

#[test]
fn lbs_rejects_bad_particles() {
    let positions = particles(50, 5);
    assert!(matches!(LbsBridge::new(&[], 16), Err(SplatError::Lbs(_))));
    let mut bridge = LbsBridge::new(&positions, 16).expect("bind");
    let mut g = random_gaussians(&mut rng(6), 5, (0.3, 0.9));
    assert!(matches!(
        bridge.advance(&mut g, &positions[..49]),
        Err(SplatError::Lbs(_))
    ));
    let mut bad = positions.clone();
    bad[7][1] = f64::NAN;
    assert!(matches!(
        bridge.advance(&mut g, &bad),
        Err(SplatError::Lbs(_))
    ));
}
