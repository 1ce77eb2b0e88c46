//! The full hidden-effect evaluation of the diagnosis (docs/diagnose.md):
//!
//!     cargo run --release -p dm-studies --example diagnose_eval -- OUT_DIR [HIDDEN] [NULL] [FIRST_SEED] [SHARD/SHARDS] [--fit-candidates] [--quick-fit] [VARIANT OPTIONS]
//!
//! synthesises HIDDEN scenes (default 16) with a seeded random effect,
//! preset and magnitude and NULL scenes (default 4) without, fits and
//! diagnoses each, and writes OUT_DIR/results.jsonl (one line per scene,
//! appended as scenes finish, so an interrupted run keeps its scenes and a
//! rerun skips the scenes it holds and reuses the fits of the others) and OUT_DIR/confusion.md over every line
//! of results.jsonl. With `SHARD/SHARDS` (e.g. `0/2`) the run takes every
//! SHARDS-th scene from the SHARD-th, so several processes can share one
//! OUT_DIR. Scenes are fitted with `evaluation_fit_options` (6 + 6
//! material steps), or with `--quick-fit` the 3 + 1 steps of
//! `quick_fit_options` (a scene's model fitted with the other options is
//! fitted again). The variant options (`--help`; `oracle_gain` takes the
//! same) change one scene or fit setting, the scene directories named
//! with its suffix (e.g. `hidden1023-p3000`).

use clap::Parser;
use dm_diagnose::DiagnoseOptions;
use dm_studies::diagnosis_evaluation::{
    SceneResult, SceneVariant, confusion_markdown, evaluation_fit_options, quick_fit_options,
    run_scene,
};
use std::io::Write;
use std::path::PathBuf;

/// Synthesises, fits and diagnoses the hidden-effect and null scenes of
/// the diagnosis evaluation and tabulates the named causes.
#[derive(Parser)]
struct Args {
    /// Where the scenes, fits, diagnoses, results.jsonl and confusion.md go.
    out: PathBuf,
    /// Hidden-effect scenes, seeds FIRST_SEED, FIRST_SEED + 1, ...
    #[arg(default_value_t = 16)]
    hidden: u64,
    /// Null scenes, seeds FIRST_SEED + 500, ...
    #[arg(default_value_t = 4)]
    null: u64,
    #[arg(default_value_t = 1000)]
    first_seed: u64,
    /// Take every SHARDS-th scene from the SHARD-th (e.g. 0/2), so several
    /// processes can share one OUT_DIR.
    #[arg(value_name = "SHARD/SHARDS", value_parser = dm_studies::parse_shard)]
    shard: Option<(usize, usize)>,
    /// Score the candidates by fits from the start.
    #[arg(long)]
    fit_candidates: bool,
    /// Fit with `quick_fit_options`: 3 + 1 material steps.
    #[arg(long)]
    quick_fit: bool,
    /// Also compute each scene's detection limits (`detection_limit` in
    /// results.jsonl; about 50 more rollouts per scene).
    #[arg(long)]
    limits: bool,
    // A scene or fit setting changed (scene directories get its suffix).
    #[command(flatten)]
    variant: SceneVariant,
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let Args {
        out,
        hidden,
        null,
        first_seed: first,
        shard,
        fit_candidates,
        quick_fit,
        limits,
        variant,
    } = Args::parse();
    let fit = if quick_fit {
        quick_fit_options()
    } else {
        evaluation_fit_options()
    };
    let (shard, shards) = shard.unwrap_or((0, 1));
    std::fs::create_dir_all(&out)?;
    // The naming is evaluated here; the body-force discovery has its own
    // evaluation (discover_eval) and would only add its minute per scene.
    let options = DiagnoseOptions {
        fit_candidates,
        discover_iters: 0,
        detect_steps: if limits {
            dm_diagnose::detectability::DEFAULT_DETECT_STEPS
        } else {
            0
        },
        ..DiagnoseOptions::default()
    };
    let mut results: Vec<SceneResult> = Vec::new();
    // Interleave null scenes among the hidden ones so a partial run has both.
    let every = hidden.checked_div(null).map_or(u64::MAX, |r| r.max(1) + 1);
    let mut jobs = Vec::new();
    let (mut h, mut n) = (0, 0);
    let mut i = 0;
    while h < hidden || n < null {
        let is_null = n < null && (i % every == every - 1 || h >= hidden);
        if is_null {
            jobs.push((first + 500 + n, true));
            n += 1;
        } else {
            jobs.push((first + h, false));
            h += 1;
        }
        i += 1;
    }
    // Scenes already in results.jsonl are not diagnosed again.
    let done: Vec<SceneResult> = std::fs::read_to_string(out.join("results.jsonl"))
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect();
    for (seed, is_null) in jobs.into_iter().skip(shard).step_by(shards) {
        if done.iter().any(|r| r.seed == seed) {
            continue;
        }
        let kind = if is_null { "null" } else { "hidden" };
        let dir = variant.scene_dir(&out, &format!("{kind}{seed}"));
        let start = std::time::Instant::now();
        match run_scene(seed, is_null, &variant, &dir, &fit, &options) {
            Ok((r, _)) => {
                println!(
                    "seed {seed}: {} {} (hidden {}{}) → {} (conf {:.2}, best {:.3}), test track {:.2} → {:.2} mm, {:.0} s",
                    r.preset,
                    if r.expected == r.cause { "OK " } else { "BAD" },
                    r.hidden,
                    r.magnitude.map(|m| format!(":{m:.3}")).unwrap_or_default(),
                    r.cause,
                    r.confidence,
                    r.best_score,
                    1e3 * r.track_before,
                    1e3 * r.track_after,
                    start.elapsed().as_secs_f64()
                );
                let mut f = std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(out.join("results.jsonl"))?;
                writeln!(f, "{}", serde_json::to_string(&r)?)?;
                drop(f);
                results.push(r);
                // Every shard's scenes so far, not only this process's.
                let all: Vec<SceneResult> = std::fs::read_to_string(out.join("results.jsonl"))?
                    .lines()
                    .filter_map(|l| serde_json::from_str(l).ok())
                    .collect();
                std::fs::write(out.join("confusion.md"), confusion_markdown(&all))?;
            }
            Err(e) => println!("seed {seed}: failed: {e}"),
        }
    }
    println!("{}", confusion_markdown(&results));
    Ok(())
}
