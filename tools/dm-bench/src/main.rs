//! `dm-bench`: speed measurements whose numbers go in docs/BENCHMARKS.md.

use anyhow::{Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::material_backward::lame_vjp;
use dm_mpm::scenes::{BenchExperts, bench_block, bench_block_frames};
use std::time::Instant;

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
        } => {
            let experts = match experts {
                Experts::Nh => BenchExperts::NeoHookean,
                Experts::Moce => BenchExperts::Mixture,
            };
            let mut world = bench_block::<f32>(particles, grid, experts, 0)
                .context("building the benchmark block")?;
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
        Command::Grad {
            particles,
            window,
            grid,
            repeats,
        } => grad_window(particles, window, grid, repeats)?,
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
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
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
