//! What does the gain search's fitness look like? The training-frame
//! L_dyn of a forward rollout (what `dm-fit`'s CMA-ES minimises) on a
//! log grid of (k_p, k_d) over the search's bounds, for a model fitted up
//! to the gain stage (`dm-fit --iters N --stage2-iters 0 --gain-evals 0
//! --residual none --rgb-iters 0`); the held-out Track beside it, for
//! reading only.
//!
//!     cargo run --release -p dm-studies --example gain_landscape -- BUNDLE MODEL_DIR [--per-decade 2] [--max-log-kp 5]

use anyhow::{Context, Result};
use clap::Parser;
use dm_bundle::Bundle;
use dm_fit::material_fit::train_loss;
use dm_fit::run::GAIN_SEARCH_LOG10;
use dm_model::WorldModel;
use dm_model::metrics::{frame_errors, split_mean};
use rayon::prelude::*;
use std::path::PathBuf;

#[derive(Parser)]
struct Args {
    bundle: PathBuf,
    model_dir: PathBuf,
    /// Grid points per decade of each gain.
    #[arg(long, default_value_t = 2)]
    per_decade: usize,
    /// The grid's largest log10 k_p (the search's bound is 5).
    #[arg(long, default_value_t = LOG_KP[1])]
    max_log_kp: f64,
}

const LOG_KP: [f64; 2] = GAIN_SEARCH_LOG10[0];
const LOG_KD: [f64; 2] = GAIN_SEARCH_LOG10[1];

fn axis([lo, hi]: [f64; 2], per_decade: usize) -> Vec<f64> {
    let steps = ((hi - lo) * per_decade as f64).round() as usize;
    (0..=steps)
        .map(|k| lo + (hi - lo) * k as f64 / steps as f64)
        .collect()
}

fn main() -> Result<()> {
    let args = Args::parse();
    let bundle = Bundle::open(&args.bundle).with_context(|| args.bundle.display().to_string())?;
    let model: WorldModel = dm_bundle::read_json(&args.model_dir.join("model.json"))?;
    let split = bundle.meta.split;
    let frames = split.train[1].min(bundle.frame_count());
    let all = bundle.frame_count();
    let points: Vec<(f64, f64)> = axis([LOG_KP[0], args.max_log_kp], args.per_decade)
        .into_iter()
        .flat_map(|kp| {
            axis(LOG_KD, args.per_decade)
                .into_iter()
                .map(move |kd| (kp, kd))
        })
        .collect();
    let scored: Vec<(f64, f64, f64, f64)> = points
        .par_iter()
        .map(|&(kp, kd)| {
            let mut candidate = model.clone();
            candidate.actuator.kp = 10f64.powf(kp);
            candidate.actuator.kd = 10f64.powf(kd);
            let loss = train_loss(&candidate, &bundle, frames).unwrap_or(f64::INFINITY);
            let held_out = candidate
                .rollout(&bundle, all, &mut |_| {})
                .map(|r| {
                    split_mean(
                        &frame_errors(&r, candidate.surface_count, &bundle.tracks).track,
                        split.test,
                    )
                })
                .unwrap_or(f64::INFINITY);
            (kp, kd, loss, held_out)
        })
        .collect();
    println!(
        "{}: start k_p {:.0}, k_d {:.1}",
        args.bundle.display(),
        model.actuator.kp,
        model.actuator.kd
    );
    println!("log10 kp  log10 kd  train L_dyn (m²)  held-out Track (mm)");
    for (kp, kd, loss, held_out) in &scored {
        println!("{kp:8.2}  {kd:8.2}  {loss:16.4e}  {:19.2}", 1e3 * held_out);
    }
    if let Some(best) = scored.iter().min_by(|a, b| a.2.total_cmp(&b.2)) {
        println!(
            "lowest training loss at k_p {:.3e}, k_d {:.3e} (held-out {:.2} mm)",
            10f64.powf(best.0),
            10f64.powf(best.1),
            1e3 * best.3
        );
    }
    Ok(())
}
