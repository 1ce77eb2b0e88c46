//! `dm-diagnose MODEL_DIR BUNDLE --out DIR [--truth FILE]`: shows where a
//! fitted model departs from the observations, names the physical cause,
//! extends the model with it and measures the held-out gain.

use anyhow::{Context, Result};
use clap::Parser;
use dm_diagnose::{DiagnoseOptions, diagnose};
use indicatif::{ProgressBar, ProgressStyle};
use std::io::IsTerminal;
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
    #[command(flatten)]
    options: DiagnoseOptions,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    // A bar on a terminal; in a log, a line per step (a tenth of a long stage).
    let terminal = std::io::stderr().is_terminal();
    let bar = if terminal {
        ProgressBar::new(0)
    } else {
        ProgressBar::hidden()
    };
    bar.set_style(
        ProgressStyle::with_template("{msg:>32} [{bar:30}] {pos}/{len} {elapsed}")
            .context("progress template")?
            .progress_chars("=> "),
    );
    let clock = std::time::Instant::now();
    let mut progress = |stage: &str, done: usize, total: usize| {
        if bar.message() != stage {
            bar.set_message(stage.to_string());
            bar.set_length(total as u64);
        }
        bar.set_position(done as u64);
        if !terminal && done.is_multiple_of(total.div_ceil(10).max(1)) {
            eprintln!(
                "dm-diagnose: {stage} {done}/{total} ({:.0} s)",
                clock.elapsed().as_secs_f64()
            );
        }
    };
    let d = diagnose(
        &cli.model_dir,
        &cli.bundle,
        &cli.out,
        cli.truth.as_deref(),
        &cli.options,
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
