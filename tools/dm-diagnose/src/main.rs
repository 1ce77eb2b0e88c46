//! `dm-diagnose MODEL_DIR BUNDLE --out DIR [--truth FILE]`: shows where a
//! fitted model departs from the observations, names the physical cause,
//! extends the model with it and measures the held-out gain (issue 6).

use anyhow::{Context, Result};
use clap::Parser;
use dm_diagnose::{DiagnoseOptions, NONE_THRESHOLD, diagnose};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(
    name = "dm-diagnose",
    about = "Diagnose a fitted model: error maps, the physical cause, the extended model and its gain"
)]
struct Cli {
    /// Fitted model directory (dm-fit's output, with model.json).
    model_dir: PathBuf,
    /// The scene bundle the model was fitted to.
    bundle: PathBuf,
    /// Output directory (diagnosis.json, report.md, plots, extended_model/).
    #[arg(long)]
    out: PathBuf,
    /// dm-synth's truth file: compare the named effect and its parameters.
    #[arg(long)]
    truth: Option<PathBuf>,
    /// Material Adam steps of the refit with the effect in place.
    #[arg(long, default_value_t = 2)]
    refit_iters: usize,
    /// Held-out score below which the cause is `none`.
    #[arg(long, default_value_t = NONE_THRESHOLD)]
    threshold: f64,
    /// Score each candidate by a fit from the start with its effect in
    /// place (the model's own dm-fit options; one fit per candidate).
    #[arg(long)]
    fit_candidates: bool,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template("{msg:>32} [{bar:30}] {pos}/{len} {elapsed}")
            .context("progress template")?
            .progress_chars("=> "),
    );
    let mut progress = |stage: &str, done: usize, total: usize| {
        if bar.message() != stage {
            bar.set_message(stage.to_string());
            bar.set_length(total as u64);
        }
        bar.set_position(done as u64);
    };
    let options = DiagnoseOptions {
        refit_iters: cli.refit_iters,
        none_threshold: cli.threshold,
        fit_candidates: cli.fit_candidates,
    };
    let d = diagnose(
        &cli.model_dir,
        &cli.bundle,
        &cli.out,
        cli.truth.as_deref(),
        &options,
        &mut progress,
    )
    .with_context(|| {
        format!(
            "diagnosing {} on {}",
            cli.model_dir.display(),
            cli.bundle.display()
        )
    })?;
    bar.finish_and_clear();
    println!(
        "cause {} (confidence {:.2}); test track {:.2} → {:.2} mm; wrote {}",
        d.cause,
        d.confidence,
        1e3 * d.gain.track_before,
        1e3 * d.gain.track_after,
        cli.out.join("report.md").display()
    );
    Ok(())
}
