//! The out-of-library evaluation of the diagnosis (docs/diagnose.md):
//!
//!     cargo run --release -p dm-studies --example discover_eval -- OUT_DIR [PER_EFFECT] [FIRST_SEED] [SHARD/SHARDS]
//!
//! for each of `wind`, `attractor` and `anisotropic_drag`, PER_EFFECT
//! scenes (default 4; seeds FIRST_SEED, FIRST_SEED + 1, … across the
//! effects in turn) hiding it, preset and magnitude drawn from the seed,
//! fitted with `evaluation_fit_options` and diagnosed with dm-diagnose's
//! defaults; the discovered body force is compared with the truth. Writes
//! OUT_DIR/results.jsonl (one line per scene, appended as scenes finish;
//! a rerun skips the scenes it holds) and prints a line per scene.

use dm_diagnose::DiagnoseOptions;
use dm_studies::diagnosis_evaluation::evaluation_fit_options;
use dm_studies::outside_library::{OutsideResult, run_outside_scene};
use dm_synth::EffectName;
use std::io::Write;
use std::path::PathBuf;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let out = PathBuf::from(args.first().ok_or_else(|| anyhow::anyhow!("OUT_DIR"))?);
    let per_effect: u64 = args.get(1).map_or(Ok(4), |a| a.parse())?;
    let first_seed: u64 = args.get(2).map_or(Ok(7000), |a| a.parse())?;
    let (shard, shards) = args
        .get(3)
        .map_or(Ok((0, 1)), |s| dm_studies::parse_shard(s))
        .map_err(anyhow::Error::msg)?;
    std::fs::create_dir_all(&out)?;
    let fit = evaluation_fit_options();
    let options = DiagnoseOptions::default();
    let scenes: Vec<(u64, EffectName)> = (0..per_effect)
        .flat_map(|k| {
            EffectName::OUTSIDE_LIBRARY
                .iter()
                .enumerate()
                .map(move |(e, &name)| (first_seed + 3 * k + e as u64, name))
        })
        .collect();
    // Scenes already in results.jsonl are not run again.
    let done: Vec<OutsideResult> = std::fs::read_to_string(out.join("results.jsonl"))
        .unwrap_or_default()
        .lines()
        .filter_map(|line| serde_json::from_str(line).ok())
        .collect();
    for (i, &(seed, effect)) in scenes.iter().enumerate() {
        if i % shards != shard || done.iter().any(|r| r.seed == seed) {
            continue;
        }
        let dir = out.join(format!("{}{seed}", effect.name()));
        let started = std::time::Instant::now();
        let result: OutsideResult = run_outside_scene(seed, effect, &dir, &fit, &options)?;
        println!(
            "{seed} {} {} {:.3}: direction {:?}°, magnitude {:?}, held-out {:+.1} %, train {:+.1} %, cause {} ({:.0} s) {}",
            result.preset,
            result.effect,
            result.magnitude,
            result
                .direction_error_deg
                .map(|d| (d * 10.0).round() / 10.0),
            result
                .magnitude_relative_error
                .map(|m| (m * 1000.0).round() / 1000.0),
            -100.0 * result.held_out_reduction,
            -100.0 * result.train_reduction,
            result.cause,
            started.elapsed().as_secs_f64(),
            result.formula
        );
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(out.join("results.jsonl"))?;
        writeln!(file, "{}", serde_json::to_string(&result)?)?;
    }
    Ok(())
}
