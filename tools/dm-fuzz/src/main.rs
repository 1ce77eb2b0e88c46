//! `dm-fuzz`: seeded mutation fuzzing of the parsers of outside input
//! (docs/RELIABILITY.md); findings are saved for regression tests.

use anyhow::{Context, Result, bail};
use clap::Parser;
use dm_fuzz::{Budget, Target};
use std::path::PathBuf;

#[global_allocator]
static HEAP: dm_fuzz::alloc_meter::MeteredAllocator = dm_fuzz::alloc_meter::MeteredAllocator;

#[derive(Parser, Debug)]
#[command(name = "dm-fuzz", about = "Fuzz the parsers of outside input")]
struct Args {
    /// Targets to fuzz (default: all): pickle, ply, obj, glb, manifest,
    /// bundle-json, bundle-npy, model-json, checkpoint, play-command.
    targets: Vec<String>,
    /// Inputs per target.
    #[arg(long, default_value_t = 1_000_000)]
    inputs: u64,
    /// Seconds per target at most.
    #[arg(long, default_value_t = 3600.0)]
    seconds: f64,
    /// Seed of the mutation generator.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Seed corpus (one folder per target).
    #[arg(long)]
    corpus: Option<PathBuf>,
    /// Where inputs that panicked or hung are written.
    #[arg(long, default_value = "fuzz/findings")]
    findings: PathBuf,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let targets: Vec<Target> = if args.targets.is_empty() {
        Target::ALL.to_vec()
    } else {
        args.targets
            .iter()
            .map(|name| Target::from_name(name).with_context(|| format!("no fuzz target `{name}`")))
            .collect::<Result<_>>()?
    };
    let corpus = args.corpus.clone().unwrap_or_else(dm_fuzz::default_corpus);
    let budget = Budget {
        inputs: args.inputs,
        seconds: args.seconds,
    };
    let mut findings = 0;
    println!(
        "target        inputs   accepted   seconds   inputs/s   slowest ms   largest MiB   findings"
    );
    for target in targets {
        let report = dm_fuzz::run(target, &corpus, args.seed, budget)
            .with_context(|| format!("fuzzing {}", target.name()))?;
        println!(
            "{:<12} {:>8} {:>10} {:>9.1} {:>10.0} {:>12.2} {:>13.2} {:>10}",
            target.name(),
            report.inputs,
            report.accepted,
            report.seconds,
            report.inputs as f64 / report.seconds.max(1e-9),
            1e3 * report.slowest_input_seconds,
            report.largest_input_bytes.unwrap_or(0) as f64 / f64::from(1u32 << 20),
            report.findings.len()
        );
        for (i, finding) in report.findings.iter().enumerate() {
            std::fs::create_dir_all(&args.findings)
                .with_context(|| format!("creating {}", args.findings.display()))?;
            let path = args
                .findings
                .join(format!("{}-{}-{i}.bin", target.name(), args.seed));
            std::fs::write(&path, &finding.input)
                .with_context(|| format!("writing {}", path.display()))?;
            eprintln!("  {}: {} ({})", target.name(), finding.what, path.display());
        }
        findings += report.findings.len();
    }
    if findings > 0 {
        bail!(
            "{findings} inputs panicked, hung or held too much heap; saved under {}",
            args.findings.display()
        );
    }
    Ok(())
}
