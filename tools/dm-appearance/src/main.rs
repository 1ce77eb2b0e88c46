//! `dm-appearance`: fits the first-frame Gaussian splats of a world model
//! to its scene's multi-view images (method.md §6) and stores them
//! in the model directory (`gaussians.ply`, `appearance.json`), where
//! dm-render and dm-eval find them.

use anyhow::{Context, Result};
use clap::Parser;
use dm_appearance::fit::DEFAULT_ITERATIONS;
use dm_appearance::{AppearanceOptions, fit_appearance, save_appearance};
use dm_bundle::Bundle;
use dm_model::WorldModel;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(
    name = "dm-appearance",
    about = "Fit first-frame Gaussian splats of a world model to its bundle's views (masked L1 + D-SSIM); writes MODEL_DIR/gaussians.ply and appearance.json"
)]
struct AppearanceArgs {
    /// Model directory with model.json (dm-fit's output); the splats are written here.
    model_dir: PathBuf,
    /// Scene bundle directory the model was made from.
    bundle: PathBuf,
    /// Adam steps (each uses every training view).
    #[arg(long, default_value_t = DEFAULT_ITERATIONS)]
    iters: usize,
    /// Camera left out of the fit and scored as a novel view (default: the
    /// last camera when the bundle has two or more).
    #[arg(long, conflicts_with = "no_holdout")]
    holdout: Option<usize>,
    /// Fit on every camera (no held-out score).
    #[arg(long)]
    no_holdout: bool,
}

fn main() -> Result<()> {
    let args = AppearanceArgs::parse();
    let model_json = args.model_dir.join("model.json");
    let model = WorldModel::load(&model_json)
        .with_context(|| format!("reading the model in {}", args.model_dir.display()))?;
    let bundle = Bundle::open(&args.bundle)
        .with_context(|| format!("reading bundle {}", args.bundle.display()))?;
    let mut options = AppearanceOptions::for_cameras(bundle.meta.cameras.len());
    options.iterations = args.iters;
    if args.no_holdout {
        options.held_out_camera = None;
    } else if args.holdout.is_some() {
        options.held_out_camera = args.holdout;
    }
    let bar = ProgressBar::new(args.iters as u64);
    bar.set_style(
        ProgressStyle::with_template("fit {msg} [{bar:40}] {pos}/{len} {elapsed}/{duration}")?
            .progress_chars("=> "),
    );
    let (gaussians, record) = fit_appearance(&model, &bundle, &options, &mut |step| {
        bar.set_message(format!("loss {:.4}", step.loss));
        bar.inc(1);
    })
    .context("fitting the splats (nothing was written)")?;
    bar.finish_and_clear();
    save_appearance(&args.model_dir, &gaussians, &record)
        .with_context(|| format!("writing the splats into {}", args.model_dir.display()))?;
    println!(
        "dm-appearance: {} Gaussians, {} steps in {:.1} s (loss {:.4} -> {:.4})",
        record.gaussian_count,
        record.iterations,
        record.fit_seconds,
        record.loss_start,
        record.loss_end
    );
    for p in &record.psnr {
        println!(
            "  frame-0 PSNR {:>6}: {:.2} dB ({})",
            p.name,
            p.psnr_db,
            if p.train { "train" } else { "held out" }
        );
    }
    println!(
        "wrote {} and {}",
        args.model_dir.join(dm_appearance::GAUSSIANS_FILE).display(),
        args.model_dir
            .join(dm_appearance::APPEARANCE_JSON)
            .display()
    );
    Ok(())
}
