//! `dm-synth`: writes a synthetic measured scene bundle and, outside it,
//! the ground truth.

use anyhow::{Context, Result};
use clap::Parser;
use dm_synth::sensor::CaptureSink;
use dm_synth::{SynthConfig, generate_with_capture};
use dm_synth_capture::SynthCaptureSink;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

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
    let mut capture = cli.capture_out.as_deref().map(SynthCaptureSink::new);
    let truth = generate_with_capture(
        &cli.config,
        &cli.out,
        &truth_path,
        capture.as_mut().map(|c| c as &mut dyn CaptureSink),
        &mut report,
    )
    .with_context(|| format!("generating scene into {}", cli.out.display()))?;
    if let Some(capture) = capture {
        capture.finish().context("closing the capture")?;
    }
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
