//! `dm-synth`: writes a synthetic measured scene bundle and, outside it,
//! the ground truth.

use anyhow::{Context, Result};
use clap::Parser;
use dm_synth::sensor::CaptureSink;
use dm_synth::{Progress, SynthConfig, TruthFile, generate_with_capture};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};

#[derive(Parser, Debug)]
#[command(
    name = "dm-synth",
    about = "Synthesise a measured scene with known ground truth"
)]
struct Cli {
    #[command(flatten)]
    config: SynthConfig,
    /// Output bundle directory (must not exist).
    #[arg(long)]
    out: PathBuf,
    /// Ground-truth JSON (default: OUT.truth.json, beside the bundle).
    #[arg(long)]
    truth: Option<PathBuf>,
    /// Also write the raw capture the rig records (per-camera colour MP4,
    /// millimetre depth PNGs, calibration.json; docs/capture.md) to this
    /// directory, which must not exist.
    #[arg(long)]
    capture_out: Option<PathBuf>,
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let truth_path = cli.truth.clone().unwrap_or_else(|| {
        let mut name = cli.out.file_name().unwrap_or_default().to_os_string();
        name.push(".truth.json");
        cli.out.with_file_name(name)
    });
    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template("{msg:>18} [{bar:40}] {pos}/{len} {elapsed}")
            .context("progress template")?
            .progress_chars("=> "),
    );
    let mut report = |stage: &str, done: usize, total: usize| {
        if bar.message() != stage {
            bar.set_message(stage.to_string());
            bar.set_length(total as u64);
        }
        bar.set_position(done as u64);
    };
    let truth = generate(&cli, &truth_path, &mut report)?;
    bar.finish_and_clear();
    println!(
        "wrote {} ({} preset, action {}, effect {}) and truth {}",
        cli.out.display(),
        truth.preset,
        truth.action,
        truth.effect.as_ref().map_or("none", |e| e.name.as_str()),
        truth_path.display()
    );
    if let Some(dir) = &cli.capture_out {
        println!("wrote capture {}", dir.display());
    }
    Ok(())
}

/// The scene, and its raw capture where `--capture-out` asks for one.
#[cfg(feature = "capture")]
fn generate(cli: &Cli, truth_path: &Path, report: Progress<'_>) -> Result<TruthFile> {
    let mut capture = cli
        .capture_out
        .as_deref()
        .map(dm_synth_capture::SynthCaptureSink::new);
    let sink = capture.as_mut().map(|c| c as &mut dyn CaptureSink);
    let truth = generate_with_capture(&cli.config, &cli.out, truth_path, sink, report)
        .with_context(|| format!("generating scene into {}", cli.out.display()))?;
    if let Some(capture) = capture {
        capture.finish().context("closing the capture")?;
    }
    Ok(truth)
}

/// The scene; a build without the `capture` feature writes no capture.
#[cfg(not(feature = "capture"))]
fn generate(cli: &Cli, truth_path: &Path, report: Progress<'_>) -> Result<TruthFile> {
    if cli.capture_out.is_some() {
        anyhow::bail!(
            "--capture-out: this dm-synth was built without the `capture` feature (OpenCV); rebuild with it"
        );
    }
    let none: Option<&mut dyn CaptureSink> = None;
    generate_with_capture(&cli.config, &cli.out, truth_path, none, report)
        .with_context(|| format!("generating scene into {}", cli.out.display()))
}
