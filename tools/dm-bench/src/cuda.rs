//! GPU measurements: substep throughput on the reference block and
//! parity of the CUDA world against the CPU world.

use anyhow::{Context, Result, bail};
use dm_cuda::{CudaDevice, CudaWorld, DeviceReal};
use dm_mpm::scenes::{BenchExperts, bench_block};
use dm_mpm::{ActuatorConfig, ActuatorMode, FloorConfig, ParticleMaterial, PhysicsConfig, World};
use rand::{RngExt, SeedableRng};
use std::sync::Arc;
use std::time::Instant;

/// `dm-bench mpm --device cuda`: `substeps` substeps timed `repeats`
/// times after 20 warm-up substeps; prints the median throughput and
/// the spread.
pub fn mpm_throughput(
    particles: usize,
    grid: usize,
    experts: BenchExperts,
    substeps: usize,
    repeats: usize,
) -> Result<()> {
    let device = CudaDevice::open(0)?;
    let world =
        bench_block::<f32>(particles, grid, experts, 0).context("building the benchmark block")?;
    let compile = Instant::now();
    let mut world = CudaWorld::new(world, device.clone())?;
    let compile_s = compile.elapsed().as_secs_f64();
    world.substeps_unchecked(20)?;
    world.finish()?;
    let mut rates = Vec::new();
    for _ in 0..repeats.max(1) {
        let start = Instant::now();
        world.substeps_unchecked(substeps)?;
        world.finish()?;
        rates.push((particles * substeps) as f64 / start.elapsed().as_secs_f64());
    }
    rates.sort_by(f64::total_cmp);
    world.time_stages(true);
    world.substeps_unchecked(substeps.min(100))?;
    world.finish()?;
    if let Some(stages) = world.stage_seconds() {
        let per = |s: f64| 1e3 * s / substeps.min(100) as f64;
        eprintln!(
            "# ms per substep, each stage waited for: cell sort {:.4}, p2g (with stress) {:.4}, grid update {:.4}, g2p {:.4}",
            per(stages.schedule),
            per(stages.p2g),
            per(stages.grid_update),
            per(stages.g2p)
        );
    }
    println!("particle_substeps_per_s {:.4e}", rates[rates.len() / 2]);
    eprintln!(
        "# {particles} particles, grid {grid}^3, {experts:?}, {substeps} substeps x {} runs on {} ({}): \
         min {:.4e}, max {:.4e}; start (NVRTC + upload) {compile_s:.2} s",
        rates.len(),
        device.name(),
        device.arch(),
        rates[0],
        rates[rates.len() - 1],
    );
    Ok(())
}

/// A parity scene: what the CUDA world must reproduce.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ParityScene {
    /// A block on a frictional floor with air drag, per-particle expert
    /// mixtures, grasped by two compliant hands that lift and pull it.
    Hands,
    /// The reference block (three-expert mixture) with plastic yield,
    /// held by one rigid hand.
    Plastic,
}

fn parity_world<T: DeviceReal>(scene: ParityScene, particles: usize) -> Result<World<T>> {
    let mut config = PhysicsConfig::volumetric([0.0; 3], 1.0, [0.0, 1.0, 0.0]);
    config.grid_res = 32;
    config.floor = Some(FloorConfig {
        up: [0.0, 1.0, 0.0],
        height: 0.1,
        margin: 0.0,
    });
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let (lo, size) = ([0.35, 0.11, 0.4], [0.3, 0.12, 0.2]);
    let positions: Vec<[f64; 3]> = (0..particles)
        .map(|_| [0, 1, 2].map(|a| lo[a] + size[a] * rng.random::<f64>()))
        .collect();
    let (youngs, weights, actuators): (Vec<f64>, Vec<[f64; 3]>, ActuatorConfig) = match scene {
        ParityScene::Hands => {
            config.effects.floor_friction = 0.4;
            config.effects.air_drag_linear = 0.5;
            config.effects.air_drag_quadratic = 0.2;
            let youngs = (0..particles)
                .map(|_| 2e4 + 6e4 * rng.random::<f64>())
                .collect();
            let weights = (0..particles)
                .map(|_| {
                    let w = [0, 1, 2].map(|_| 0.05 + rng.random::<f64>());
                    let s: f64 = w.iter().sum();
                    w.map(|x| x / s)
                })
                .collect();
            (youngs, weights, ActuatorConfig::default())
        }
        ParityScene::Plastic => {
            config.effects.plastic_yield = Some(0.05);
            let actuators = ActuatorConfig {
                mode: ActuatorMode::Rigid,
                ..ActuatorConfig::default()
            };
            (
                vec![5e4; particles],
                vec![[0.5, 0.3, 0.2]; particles],
                actuators,
            )
        }
    };
    let poisson = vec![0.3; particles];
    let material = ParticleMaterial::from_fields(&youngs, &poisson, &weights);
    let volume = (0.5 * config.dx()).powi(3);
    Ok(World::new(config, &positions, volume, material, actuators)?)
}

/// The anchors of `frame`: the hands close on the block's ends, then lift
/// and pull it apart.
fn parity_anchors(scene: ParityScene, frame: usize) -> (Vec<[f64; 3]>, Vec<[f64; 3]>, Vec<bool>) {
    let at = |f: usize| -> Vec<[f64; 3]> {
        let t = f as f64 * 0.01;
        match scene {
            ParityScene::Hands => vec![
                [0.36 - 0.5 * t, 0.2 + t, 0.5],
                [0.64 + 0.5 * t, 0.2 + t, 0.5],
            ],
            ParityScene::Plastic => vec![[0.36 - t, 0.2 + 2.0 * t, 0.5]],
        }
    };
    let from = at(frame);
    let active = vec![true; from.len()];
    (from, at(frame + 1), active)
}

/// Largest position and F differences between the two worlds.
fn compare<T: DeviceReal>(cpu: &World<T>, gpu: &mut CudaWorld<T>) -> Result<(f64, f64)> {
    let gpu_state = gpu.state()?;
    let cpu_state = cpu.state();
    let dx = cpu_state
        .x
        .iter()
        .zip(&gpu_state.x)
        .map(|(a, b)| (a - b).norm().to_f64())
        .fold(0.0, f64::max);
    let df = cpu_state
        .f
        .iter()
        .zip(&gpu_state.f)
        .map(|(a, b)| (a - b).norm().to_f64())
        .fold(0.0, f64::max);
    Ok((dx, df))
}

/// Tolerance of the one-frame position parity, relative to the domain.
const POSITION_PARITY: f64 = 1e-4;

fn parity_run<T: DeviceReal>(
    device: &Arc<CudaDevice>,
    scene: ParityScene,
    particles: usize,
    frames: usize,
) -> Result<bool> {
    let mut cpu = parity_world::<T>(scene, particles)?;
    let mut gpu = CudaWorld::new(parity_world::<T>(scene, particles)?, device.clone())?;
    let domain = cpu.config().domain_size;
    let substeps = cpu.config().substeps_per_frame;
    let precision = T::PRECISION.c_type();
    let mut passed = true;
    let (mut cpu_s, mut gpu_s) = (0.0, 0.0);
    for frame in 0..frames {
        let (from, to, active) = parity_anchors(scene, frame);
        let start = Instant::now();
        cpu.step_frame(&from, &to, &active)?;
        cpu_s += start.elapsed().as_secs_f64();
        let start = Instant::now();
        gpu.step_frame(&from, &to, &active)?;
        gpu_s += start.elapsed().as_secs_f64();
        if frame == 0 || frame + 1 == frames {
            let (dx, df) = compare(&cpu, &mut gpu)?;
            let relative = dx / domain;
            let gate = frame == 0;
            let ok = !gate || relative <= POSITION_PARITY;
            passed &= ok;
            println!(
                "parity {scene:?} {precision} frames {} ({} substeps each): max |dx|/domain {relative:.3e}, \
                 max |dF| {df:.3e}{}",
                frame + 1,
                substeps,
                if gate {
                    if ok { " — pass" } else { " — FAIL" }
                } else {
                    ""
                }
            );
        }
    }
    let coupled = cpu.actuators().coupled_particle_count();
    eprintln!(
        "# {scene:?} {precision}: {particles} particles, {coupled} coupled; {frames} frames: cpu {cpu_s:.2} s, gpu {gpu_s:.2} s"
    );
    Ok(passed)
}

/// `dm-bench cuda-parity`: CPU and CUDA worlds side by side; fails when a
/// one-frame position difference exceeds [`POSITION_PARITY`].
pub fn parity(particles: usize, frames: usize) -> Result<()> {
    let device = CudaDevice::open(0)?;
    println!("device {} ({})", device.name(), device.arch());
    let mut passed = true;
    for scene in [ParityScene::Hands, ParityScene::Plastic] {
        passed &= parity_run::<f64>(&device, scene, particles, frames)?;
        passed &= parity_run::<f32>(&device, scene, particles, frames)?;
    }
    if !passed {
        bail!("the CUDA world differs from the CPU world beyond {POSITION_PARITY:e} of the domain");
    }
    Ok(())
}
