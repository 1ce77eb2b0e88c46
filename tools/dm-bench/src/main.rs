//! `dm-bench`: speed measurements whose numbers go in docs/BENCHMARKS.md.

use anyhow::{Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use dm_mpm::scenes::{BenchExperts, bench_block};
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
    }
    Ok(())
}
