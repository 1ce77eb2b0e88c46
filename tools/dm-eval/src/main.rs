//! `dm-eval`: the benchmark's future-prediction metrics of a world model on
//! a scene bundle (method.md §9; docs/metrics.md): one open-loop rollout
//! from frame 0 driven by the observed hand track, scored per frame and
//! per split; writes metrics.json, metrics.md and per-frame plots.

use anyhow::{Context, Result, bail};
use clap::Parser;
use dm_bundle::Bundle;
use dm_eval::lpips::{Lpips, LpipsPaths, MAKE_TARGET};
use dm_eval::report::{RunInfo, write_report};
use dm_eval::{EvalOptions, evaluate};
use dm_model::WorldModel;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Parser, Debug)]
#[command(
    name = "dm-eval",
    about = "Future-prediction metrics (Chamfer, Track, IoU, PSNR, SSIM, LPIPS) of a world model on a scene"
)]
struct EvalArgs {
    /// Model directory with model.json (dm-fit's output).
    model_dir: PathBuf,
    /// Scene bundle directory.
    bundle: PathBuf,
    /// Output directory (created; existing files are replaced atomically).
    #[arg(long)]
    out: PathBuf,
    /// Camera of the image metrics (the protocol uses camera 0).
    #[arg(long, default_value_t = 0)]
    camera: usize,
    /// Frames to roll out and score (default: the whole clip).
    #[arg(long)]
    frames: Option<usize>,
    /// LPIPS cache directory (default: $DM_LPIPS_DIR, else the workspace's
    /// .cache/lpips, built by `make lpips`).
    #[arg(long)]
    lpips_dir: Option<PathBuf>,
    /// Report LPIPS as null instead of failing when its network is missing.
    #[arg(long)]
    skip_lpips: bool,
    /// Threads of the LPIPS network (0: all cores).
    #[arg(long, default_value_t = 0)]
    lpips_threads: usize,
}

fn main() -> Result<()> {
    let args = EvalArgs::parse();
    let model_json = args.model_dir.join("model.json");
    let model: WorldModel = dm_bundle::read_json(&model_json)
        .with_context(|| format!("reading the model in {}", args.model_dir.display()))?;
    let bundle = Bundle::open(&args.bundle)
        .with_context(|| format!("reading bundle {}", args.bundle.display()))?;

    let lpips_dir = args
        .lpips_dir
        .clone()
        .unwrap_or_else(LpipsPaths::default_cache_dir);
    let (mut lpips, lpips_note) = match LpipsPaths::in_dir(&lpips_dir)
        .and_then(|paths| Ok((Lpips::load(&paths, args.lpips_threads)?, paths)))
    {
        Ok((network, paths)) => (Some(network), paths.model.display().to_string()),
        Err(e) if args.skip_lpips => {
            eprintln!("warning: LPIPS skipped (reported as null): {e}");
            (None, format!("skipped: {e}"))
        }
        Err(e) => {
            return Err(e).with_context(|| {
                format!(
                    "loading LPIPS (run `{MAKE_TARGET}`, or pass --skip-lpips to report it as null)"
                )
            });
        }
    };

    let frames = args
        .frames
        .unwrap_or(bundle.frame_count())
        .min(bundle.frame_count());
    if frames < 2 {
        bail!("--frames must be at least 2");
    }
    let bar = ProgressBar::new(2 * frames as u64 - 1);
    bar.set_style(
        ProgressStyle::with_template("{msg:8} [{bar:40}] {pos}/{len} {elapsed}")?
            .progress_chars("=> "),
    );
    let start = Instant::now();
    // The fitted splats when dm-appearance made them, else particle spheres.
    let splats = if dm_appearance::store::has_appearance(&args.model_dir) {
        let (gaussians, _) = dm_appearance::load_appearance(&args.model_dir, &model)
            .with_context(|| format!("reading the splats in {}", args.model_dir.display()))?;
        Some(gaussians)
    } else {
        None
    };
    let options = EvalOptions {
        camera: args.camera,
        frames: Some(frames),
        splats,
    };
    let renderer = dm_eval::renderer_name(&options).to_string();
    let evaluation = evaluate(
        &model,
        &bundle,
        &options,
        lpips.as_mut(),
        &mut |stage, t| {
            bar.set_message(stage);
            let done = if stage == "rollout" {
                t
            } else {
                frames - 1 + t
            };
            bar.set_position(done as u64);
        },
    )
    .context("evaluating the world model (nothing was written)")?;
    let metrics = evaluation.metrics;
    bar.finish_and_clear();
    let seconds = start.elapsed().as_secs_f64();

    let run = RunInfo {
        bundle: args.bundle.display().to_string(),
        model: args.model_dir.display().to_string(),
        camera: args.camera,
        camera_name: bundle.meta.cameras[args.camera].name.clone(),
        frames,
        split: bundle.meta.split,
        lpips: lpips_note,
        renderer,
        rollout_and_metrics_seconds: seconds,
        lpips_ms_per_frame: lpips
            .is_some()
            .then(|| 1e3 * evaluation.lpips_seconds / frames as f64),
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let paths = write_report(&args.out, &metrics, &run)?;
    print!("{}", dm_eval::report::markdown(&metrics, &run));
    println!(
        "\ndm-eval: {frames} frames in {seconds:.1} s; wrote {}, {} and {} plots in {}",
        paths.json.display(),
        paths.markdown.display(),
        paths.plots.len(),
        args.out.join(dm_eval::report::PLOTS_DIR).display()
    );
    Ok(())
}
