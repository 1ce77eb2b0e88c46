//! The full hidden-effect evaluation of issue 6:
//!
//!     cargo run --release -p dm-diagnose --example diagnose_eval -- OUT_DIR [HIDDEN] [NULL] [FIRST_SEED] [SHARD/SHARDS] [--fit-candidates] [--quick-fit]
//!
//! synthesises HIDDEN scenes (default 16) with a seeded random effect,
//! preset and magnitude and NULL scenes (default 4) without, fits and
//! diagnoses each, and writes OUT_DIR/results.jsonl (one line per scene,
//! appended as scenes finish, so an interrupted run keeps its scenes and a
//! rerun skips finished steps) and OUT_DIR/confusion.md over every line
//! of results.jsonl. With `SHARD/SHARDS` (e.g. `0/2`) the run takes every
//! SHARDS-th scene from the SHARD-th, so several processes can share one
//! OUT_DIR. Scenes are fitted with `evaluation_fit_options` (6 + 6
//! material steps), or with `--quick-fit` the 3 + 1 steps of sessions
//! one to fourteen (a scene's model fitted with the other options is
//! fitted again).

use dm_diagnose::DiagnoseOptions;
use dm_diagnose::evaluation::{
    SceneResult, confusion_markdown, evaluation_fit_options, quick_fit_options, run_scene,
};
use std::io::Write;
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    // `--fit-candidates` anywhere: score candidates by fits from the start.
    let fit_candidates = args.iter().any(|a| a == "--fit-candidates");
    let fit = if args.iter().any(|a| a == "--quick-fit") {
        quick_fit_options()
    } else {
        evaluation_fit_options()
    };
    args.retain(|a| a != "--fit-candidates" && a != "--quick-fit");
    let out = PathBuf::from(
        args.first()
            .ok_or("usage: diagnose_eval OUT_DIR [HIDDEN] [NULL] [FIRST_SEED] [SHARD/SHARDS] [--fit-candidates] [--quick-fit]")?,
    );
    let hidden: u64 = args.get(1).map_or(Ok(16), |s| s.parse())?;
    let null: u64 = args.get(2).map_or(Ok(4), |s| s.parse())?;
    let first: u64 = args.get(3).map_or(Ok(1000), |s| s.parse())?;
    let (shard, shards): (usize, usize) = match args.get(4) {
        None => (0, 1),
        Some(s) => {
            let (a, b) = s.split_once('/').ok_or("SHARD/SHARDS, e.g. 0/2")?;
            (a.parse()?, b.parse::<usize>()?.max(1))
        }
    };
    std::fs::create_dir_all(&out)?;
    let options = DiagnoseOptions {
        fit_candidates,
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
    for (seed, is_null) in jobs.into_iter().skip(shard).step_by(shards) {
        let dir = out.join(format!(
            "{}{}",
            if is_null { "null" } else { "hidden" },
            seed
        ));
        let start = std::time::Instant::now();
        match run_scene(seed, is_null, &dir, &fit, &options) {
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
