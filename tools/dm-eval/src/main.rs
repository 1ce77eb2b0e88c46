//! `dm-eval`: the benchmark's future-prediction metrics of a world model on
//! a scene bundle (method.md §9; docs/metrics.md): one open-loop rollout
//! from frame 0 driven by the observed hand track, scored per frame and
//! per split; writes metrics.json, metrics.md and per-frame plots. With
//! `--suite FILE` it runs a benchmark suite instead (docs/suite.md).

use anyhow::{Context, Result, bail};
use clap::Parser;
use dm_bundle::Bundle;
use dm_eval::lpips::{Lpips, MAKE_TARGET};
use dm_eval::report::{RunInfo, write_report};
use dm_eval::{EvalOptions, evaluate};
use dm_model::WorldModel;
use dm_model::device::Device;
use dm_suite::{Suite, SuiteProgress, run_suite, update_results_markdown};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Parser, Debug)]
#[command(
    name = "dm-eval",
    about = "Future-prediction metrics (Chamfer, Track, IoU, PSNR, SSIM, LPIPS) of a world model on a scene"
)]
struct EvalArgs {
    /// Model directory with model.json (dm-fit's output).
    #[arg(required_unless_present = "suite")]
    model_dir: Option<PathBuf>,
    /// Scene bundle directory.
    #[arg(required_unless_present = "suite")]
    bundle: Option<PathBuf>,
    /// Output directory (created; existing files are replaced atomically).
    /// With --suite: the scenes, fits, cached results, suite.json and
    /// tables.md (rerunning resumes from the cached results).
    #[arg(long)]
    out: PathBuf,
    /// Run the benchmark suite of this file (docs/suite.md) instead of
    /// scoring one model.
    #[arg(long, conflicts_with_all = ["model_dir", "bundle", "frames"])]
    suite: Option<PathBuf>,
    /// With --suite: also write the tables into this Markdown file between
    /// the suite markers (replacing an earlier run's section).
    #[arg(long, requires = "suite")]
    results_md: Option<PathBuf>,
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
    /// Where the rollout's MPM world and residual network run (cuda: the
    /// first NVIDIA GPU; the metrics stay on the CPU).
    #[arg(long, value_enum, default_value_t = Device::Cpu, conflicts_with = "suite")]
    device: Device,
}

fn load_lpips(args: &EvalArgs) -> Result<(Option<Lpips>, String)> {
    let (network, note) = Lpips::load_or_skip(
        args.lpips_dir.as_deref(),
        args.lpips_threads,
        args.skip_lpips,
    )
    .with_context(|| {
        format!("loading LPIPS (run `{MAKE_TARGET}`, or pass --skip-lpips to report it as null)")
    })?;
    if network.is_none() {
        eprintln!("warning: LPIPS {note} (reported as null)");
    }
    Ok((network, note))
}

fn main() -> Result<()> {
    let args = EvalArgs::parse();
    match (&args.suite, &args.model_dir, &args.bundle) {
        (Some(suite), _, _) => suite_main(&args, suite),
        (None, Some(model_dir), Some(bundle)) => eval_main(&args, model_dir, bundle),
        _ => bail!("give MODEL_DIR and BUNDLE, or --suite FILE"),
    }
}

/// `dm-eval --suite FILE --out DIR [--results-md FILE]`.
fn suite_main(args: &EvalArgs, suite_path: &Path) -> Result<()> {
    let suite = Suite::load(suite_path)
        .with_context(|| format!("reading suite {}", suite_path.display()))?;
    let (mut lpips, _) = load_lpips(args)?;
    let command = std::iter::once("dm-eval".to_owned())
        .chain(std::env::args().skip(1))
        .collect::<Vec<_>>()
        .join(" ");
    let bar = ProgressBar::new((suite.scenes.len() * suite.variants.len()) as u64);
    bar.set_style(
        ProgressStyle::with_template("[{bar:30}] {pos}/{len} {elapsed} {prefix} {wide_msg}")?
            .progress_chars("=> "),
    );
    let report = run_suite(
        &suite,
        &args.out,
        lpips.as_mut(),
        &command,
        &mut |event| match event {
            SuiteProgress::Scene { id, .. } => {
                bar.set_prefix(format!("{id}: synthesising"));
            }
            SuiteProgress::Run {
                scene,
                variant,
                index,
                cached,
                ..
            } => {
                bar.set_position(index as u64);
                let note = if cached { " (cached)" } else { "" };
                bar.set_prefix(format!("{scene} / {variant}{note}"));
                let line = format!(
                    "run {}/{}: {scene} / {variant}{note}",
                    index + 1,
                    bar.length().unwrap_or(0)
                );
                // A hidden bar (stderr not a terminal: a log) prints nothing itself.
                if bar.is_hidden() {
                    eprintln!("{line}");
                } else {
                    bar.println(line);
                }
            }
            SuiteProgress::Detail(line) => bar.set_message(line.to_owned()),
        },
    )
    .with_context(|| {
        format!(
            "running suite {} into {}",
            suite_path.display(),
            args.out.display()
        )
    })?;
    bar.finish_and_clear();
    let tables = dm_suite::tables_markdown(&report);
    print!("{tables}");
    if let Some(results_md) = &args.results_md {
        update_results_markdown(results_md, &suite.file.results_heading, &tables)
            .with_context(|| format!("writing the tables into {}", results_md.display()))?;
    }
    let diverged = report
        .runs
        .iter()
        .filter(|r| r.status == dm_suite::RunStatus::Diverged)
        .count();
    println!(
        "\ndm-eval: {} runs ({} cached, {diverged} diverged) in {:.1} s; wrote {} and {}",
        report.runs.len(),
        report.cached_runs,
        report.seconds,
        args.out.join(dm_suite::SUITE_JSON).display(),
        args.out.join(dm_suite::TABLES_MARKDOWN).display()
    );
    Ok(())
}

/// `dm-eval MODEL_DIR BUNDLE --out DIR`.
fn eval_main(args: &EvalArgs, model_dir: &Path, bundle_dir: &Path) -> Result<()> {
    let model_json = model_dir.join("model.json");
    let model = WorldModel::load(&model_json)
        .with_context(|| format!("reading the model in {}", model_dir.display()))?;
    let bundle = Bundle::open(bundle_dir)
        .with_context(|| format!("reading bundle {}", bundle_dir.display()))?;
    let (mut lpips, lpips_note) = load_lpips(args)?;

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
    let splats = if dm_appearance::store::has_appearance(model_dir) {
        let (gaussians, _) = dm_appearance::load_appearance(model_dir, &model)
            .with_context(|| format!("reading the splats in {}", model_dir.display()))?;
        Some(gaussians)
    } else {
        None
    };
    let options = EvalOptions {
        camera: args.camera,
        frames: Some(frames),
        splats,
        device: args.device,
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
        bundle: bundle_dir.display().to_string(),
        model: model_dir.display().to_string(),
        camera: args.camera,
        camera_name: bundle.meta.cameras[args.camera].name.clone(),
        frames,
        split: bundle.meta.split,
        lpips: lpips_note,
        renderer,
        device: args.device,
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
