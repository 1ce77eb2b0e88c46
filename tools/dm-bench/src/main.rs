//! `dm-bench`: speed measurements whose numbers go in docs/BENCHMARKS.md.

use anyhow::{Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::material_backward::lame_vjp;
use dm_mpm::scenes::{BenchExperts, bench_block, bench_block_frames};
use std::time::Instant;

mod cuda;
mod images;
mod residual;

#[derive(Parser, Debug)]
#[command(name = "dm-bench", about = "DeformMaster benchmarks")]
struct Cli {
    /// Worker threads (default: all cores).
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum Experts {
    /// Single Neo-Hookean expert.
    Nh,
    /// Mixture of three constitutive experts.
    Moce,
}

/// Where the MPM world runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Device {
    Cpu,
    /// An NVIDIA GPU through CUDA (driver and NVRTC loaded at run time).
    Cuda,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// MPM substep throughput on the reference falling block.
    Mpm {
        #[arg(long, default_value_t = 100_000)]
        particles: usize,
        #[arg(long, default_value_t = 32)]
        grid: usize,
        #[arg(long, value_enum, default_value_t = Experts::Nh)]
        experts: Experts,
        /// Measured substeps (after 20 warm-up substeps).
        #[arg(long, default_value_t = 400)]
        substeps: usize,
        /// Viscous damping η, Pa·s (the grid's implicit solve; the block's
        /// density is 1 kg/m³, so dt η/(ρ dx²) is printed to compare).
        #[arg(long, default_value_t = 0.0)]
        viscosity: f64,
        #[arg(long, value_enum, default_value_t = Device::Cpu)]
        device: Device,
        /// Timed runs on the GPU (the median is printed, with the spread).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
    },
    /// The CUDA world against the CPU world (f64 and f32) on two scenes
    /// with hands, floor friction, drag, expert mixtures and plasticity;
    /// fails when one frame's positions differ by more than 1e-4 of the domain.
    CudaParity {
        #[arg(long, default_value_t = 20_000)]
        particles: usize,
        /// Frames simulated (the first and last are compared).
        #[arg(long, default_value_t = 10)]
        frames: usize,
        /// Compare the positions only: no adjoint and no residual network.
        #[arg(long)]
        positions_only: bool,
    },
    /// Forward + backward of one truncated-BPTT window on the reference
    /// block (Neo-Hookean); loss = mean |x|² after the window; gradient
    /// with respect to every particle's Young's modulus.
    Grad {
        #[arg(long, default_value_t = 10_000)]
        particles: usize,
        #[arg(long, default_value_t = 20)]
        window: usize,
        #[arg(long, default_value_t = 32)]
        grid: usize,
        /// Timed repetitions (the median is printed).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
        #[arg(long, value_enum, default_value_t = Device::Cpu)]
        device: Device,
    },
    /// The PNPGD residual of one frame (method.md §5 sizes): forward, then
    /// the vector-Jacobian product, on the reference block's particles.
    Residual {
        #[arg(long, default_value_t = 8_000)]
        particles: usize,
        #[arg(long, default_value_t = 32)]
        grid: usize,
        /// Timed repetitions after one warm-up (the median is printed).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
        #[arg(long, value_enum, default_value_t = Device::Cpu)]
        device: Device,
    },
    /// Gaussian-splat render (forward, then backward of a squared-error
    /// loss) of seeded random Gaussians in a 0.3 m ball seen from 0.7 m.
    Render {
        #[arg(long, default_value_t = 50_000)]
        gaussians: usize,
        #[arg(long, default_value_t = 640)]
        width: u32,
        #[arg(long, default_value_t = 480)]
        height: u32,
        /// Timed repetitions after one warm-up (medians are printed).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
    },
    /// dm-view's sphere-splat renderer (the synthetic scenes' images and
    /// the previews): seeded splats over a checker floor, four cases.
    SphereRender {
        /// Splats of the dense object and of the sparse cloud.
        #[arg(long, default_value_t = 50_000)]
        splats: usize,
        #[arg(long, default_value_t = 640)]
        width: u32,
        #[arg(long, default_value_t = 480)]
        height: u32,
        /// Timed renders per case after one warm-up (medians are printed).
        #[arg(long, default_value_t = 20)]
        repeats: usize,
        /// Also write three views of the dense object side by side to this PNG.
        #[arg(long)]
        preview: Option<std::path::PathBuf>,
    },
    /// dm-eval's image metrics (PSNR, SSIM, LPIPS) of two textured images
    /// at the benchmark's resolution; LPIPS needs the `make lpips` cache.
    Metrics {
        #[arg(long, default_value_t = 848)]
        width: u32,
        #[arg(long, default_value_t = 480)]
        height: u32,
        /// Timed calls per metric after one warm-up (means are printed).
        #[arg(long, default_value_t = 10)]
        repeats: usize,
        /// ONNX Runtime intra-op threads of LPIPS (0: all cores).
        #[arg(long, default_value_t = 0)]
        lpips_threads: usize,
    },
    /// The playground's frame (simulation, splat LBS, message and a
    /// 640×480 view) of a fitted model: prints `play_fps` (docs/BENCHMARKS.md).
    Play {
        /// Fitted model directory (splats used when present).
        #[arg(long)]
        model: std::path::PathBuf,
        /// Timed frames after 3 warm-up frames.
        #[arg(long, default_value_t = 40)]
        frames: usize,
        #[command(flatten)]
        simulation: dm_play::PlayOptions,
    },
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    if let Some(threads) = cli.threads {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build_global()
            .context("configuring the thread pool")?;
    }
    match cli.command {
        Command::Mpm {
            particles,
            grid,
            experts,
            substeps,
            viscosity,
            device,
            repeats,
        } => {
            let experts = match experts {
                Experts::Nh => BenchExperts::NeoHookean,
                Experts::Moce => BenchExperts::Mixture,
            };
            if device == Device::Cuda {
                if viscosity > 0.0 {
                    anyhow::bail!("--viscosity runs on the CPU only (use --device cpu)");
                }
                return cuda::mpm_throughput(particles, grid, experts, substeps, repeats);
            }
            let mut world = bench_block::<f32>(particles, grid, experts, 0)
                .context("building the benchmark block")?;
            if viscosity > 0.0 {
                let mut effects = world.config().effects.clone();
                effects.viscosity = viscosity;
                world
                    .set_effects(effects)
                    .context("setting the viscosity")?;
                let c = world.config();
                eprintln!(
                    "# viscosity {viscosity} Pa·s: dt η/(ρ dx²) = {:.3}",
                    c.dt * viscosity / (c.density * c.dx() * c.dx())
                );
            }
            for _ in 0..20 {
                world.substep()?;
            }
            let start = Instant::now();
            for _ in 0..substeps {
                world.substep()?;
            }
            let seconds = start.elapsed().as_secs_f64();
            println!(
                "particle_substeps_per_s {:.4e}",
                (particles * substeps) as f64 / seconds
            );
            eprintln!("# stage seconds (incl. warm-up): {:?}", world.stage_seconds);
            eprintln!(
                "# {particles} particles, grid {grid}^3, {experts:?}, {substeps} substeps in {seconds:.3} s, {} threads",
                rayon::current_num_threads()
            );
        }
        Command::CudaParity {
            particles,
            frames,
            positions_only,
        } => cuda::parity(particles, frames, positions_only)?,
        Command::Grad {
            particles,
            window,
            grid,
            repeats,
            device: Device::Cuda,
        } => cuda::grad_window(particles, window, grid, repeats)?,
        Command::Grad {
            particles,
            window,
            grid,
            repeats,
            device: Device::Cpu,
        } => grad_window(particles, window, grid, repeats)?,
        Command::Residual {
            particles,
            grid,
            repeats,
            device,
        } => {
            let gpu = match device {
                Device::Cpu => None,
                Device::Cuda => Some(dm_cuda::CudaDevice::open(0)?),
            };
            residual::frame(particles, grid, repeats, gpu)?
        }
        Command::Render {
            gaussians,
            width,
            height,
            repeats,
        } => render_bench(gaussians, width, height, repeats)?,
        Command::Play {
            model,
            frames,
            simulation,
        } => play_bench(&model, frames, &simulation)?,
        Command::SphereRender {
            splats,
            width,
            height,
            repeats,
            preview,
        } => images::sphere_render(splats, width, height, repeats, preview.as_deref())?,
        Command::Metrics {
            width,
            height,
            repeats,
            lpips_threads,
        } => images::metrics(width, height, repeats, lpips_threads)?,
    }
    Ok(())
}

fn grad_window(particles: usize, window: usize, grid: usize, repeats: usize) -> Result<()> {
    let (youngs, poisson) = (400.0, 0.2);
    let mut forward = Vec::new();
    let mut total = Vec::new();
    let mut checksum = 0.0;
    for _ in 0..repeats.max(1) {
        let mut world =
            bench_block_frames::<f32>(particles, grid, BenchExperts::NeoHookean, 0, window)
                .context("building the benchmark block")?;
        let start = Instant::now();
        let tape = world.step_frame_taped(&[], &[], &[], window)?;
        let forward_s = start.elapsed().as_secs_f64();
        let state = world.state();
        let n = state.len() as f32;
        let mut upstream = ParticleGrads::zeros(state.len());
        for (g, x) in upstream.x.iter_mut().zip(&state.x) {
            *g = x * (2.0 / n);
        }
        let grads = world.backward_frame(&tape, &upstream)?;
        let grad_youngs: Vec<f32> = grads
            .mu
            .iter()
            .zip(&grads.lambda)
            .map(|(&gm, &gl)| lame_vjp(youngs as f32, poisson as f32, gm, gl).0)
            .collect();
        total.push(start.elapsed().as_secs_f64());
        forward.push(forward_s);
        checksum = grad_youngs.iter().map(|g| f64::from(*g)).sum::<f64>();
    }
    let (t, f) = (median(&mut total), median(&mut forward));
    println!("grad_window_s {t:.4}");
    eprintln!(
        "# {particles} particles, grid {grid}^3, window {window}: forward {f:.4} s, backward {:.4} s \
         (backward/forward {:.2}); sum dL/dE = {checksum:.4e}; {} threads",
        t - f,
        (t - f) / f,
        rayon::current_num_threads()
    );
    Ok(())
}

/// Median of timings (upper median for even counts).
fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn play_bench(
    model_dir: &std::path::Path,
    frames: usize,
    options: &dm_play::PlayOptions,
) -> Result<()> {
    use dm_play::{encode_frame, open_session};
    let mut session = open_session(model_dir, options)
        .with_context(|| format!("opening the model in {}", model_dir.display()))?;
    // A hand grabs the object at its centre (picked from above) and moves
    // it up and down: the load of a user pulling it around.
    let view = session.view().clone();
    let up = view.up;
    let origin = [0, 1, 2].map(|a| view.centre[a] + up[a]);
    let particle = session
        .pick(origin, up.map(|c| -c))
        .context("no particle under the object's centre to grab")?;
    session.grab(0, particle)?;
    let camera = &view.cameras[0];
    let settings = dm_splat::RenderSettings::default();
    let sprites = session.sprites();
    let mut sim_ms = Vec::new();
    let mut render_ms = Vec::new();
    let mut splat_render_ms = Vec::new();
    let mut total_ms = Vec::new();
    for frame in 0..frames + 3 {
        let direction = if (frame / 15) % 2 == 0 { 0.2 } else { -0.2 };
        session.set_hand_velocity(0, up.map(|c| direction * c))?;
        let start = Instant::now();
        session.step().context("simulating a frame")?;
        let message = encode_frame(&session);
        std::hint::black_box(&message);
        let simulated = start.elapsed().as_secs_f64() * 1e3;
        // What the page draws (depth-tested sprites), here on the CPU.
        let drawn = dm_play::draw_sprites(camera, &session.sprite_positions(), &sprites, &view);
        std::hint::black_box(drawn.rgb.len());
        let total = start.elapsed().as_secs_f64() * 1e3;
        // The faithful splat render (dm-render's rasterizer), for reference.
        let splat_start = Instant::now();
        if let Some(gaussians) = session.splats() {
            let image =
                dm_splat::render(gaussians, camera, &settings).context("rendering the splats")?;
            std::hint::black_box(image.image().len());
        }
        let splat_render = splat_start.elapsed().as_secs_f64() * 1e3;
        if frame >= 3 {
            sim_ms.push(simulated);
            render_ms.push(total - simulated);
            splat_render_ms.push(splat_render);
            total_ms.push(total);
        }
    }
    let state = session.state();
    println!(
        "play: {} particles, {} {}, grid {}^3, {} substeps per {:.1} ms frame (CFL {}), render {}x{}, {} threads",
        state.particle_count,
        sprites.count,
        sprites.kind,
        state.grid,
        state.substeps_per_frame,
        1e3 * state.frame_dt,
        options.cfl.map_or("model's".to_string(), |c| c.to_string()),
        camera.width,
        camera.height,
        rayon::current_num_threads()
    );
    let total = median(&mut total_ms);
    let sim = median(&mut sim_ms);
    println!("play_sim_ms {sim:.2}");
    println!("play_render_ms {:.2}", median(&mut render_ms));
    if session.splats().is_some() {
        let splat = median(&mut splat_render_ms);
        println!("play_splat_render_ms {splat:.2}");
        println!("play_fps_with_splat_render {:.1}", 1e3 / (sim + splat));
    }
    println!("play_frame_ms {total:.2}");
    println!("play_fps {:.1}", 1e3 / total);
    Ok(())
}

fn render_bench(count: usize, width: u32, height: u32, repeats: usize) -> Result<()> {
    use dm_splat::gaussians::logit;
    use dm_splat::{Gaussians, RenderSettings, render, render_backward};
    use nalgebra::{Point3, Vector3};
    use rand::{RngExt, SeedableRng};

    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut uniform = |lo: f64, hi: f64| lo + (hi - lo) * rng.random::<f64>();
    let mut gaussians = Gaussians::<f32>::default();
    // An object-sized cloud: uniform in a 0.15 m-radius ball, σ 2-10 mm
    // (roughly what a fit of a plush toy at this density produces).
    while gaussians.len() < count {
        let p = Vector3::new(uniform(-1.0, 1.0), uniform(-1.0, 1.0), uniform(-1.0, 1.0));
        if p.norm() > 1.0 {
            continue;
        }
        let q = [
            uniform(-1.0, 1.0),
            uniform(-1.0, 1.0),
            uniform(-1.0, 1.0),
            uniform(-1.0, 1.0),
        ];
        let n = q.iter().map(|c| c * c).sum::<f64>().sqrt().max(1e-6);
        gaussians.push(
            (p * 0.15).cast::<f32>(),
            Vector3::new(
                uniform(0.002f64.ln(), 0.01f64.ln()),
                uniform(0.002f64.ln(), 0.01f64.ln()),
                uniform(0.002f64.ln(), 0.01f64.ln()),
            )
            .cast::<f32>(),
            q.map(|c| (c / n) as f32),
            logit(uniform(0.1, 0.99)) as f32,
            Vector3::new(uniform(0.0, 1.0), uniform(0.0, 1.0), uniform(0.0, 1.0)).cast::<f32>(),
        );
    }
    let camera = dm_view::Camera::look_at(
        Point3::new(0.5, -0.45, 0.2),
        Point3::origin(),
        Vector3::z(),
        width,
        height,
        50.0,
    );
    let settings = RenderSettings {
        background: [1.0, 1.0, 1.0],
        ..RenderSettings::default()
    };
    let target = vec![[0.5f32; 3]; width as usize * height as usize];
    let mut forward_ms = Vec::new();
    let mut backward_ms = Vec::new();
    let mut summary = String::new();
    for rep in 0..=repeats.max(1) {
        let start = Instant::now();
        let out = render(&gaussians, &camera, &settings).context("rendering")?;
        let forward = start.elapsed().as_secs_f64() * 1e3;
        let grad_image: Vec<[f32; 3]> = out
            .image()
            .iter()
            .zip(&target)
            .map(|(a, b)| [a[0] - b[0], a[1] - b[1], a[2] - b[2]])
            .collect();
        let start = Instant::now();
        let grads = render_backward(&gaussians, &camera, &settings, &out, &grad_image)
            .context("back-propagating")?;
        let backward = start.elapsed().as_secs_f64() * 1e3;
        if rep > 0 {
            forward_ms.push(forward);
            backward_ms.push(backward);
        }
        let coverage =
            out.alpha().iter().map(|a| f64::from(*a)).sum::<f64>() / f64::from(width * height);
        summary = format!(
            "{} visible, {} tile intersections, coverage {coverage:.3}, |dL/dmean| sum {:.4e}",
            out.projected.visible_count(),
            out.bins.intersections(),
            grads.means.iter().map(|g| f64::from(g.norm())).sum::<f64>()
        );
    }
    println!("render_ms {:.2}", median(&mut forward_ms));
    println!("render_backward_ms {:.2}", median(&mut backward_ms));
    eprintln!(
        "# {count} Gaussians, {width}x{height}, f32, {} threads: {summary}",
        rayon::current_num_threads()
    );
    Ok(())
}
