//! Reference scenes shared by benchmarks and validation tests.

use crate::SimError;
use crate::actuators::ActuatorConfig;
use crate::config::PhysicsConfig;
use crate::material::ParticleMaterial;
use crate::real::Real;
use crate::world::World;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Which constitutive model the benchmark block uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BenchExperts {
    /// A single Neo-Hookean expert.
    NeoHookean,
    /// The three-expert mixture with fixed weights (0.5, 0.3, 0.2).
    Mixture,
}

/// The block our peer measurements use: `n` particles uniformly
/// random in [0.35,0.65]×[0.15,0.45]×[0.35,0.65] of the unit domain,
/// initial velocity (0.3, −1.5, 0) m/s plus a rotation about the block's
/// centre (2 rad/s about z) and a uniform compression (rate 1/s),
/// E = 400 Pa, ν = 0.2, density 1, dt 8e-4 on a 32³ grid (shorter in
/// proportion to the cell on finer grids, so the wave's Courant number
/// stays that of 32³), gravity −y, 3-cell walls, no floor.
pub fn bench_block<T: Real>(
    particles: usize,
    grid_res: usize,
    experts: BenchExperts,
    seed: u64,
) -> Result<World<T>, SimError> {
    bench_block_frames(particles, grid_res, experts, seed, 42)
}

/// [`bench_block`] with `substeps_per_frame` substeps in a frame (the
/// gradient benchmark differentiates one frame of exactly its window).
pub fn bench_block_frames<T: Real>(
    particles: usize,
    grid_res: usize,
    experts: BenchExperts,
    seed: u64,
    substeps_per_frame: usize,
) -> Result<World<T>, SimError> {
    let mut config = PhysicsConfig::volumetric([0.0; 3], 1.0, [0.0, 1.0, 0.0]);
    config.substeps_per_frame = substeps_per_frame;
    config.grid_res = grid_res;
    config.floor = None;
    config.particle_damping = 0.0;
    config.grid_damping = 1.0;
    config.density = 1.0;
    config.cfl = None; // the peers' fixed-step configuration
    config.dt = 8e-4 * 32.0 / grid_res as f64;
    config.gravity = [0.0, -9.8, 0.0];
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let lo = [0.35, 0.15, 0.35];
    let centre = [0.5, 0.3, 0.5];
    let positions: Vec<[f64; 3]> = (0..particles)
        .map(|_| [0, 1, 2].map(|a| lo[a] + 0.3 * rng.random::<f64>()))
        .collect();
    let velocities: Vec<[f64; 3]> = positions
        .iter()
        .map(|p| {
            let r = [p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]];
            let (spin, squeeze) = (2.0, 1.0);
            [
                0.3 - spin * r[1] - squeeze * r[0],
                -1.5 + spin * r[0] - squeeze * r[1],
                -squeeze * r[2],
            ]
        })
        .collect();
    let weights = match experts {
        BenchExperts::NeoHookean => [1.0, 0.0, 0.0],
        BenchExperts::Mixture => [0.5, 0.3, 0.2],
    };
    let material = ParticleMaterial::uniform(particles, 400.0, 0.2, weights);
    let dx = 1.0 / grid_res as f64;
    let volume = (0.5 * dx).powi(3);
    let mut world = World::new(
        config,
        &positions,
        volume,
        material,
        ActuatorConfig::default(),
    )?;
    world.set_velocities(&velocities)?;
    Ok(world)
}
