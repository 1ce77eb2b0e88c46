//! GPU measurements: substep throughput on the reference block and
//! parity of the CUDA world against the CPU world.

use anyhow::{Context, Result, bail};
use dm_cuda::{CudaDevice, CudaWorld, DeviceReal};
use dm_mpm::scenes::{BenchExperts, bench_block};
use dm_mpm::state::Particles;
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
    Ok(largest_differences(&cpu.state(), &gpu.state()?))
}

/// Largest position and F differences between two states.
fn largest_differences<T: DeviceReal>(a: &Particles<T>, b: &Particles<T>) -> (f64, f64) {
    let dx =
        a.x.iter()
            .zip(&b.x)
            .map(|(a, b)| (a - b).norm().to_f64())
            .fold(0.0, f64::max);
    let df =
        a.f.iter()
            .zip(&b.f)
            .map(|(a, b)| (a - b).norm().to_f64())
            .fold(0.0, f64::max);
    (dx, df)
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
    let mut after_first_frame = None;
    for frame in 0..frames {
        let (from, to, active) = parity_anchors(scene, frame);
        let start = Instant::now();
        cpu.step_frame(&from, &to, &active)?;
        cpu_s += start.elapsed().as_secs_f64();
        let start = Instant::now();
        gpu.step_frame(&from, &to, &active)?;
        gpu_s += start.elapsed().as_secs_f64();
        if frame == 0 {
            after_first_frame = Some(gpu.state()?);
        }
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
    if let Some(first) = after_first_frame {
        passed &= restart_parity(&mut gpu, scene, particles, &first)?;
    }
    let coupled = cpu.actuators().coupled_particle_count();
    eprintln!(
        "# {scene:?} {precision}: {particles} particles, {coupled} coupled; {frames} frames: cpu {cpu_s:.2} s, gpu {gpu_s:.2} s"
    );
    Ok(passed)
}

/// The GPU world started again from its first frame (as a planner's kept
/// worlds are): its first frame again, against `first` (that frame's state
/// the first time); where graphs are on, replayed without a new capture.
fn restart_parity<T: DeviceReal>(
    gpu: &mut CudaWorld<T>,
    scene: ParityScene,
    particles: usize,
    first: &Particles<T>,
) -> Result<bool> {
    let captured = gpu.graph_captures();
    gpu.restart_from(parity_world::<T>(scene, particles)?)?;
    let (from, to, active) = parity_anchors(scene, 0);
    gpu.step_frame(&from, &to, &active)?;
    let (dx, _) = largest_differences(first, &gpu.state()?);
    let relative = dx / gpu.config().domain_size;
    let captured_again = gpu.graph_captures() - captured;
    let ok = relative <= POSITION_PARITY && (!gpu.device().graphs_enabled() || captured_again == 0);
    println!(
        "restarted world {scene:?} {}: frame 1 again, max |dx|/domain {relative:.3e}, graphs captured again {captured_again}{}",
        T::PRECISION.c_type(),
        if ok { " — pass" } else { " — FAIL" }
    );
    Ok(ok)
}

/// `dm-bench cuda-parity`: CPU and CUDA worlds side by side; fails when a
/// one-frame position difference exceeds [`POSITION_PARITY`] (then, unless
/// `positions_only`, when an adjoint or the residual network differs).
pub fn parity(particles: usize, frames: usize, positions_only: bool) -> Result<()> {
    let device = CudaDevice::open(0)?;
    println!("device {} ({})", device.name(), device.arch());
    let mut passed = true;
    for scene in [ParityScene::Hands, ParityScene::Plastic] {
        passed &= parity_run::<f64>(&device, scene, particles, frames)?;
        passed &= parity_run::<f32>(&device, scene, particles, frames)?;
    }
    let positions_differ = || {
        anyhow::anyhow!(
            "the CUDA world differs from the CPU world beyond {POSITION_PARITY:e} of the domain"
        )
    };
    if positions_only {
        return if passed {
            Ok(())
        } else {
            Err(positions_differ())
        };
    }
    let mut gradients = true;
    for scene in [ParityScene::Hands, ParityScene::Plastic] {
        gradients &= gradient_parity_run::<f64>(&device, scene, particles)?;
        gradients &= gradient_parity_run::<f32>(&device, scene, particles)?;
    }
    let residual = crate::residual::parity::<f64>(&device, particles)?
        & crate::residual::parity::<f32>(&device, particles)?;
    if !passed {
        return Err(positions_differ());
    }
    if !gradients {
        bail!(
            "a gradient of the CUDA adjoint differs from the CPU's (cosine below {GRADIENT_COSINE} or norm off by more than {GRADIENT_NORM})"
        );
    }
    if !residual {
        bail!(
            "the residual network on the GPU differs from the CPU's (Δv beyond {:e} of α, or a gradient as above)",
            crate::residual::DV_PARITY
        );
    }
    Ok(())
}

/// Cosine and norm ratio (GPU over CPU) of two gradients.
fn agreement(cpu: &[f64], gpu: &[f64]) -> (f64, f64) {
    let dot: f64 = cpu.iter().zip(gpu).map(|(a, b)| a * b).sum();
    let (na, nb) = (
        cpu.iter().map(|a| a * a).sum::<f64>().sqrt(),
        gpu.iter().map(|b| b * b).sum::<f64>().sqrt(),
    );
    if na == 0.0 && nb == 0.0 {
        return (1.0, 1.0);
    }
    (
        dot / (na * nb).max(f64::MIN_POSITIVE),
        nb / na.max(f64::MIN_POSITIVE),
    )
}

/// Gradient parity: the cosine at least this…
const GRADIENT_COSINE: f64 = 0.999;
/// …and the norm within this fraction of the CPU's.
const GRADIENT_NORM: f64 = 0.01;

/// Vectors or matrices as their f64 entries.
fn entries<T: DeviceReal, const R: usize, const C: usize>(
    values: &[nalgebra::SMatrix<T, R, C>],
) -> Vec<f64> {
    values
        .iter()
        .flat_map(|m| m.iter().map(|c| c.to_f64()))
        .collect()
}

fn scalars<T: DeviceReal>(values: &[T]) -> Vec<f64> {
    values.iter().map(|c| c.to_f64()).collect()
}

fn weight_entries<T: DeviceReal>(weights: &[[T; 3]]) -> Vec<f64> {
    weights.iter().flat_map(|w| w.map(|c| c.to_f64())).collect()
}

/// Every group of a substep's adjoint as f64 vectors, by name.
fn substep_groups<T: DeviceReal>(
    g: &dm_mpm::substep::SubstepGrads<T>,
) -> Vec<(&'static str, Vec<f64>)> {
    vec![
        ("x", entries(&g.state.x)),
        ("v", entries(&g.state.v)),
        ("F", entries(&g.state.f)),
        ("C", entries(&g.state.c)),
        ("mu", scalars(&g.mu)),
        ("lambda", scalars(&g.lambda)),
        ("expert weights", weight_entries(&g.weights)),
        ("actuator accel", entries(&g.external_accel)),
        (
            "drag (summed)",
            (0..2)
                .map(|e| g.effects.iter().map(|p| p[e].to_f64()).sum())
                .collect(),
        ),
        ("mass", scalars(&g.mass)),
        ("gravity", entries(std::slice::from_ref(&g.gravity))),
        ("friction", vec![g.friction.to_f64()]),
        ("damping factor", vec![g.damping_factor.to_f64()]),
    ]
}

/// Every group of a frame's adjoint as f64 vectors, by name.
fn frame_groups<T: DeviceReal>(g: &dm_mpm::tape::FrameGrads<T>) -> Vec<(&'static str, Vec<f64>)> {
    let e = &g.effects;
    vec![
        ("x", entries(&g.state.x)),
        ("v", entries(&g.state.v)),
        ("F", entries(&g.state.f)),
        ("C", entries(&g.state.c)),
        ("mu", scalars(&g.mu)),
        ("lambda", scalars(&g.lambda)),
        ("expert weights", weight_entries(&g.weights)),
        ("mass", scalars(&g.mass)),
        ("gains", vec![g.gains.kp, g.gains.kd]),
        ("drag", vec![e.air_drag_linear, e.air_drag_quadratic]),
        ("gravity", e.gravity.to_vec()),
        ("friction", vec![e.floor_friction]),
        ("particle damping", vec![e.particle_damping]),
        (
            "anchors",
            g.anchors_from
                .iter()
                .chain(&g.anchors_to)
                .flatten()
                .copied()
                .collect(),
        ),
    ]
}

/// Prints each group's agreement after `label`; whether every group
/// passes.
pub fn report_agreement(
    label: &str,
    want: Vec<(&'static str, Vec<f64>)>,
    got: Vec<(&'static str, Vec<f64>)>,
) -> bool {
    let mut passed = true;
    let mut line = String::new();
    for ((name, a), (_, b)) in want.into_iter().zip(got) {
        let (cosine, ratio) = agreement(&a, &b);
        let ok = cosine >= GRADIENT_COSINE && (ratio - 1.0).abs() <= GRADIENT_NORM;
        passed &= ok;
        line.push_str(&format!(
            "{name} {cosine:.6}/{ratio:.5}{}; ",
            if ok { "" } else { " FAIL" }
        ));
    }
    println!("{label} (cosine/norm ratio): {line}");
    passed
}

/// The CPU and CUDA worlds of `scene` after its first frame, the CUDA
/// world holding the CPU world's state (so both differentiate the same).
fn worlds_after_first_frame<T: DeviceReal>(
    device: &Arc<CudaDevice>,
    scene: ParityScene,
    particles: usize,
) -> Result<(World<T>, CudaWorld<T>)> {
    let mut cpu = parity_world::<T>(scene, particles)?;
    let (from, to, active) = parity_anchors(scene, 0);
    cpu.step_frame(&from, &to, &active)?;
    let mut gpu = CudaWorld::new(parity_world::<T>(scene, particles)?, device.clone())?;
    gpu.step_frame(&from, &to, &active)?;
    gpu.set_state(&cpu.state())?;
    Ok((cpu, gpu))
}

/// One substep's adjoint on both devices, at the state after the first
/// frame of `scene`, with seeded upstream gradients; prints each group's
/// agreement and returns whether all pass.
fn gradient_parity_run<T: DeviceReal>(
    device: &Arc<CudaDevice>,
    scene: ParityScene,
    particles: usize,
) -> Result<bool> {
    use dm_mpm::g2p_backward::ParticleGrads;
    use dm_mpm::real::{Mat3, Vec3};
    use dm_mpm::substep::{SubstepInputs, SubstepScratch, substep_backward};
    let (cpu, mut gpu) = worlds_after_first_frame::<T>(device, scene, particles)?;
    // The next frame's first-substep forces.
    let before = cpu.slot_particles().clone();
    let (from, to, _) = parity_anchors(scene, 1);
    let frame_dt = cpu.config().dt * cpu.config().substeps_per_frame as f64;
    let anchor_x: Vec<Vec3<T>> = from.iter().map(|&p| dm_mpm::real::vec3(p)).collect();
    let anchor_v: Vec<Vec3<T>> = from
        .iter()
        .zip(&to)
        .map(|(a, b)| dm_mpm::real::vec3([0, 1, 2].map(|i| (b[i] - a[i]) / frame_dt)))
        .collect();
    let n = before.len();
    let mut accel = vec![Vec3::zeros(); n];
    cpu.actuators()
        .accelerations(&before.x, &before.v, &anchor_x, &anchor_v, &mut accel);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let mut r = || T::lit(rng.random::<f64>() - 0.5);
    let grad_after = ParticleGrads {
        x: (0..n).map(|_| Vec3::new(r(), r(), r())).collect(),
        v: (0..n).map(|_| Vec3::new(r(), r(), r())).collect(),
        f: (0..n).map(|_| Mat3::from_fn(|_, _| r())).collect(),
        c: (0..n).map(|_| Mat3::from_fn(|_, _| r())).collect(),
    };
    let inputs = SubstepInputs {
        material: cpu.slot_material(),
        pure_neo_hookean: cpu.is_pure_neo_hookean(),
        external_accel: Some(&accel),
    };
    let k = *cpu.consts();
    let mut scratch = SubstepScratch::new(cpu.config().grid_res);
    let want = substep_backward(&k, &inputs, &before, &grad_after, &mut scratch)?;
    let got = gpu.substep_backward(&before, Some(&accel), &grad_after)?;
    let label = format!("gradient parity {scene:?} {}", T::PRECISION.c_type());
    let passed = report_agreement(&label, substep_groups(&want), substep_groups(&got));
    Ok(passed && frame_gradient_parity_run::<T>(device, scene, particles)?)
}

/// A frame's adjoint (`backward_frame`, the actuators' and anchors'
/// adjoints included) on both devices from the same state: the second
/// frame taped whole, then in f64 the third taped over its last half (the
/// first half replayed as a CUDA graph where graphs are on). In f32 the
/// two devices' untaped halves part by round-off, which a plastic kink
/// turns into a different adjoint: only f64 isolates the adjoint there.
/// Then, in both precisions, the next frame's last half taped again from
/// the state kept at its start (the fit's backward pass). Prints each
/// group's agreement and returns whether all pass.
fn frame_gradient_parity_run<T: DeviceReal>(
    device: &Arc<CudaDevice>,
    scene: ParityScene,
    particles: usize,
) -> Result<bool> {
    use dm_mpm::g2p_backward::ParticleGrads;
    use dm_mpm::real::Vec3;
    let (mut cpu, mut gpu) = worlds_after_first_frame::<T>(device, scene, particles)?;
    let substeps = cpu.config().substeps_per_frame;
    let n = cpu.particle_count();
    let upstream = ParticleGrads {
        x: (0..n)
            .map(|p| Vec3::new(T::one(), T::lit(-0.5), T::lit(0.25)) * T::lit(p as f64 / n as f64))
            .collect(),
        ..ParticleGrads::zeros(n)
    };
    let mut passed = true;
    let mut windows = vec![(1, substeps)];
    if T::PRECISION == dm_cuda::Precision::F64 {
        windows.push((2, substeps.div_ceil(2)));
    }
    let windows_run = windows.len();
    for (frame, window) in windows {
        gpu.set_state(&cpu.state())?;
        let (from, to, active) = parity_anchors(scene, frame);
        let cpu_tape = cpu.step_frame_taped(&from, &to, &active, window)?;
        let gpu_tape = gpu.step_frame_taped(&from, &to, &active, window)?;
        let want = cpu.backward_frame(&cpu_tape, &upstream)?;
        let got = gpu.backward_frame(&gpu_tape, &upstream)?;
        let label = format!(
            "frame gradient parity {scene:?} {}, {window} of {substeps} substeps",
            T::PRECISION.c_type()
        );
        passed &= report_agreement(&label, frame_groups(&want), frame_groups(&got));
    }
    // As a fit's backward pass: the frame kept at its window's start, then
    // only the window taped again, on both devices from the CPU's kept state.
    let window = substeps.div_ceil(2);
    let (from, to, active) = parity_anchors(scene, windows_run + 1);
    let start = cpu.state();
    let kept = cpu.step_frame_keeping(&from, &to, &active, substeps - window)?;
    gpu.set_state(&start)?;
    let gpu_kept = gpu.step_frame_keeping(&from, &to, &active, substeps - window)?;
    let domain = cpu.config().domain_size;
    let (dx, _) = largest_differences(&kept, &gpu_kept);
    let kept_ok = dx / domain <= POSITION_PARITY;
    passed &= kept_ok;
    println!(
        "kept state parity {scene:?} {}, substep {} of {substeps}: max |dx|/domain {:.3e}{}",
        T::PRECISION.c_type(),
        substeps - window,
        dx / domain,
        if kept_ok { " — pass" } else { " — FAIL" }
    );
    cpu.set_state(&kept)?;
    gpu.set_state(&kept)?;
    let cpu_tape = cpu.step_frame_rest_taped(&from, &to, window)?;
    let gpu_tape = gpu.step_frame_rest_taped(&from, &to, window)?;
    let want = cpu.backward_frame(&cpu_tape, &upstream)?;
    let got = gpu.backward_frame(&gpu_tape, &upstream)?;
    let label = format!(
        "frame gradient parity {scene:?} {}, the last {window} of {substeps} substeps from the kept state",
        T::PRECISION.c_type()
    );
    passed &= report_agreement(&label, frame_groups(&want), frame_groups(&got));
    Ok(passed)
}

/// `dm-bench grad --device cuda`: forward and backward of one window of
/// free substeps on the reference block (loss mean |x|² after it), the
/// median of `repeats`; then the same window on the CPU for the gradients'
/// agreement (dL/dE per particle and dL/dx at the window's start).
pub fn grad_window(particles: usize, window: usize, grid: usize, repeats: usize) -> Result<()> {
    use dm_mpm::g2p_backward::ParticleGrads;
    use dm_mpm::material_backward::lame_vjp;
    use dm_mpm::scenes::bench_block_frames;
    let (youngs, poisson) = (400.0f32, 0.2f32);
    let device = CudaDevice::open(0)?;
    let block = || {
        bench_block_frames::<f32>(particles, grid, BenchExperts::NeoHookean, 0, window)
            .context("building the benchmark block")
    };
    let upstream_of = |x: &[dm_mpm::real::Vec3<f32>]| {
        let n = x.len() as f32;
        let mut g = ParticleGrads::zeros(x.len());
        for (g, x) in g.x.iter_mut().zip(x) {
            *g = x * (2.0 / n);
        }
        g
    };
    // One world: its buffers are allocated once, as in a fit; every
    // repetition starts the window from the block's first state.
    let first = block()?;
    let start_state = first.slot_particles().clone();
    let mut gpu = CudaWorld::new(first, device.clone())?;
    let mut forward = Vec::new();
    let mut total = Vec::new();
    for repeat in 0..=repeats.max(1) {
        gpu.edit(|w| *w.slot_particles_mut() = start_state.clone())?;
        device.stream().synchronize()?;
        let start = Instant::now();
        let tape = gpu.taped_substeps(window)?;
        let forward_s = start.elapsed().as_secs_f64();
        // The loss's gradient needs the window's last positions.
        let last = gpu.slot_positions()?;
        gpu.backward_tape(&tape, &upstream_of(&last), false)?;
        let total_s = start.elapsed().as_secs_f64();
        if repeat > 0 {
            forward.push(forward_s);
            total.push(total_s);
        }
    }
    let (t, f) = (median_of(&mut total), median_of(&mut forward));
    println!("grad_window_s {t:.5}");
    // One more window with every stage waited for, its gradients kept.
    gpu.edit(|w| *w.slot_particles_mut() = start_state.clone())?;
    let tape = gpu.taped_substeps(window)?;
    let last = gpu.slot_positions()?;
    gpu.time_stages(true);
    let grads = gpu.backward_tape(&tape, &upstream_of(&last), true)?;
    let ids = gpu.host()?.id_of_slot().to_vec();
    if let Some(s) = gpu.adjoint_seconds() {
        let per = |x: f64| 1e3 * x / window as f64;
        eprintln!(
            "# adjoint ms per substep, each stage waited for: recompute (sort, P2G, grid update) {:.4}, \
             G2P gather {:.4}, G2P scatter {:.4}, grid update {:.4}, P2G and stress {:.4}",
            per(s.recompute),
            per(s.g2p_gather),
            per(s.g2p_scatter),
            per(s.grid_update),
            per(s.p2g)
        );
    }
    eprintln!(
        "# {particles} particles, grid {grid}^3, window {window} on {}: forward {f:.5} s, backward {:.5} s",
        device.name(),
        t - f
    );
    // The CPU's gradients of the same window (caller order).
    let Some(state_grads) = grads.state else {
        bail!("the window's state adjoint was not fetched");
    };
    let mut cpu = block()?;
    let tape = cpu.step_frame_taped(&[], &[], &[], window)?;
    let want = cpu.backward_frame(&tape, &upstream_of(&cpu.state().x))?;
    let youngs_grad = |mu: &[f32], lambda: &[f32]| -> Vec<f64> {
        mu.iter()
            .zip(lambda)
            .map(|(&gm, &gl)| f64::from(lame_vjp(youngs, poisson, gm, gl).0))
            .collect()
    };
    let mut gpu_mu = vec![0.0f32; ids.len()];
    let mut gpu_lambda = vec![0.0f32; ids.len()];
    let mut gpu_x = vec![0.0f64; 3 * ids.len()];
    for (slot, &id) in ids.iter().enumerate() {
        gpu_mu[id as usize] = grads.mu[slot];
        gpu_lambda[id as usize] = grads.lambda[slot];
        for a in 0..3 {
            gpu_x[3 * id as usize + a] = f64::from(state_grads.x[slot][a]);
        }
    }
    let want_x: Vec<f64> = want
        .state
        .x
        .iter()
        .flat_map(|v| v.iter().map(|c| f64::from(*c)))
        .collect();
    let (cos_e, ratio_e) = agreement(
        &youngs_grad(&want.mu, &want.lambda),
        &youngs_grad(&gpu_mu, &gpu_lambda),
    );
    let (cos_x, ratio_x) = agreement(&want_x, &gpu_x);
    println!(
        "gradient agreement with the CPU (cosine / norm ratio): dL/dE {cos_e:.6} / {ratio_e:.5}, dL/dx0 {cos_x:.6} / {ratio_x:.5}"
    );
    Ok(())
}

/// Median of timings (upper median for even counts).
fn median_of(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}
