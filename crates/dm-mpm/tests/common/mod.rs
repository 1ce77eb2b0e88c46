//! Helpers shared by the dm-mpm test crates (random matrices, scenes).
#![allow(dead_code)] // each test crate uses a different subset

use dm_mpm::real::{Mat3, Real, Vec3};
use nalgebra::{Quaternion, UnitQuaternion};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

/// Uniform in `[lo, hi)`.
pub fn uniform(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * rng.random::<f64>()
}

/// A uniformly distributed proper rotation (unit quaternion by rejection).
pub fn random_rotation(rng: &mut ChaCha8Rng) -> Mat3<f64> {
    loop {
        let q = [0; 4].map(|_| uniform(rng, -1.0, 1.0));
        let n2: f64 = q.iter().map(|c| c * c).sum();
        if (0.01..=1.0).contains(&n2) {
            let q = UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]));
            return q.to_rotation_matrix().into_inner();
        }
    }
}

/// `Q1 diag(sigma) Q2ᵀ` with random rotations: known singular values.
pub fn with_singular_values(rng: &mut ChaCha8Rng, sigma: [f64; 3]) -> Mat3<f64> {
    let q1 = random_rotation(rng);
    let q2 = random_rotation(rng);
    q1 * Mat3::from_diagonal(&Vec3::new(sigma[0], sigma[1], sigma[2])) * q2.transpose()
}

/// A random deformation gradient with singular values in `[lo, hi]`, det > 0.
pub fn random_f(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> Mat3<f64> {
    let s = [0; 3].map(|_| uniform(rng, lo, hi));
    with_singular_values(rng, s)
}

/// Largest absolute entry of `a - b` over the largest absolute entry of `b`
/// (a relative error that does not blow up on near-zero entries).
pub fn rel_err<T: Real>(a: &Mat3<T>, b: &Mat3<T>) -> f64 {
    let diff = (a - b).amax().to_f64();
    let scale = b.amax().to_f64().max(f64::MIN_POSITIVE);
    diff / scale
}

/// Regular lattice of points with spacing `h` filling `[lo, hi]` (cell centred).
pub fn lattice(lo: [f64; 3], hi: [f64; 3], h: f64) -> Vec<[f64; 3]> {
    let n = [0, 1, 2].map(|a| ((hi[a] - lo[a]) / h).round().max(1.0) as usize);
    let mut out = Vec::with_capacity(n[0] * n[1] * n[2]);
    for i in 0..n[0] {
        for j in 0..n[1] {
            for k in 0..n[2] {
                let idx = [i, j, k];
                out.push([0, 1, 2].map(|a| lo[a] + (idx[a] as f64 + 0.5) * h));
            }
        }
    }
    out
}

/// Lattice with every point jittered by up to `jitter * h` per axis.
pub fn jittered_lattice(
    rng: &mut ChaCha8Rng,
    lo: [f64; 3],
    hi: [f64; 3],
    h: f64,
    jitter: f64,
) -> Vec<[f64; 3]> {
    lattice(lo, hi, h)
        .into_iter()
        .map(|p| p.map(|c| c + jitter * h * uniform(rng, -1.0, 1.0)))
        .collect()
}

/// Axis-aligned bounding box of points: (min, max).
pub fn bounds(points: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    (lo, hi)
}

pub fn mean(points: &[[f64; 3]]) -> [f64; 3] {
    let mut m = [0.0; 3];
    for p in points {
        for a in 0..3 {
            m[a] += p[a] / points.len() as f64;
        }
    }
    m
}

use dm_mpm::{ActuatorConfig, ParticleMaterial, PhysicsConfig, World};

/// Grid cells per axis of the floor scenes.
pub const FLOOR_GRID: usize = 32;
/// Cells between the bottom face of the domain and the floor plane z = 0
/// (3 wall cells plus 2 spare).
pub const FLOOR_CELLS_ABOVE_BOTTOM: f64 = 5.0;

/// Volumetric defaults in a 1 m cube centred on the z axis, floor z = 0
/// five cells above the bottom face, gravity -z.
pub fn floor_config() -> PhysicsConfig {
    let dx = 1.0 / FLOOR_GRID as f64;
    let mut c = PhysicsConfig::volumetric(
        [-0.5, -0.5, -FLOOR_CELLS_ABOVE_BOTTOM * dx],
        1.0,
        [0.0, 0.0, 1.0],
    );
    c.grid_res = FLOOR_GRID;
    c
}

/// Volumetric defaults in the unit cube with no floor and no damping, for
/// scenes whose answer is known in closed form (free flight, drag, momentum).
pub fn free_space_config() -> PhysicsConfig {
    let mut c = PhysicsConfig::volumetric([0.0; 3], 1.0, [0.0, 0.0, 1.0]);
    c.grid_res = FLOOR_GRID;
    c.floor = None;
    c.particle_damping = 0.0;
    c.grid_damping = 1.0;
    c
}

/// A world of a lattice block (2 particles per cell per axis) with one
/// uniform material.
pub fn block_world<T: dm_mpm::Real>(
    config: PhysicsConfig,
    positions: &[[f64; 3]],
    youngs: f64,
    poisson: f64,
    weights: [f64; 3],
    actuators: ActuatorConfig,
) -> World<T> {
    let h = config.dx() / 2.0;
    let material = ParticleMaterial::uniform(positions.len(), youngs, poisson, weights);
    World::new(config, positions, h * h * h, material, actuators).expect("valid world")
}
