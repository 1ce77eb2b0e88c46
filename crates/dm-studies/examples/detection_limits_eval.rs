//! Whether the diagnosis's detection limits mean something
//! (docs/diagnose.md, "Detectability"):
//!
//!     cargo run --release -p dm-studies --example detection_limits_eval -- OUT_DIR [DRAWS=8] [FIRST_SEED=9100] [SHARD/SHARDS]
//!
//! for each evaluation draw (seeds FIRST_SEED, FIRST_SEED + 1, …), the
//! null twin is fitted (`evaluation_fit_options`) and diagnosed, and the
//! draw's effect hidden at 0.5× and 2× the limit reported there, each
//! fitted and diagnosed. Writes OUT_DIR/results.jsonl (one line per hidden
//! scene; a rerun skips the draws it holds) and prints the naming rate per
//! factor.

use dm_diagnose::DiagnoseOptions;
use dm_studies::detection_limits::{LimitCheck, check_limits};
use dm_studies::diagnosis_evaluation::evaluation_fit_options;
use std::io::Write;
use std::path::PathBuf;

/// The multiples of the limit each effect is hidden at.
const FACTORS: [f64; 2] = [0.5, 2.0];

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let out = PathBuf::from(args.first().ok_or_else(|| anyhow::anyhow!("OUT_DIR"))?);
    let draws: u64 = args.get(1).map_or(Ok(8), |a| a.parse())?;
    let first_seed: u64 = args.get(2).map_or(Ok(9100), |a| a.parse())?;
    let (shard, shards) = args
        .get(3)
        .map_or(Ok((0, 1)), |s| dm_studies::parse_shard(s))
        .map_err(anyhow::Error::msg)?;
    std::fs::create_dir_all(&out)?;
    let fit = evaluation_fit_options();
    let options = DiagnoseOptions {
        discover_iters: 0,
        ..DiagnoseOptions::default()
    };
    let read = || -> Vec<LimitCheck> {
        std::fs::read_to_string(out.join("results.jsonl"))
            .unwrap_or_default()
            .lines()
            .filter_map(|line| serde_json::from_str(line).ok())
            .collect()
    };
    let done = read();
    for seed in
        (first_seed..first_seed + draws).filter(|s| (s - first_seed) as usize % shards == shard)
    {
        if done.iter().any(|r| r.seed == seed) {
            continue;
        }
        let started = std::time::Instant::now();
        let checks = check_limits(seed, &out, &fit, &options, &FACTORS)?;
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(out.join("results.jsonl"))?;
        for c in &checks {
            writeln!(file, "{}", serde_json::to_string(c)?)?;
            println!(
                "{seed} {} {}: limit {:?} {}, ×{} → {} (best {:.3}) {} ({:.0} s)",
                c.preset,
                c.effect,
                c.limit,
                c.unit,
                c.factor,
                c.cause,
                c.best_score,
                if c.named { "named" } else { "not named" },
                started.elapsed().as_secs_f64()
            );
        }
    }
    let all = read();
    for factor in FACTORS {
        let tried: Vec<&LimitCheck> = all
            .iter()
            .filter(|c| c.factor == factor && c.magnitude.is_some())
            .collect();
        let named = tried.iter().filter(|c| c.named).count();
        println!("×{factor}: named {named}/{}", tried.len());
    }
    let untestable = all.iter().filter(|c| c.limit.is_none()).count() / FACTORS.len();
    println!("draws whose effect this clip cannot reveal: {untestable}");
    Ok(())
}
