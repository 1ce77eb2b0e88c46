//! `dm-sim`: open-loop rollout of a scene's world model from its first
//! frame, driven by the observed hand track; writes the trajectory, a
//! summary with track/shape errors per split, and a preview image.

use anyhow::{Context, Result, bail};
use clap::Parser;
use dm_bundle::{Bundle, write_file_atomic, write_json_atomic, write_npy_file};
use dm_model::device::Device;
use dm_model::metrics::{frame_errors, split_mean};
use dm_model::preview::comparison_strip;
use dm_model::{ModelOptions, WorldModel};
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

/// Arguments, saved as the run record in `summary.json`.
#[derive(Parser, Debug, Serialize)]
#[command(
    name = "dm-sim",
    about = "Roll out a scene's world model from its first frame"
)]
struct SimArgs {
    /// Scene bundle directory.
    bundle: PathBuf,
    /// Output directory (created; existing files are replaced atomically).
    #[arg(long)]
    out: PathBuf,
    /// A fitted model directory (dm-fit's output); without it the untrained
    /// model of the bundle is rolled out.
    #[arg(long)]
    model_dir: Option<PathBuf>,
    #[command(flatten)]
    model: ModelOptions,
    /// Frames to roll out (default: the whole clip).
    #[arg(long)]
    frames: Option<usize>,
    /// Where the MPM world and the residual network run (cuda: the first
    /// NVIDIA GPU).
    #[arg(long, value_enum, default_value_t = Device::Cpu)]
    device: Device,
}

#[derive(Serialize)]
struct SplitErrors {
    train: f64,
    test: f64,
}

#[derive(Serialize)]
struct Summary<'a> {
    options: &'a SimArgs,
    frames: usize,
    particles: usize,
    seconds: f64,
    material: serde_json::Value,
    track_error_m: SplitErrors,
    chamfer_m: SplitErrors,
    per_frame_track_error_m: Vec<f64>,
    preview: String,
}

fn main() -> Result<()> {
    let args = SimArgs::parse();
    let bundle = Bundle::open(&args.bundle)
        .with_context(|| format!("reading bundle {}", args.bundle.display()))?;
    let model: WorldModel = match &args.model_dir {
        Some(dir) => WorldModel::load(&dir.join("model.json"))
            .with_context(|| format!("reading the fitted model in {}", dir.display()))?,
        None => {
            WorldModel::from_bundle(&bundle, &args.model).context("building the world model")?
        }
    };
    let frames = args
        .frames
        .unwrap_or(bundle.frame_count())
        .min(bundle.frame_count());
    if frames < 2 {
        bail!("--frames must be at least 2");
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;

    let bar = ProgressBar::new(frames as u64 - 1);
    bar.set_style(
        ProgressStyle::with_template("rollout [{bar:40}] {pos}/{len} frames {elapsed}")?
            .progress_chars("=> "),
    );
    let start = Instant::now();
    let rollout = model
        .rollout_on(&bundle, frames, args.device, &mut |t| {
            bar.set_position(t as u64)
        })
        .context("rolling out the world model (nothing was written)")?;
    let seconds = start.elapsed().as_secs_f64();
    bar.finish_and_clear();

    let n = model.particles.len();
    let mut trajectory = ndarray::Array3::<f32>::zeros((frames, n, 3));
    for (t, frame) in rollout.iter().enumerate() {
        for (i, p) in frame.iter().enumerate() {
            for a in 0..3 {
                trajectory[[t, i, a]] = p[a];
            }
        }
    }
    let rollout_path = args.out.join("rollout.npy");
    write_file_atomic(&rollout_path, |temp| {
        write_npy_file(temp, &trajectory).map_err(|e| std::io::Error::other(e.to_string()))
    })?;

    let errors = frame_errors(&rollout, model.surface_count, &bundle.tracks);
    let split = &bundle.meta.split;
    let clip = |r: [usize; 2]| [r[0].min(frames), r[1].min(frames)];
    let last = frames - 1;
    let shown: Vec<usize> = [0, last / 3, (2 * last) / 3, last].into_iter().collect();
    let radius = model.splat_radius();
    let strip = comparison_strip(&bundle, 0, &rollout, &model.colors, radius, &shown)?;
    let preview_path = args.out.join("preview.png");
    write_file_atomic(&preview_path, |temp| {
        strip
            .save_with_format(temp, image::ImageFormat::Png)
            .map_err(|e| std::io::Error::other(e.to_string()))
    })?;

    let (e_median, nu_median) = model.material_medians();
    let summary = Summary {
        options: &args,
        frames,
        particles: n,
        seconds,
        material: serde_json::json!({ "E_median_pa": e_median, "nu_median": nu_median }),
        track_error_m: SplitErrors {
            train: split_mean(&errors.track, clip(split.train)),
            test: split_mean(&errors.track, clip(split.test)),
        },
        chamfer_m: SplitErrors {
            train: split_mean(&errors.chamfer, clip(split.train)),
            test: split_mean(&errors.chamfer, clip(split.test)),
        },
        per_frame_track_error_m: errors.track.clone(),
        preview: preview_path.display().to_string(),
    };
    write_json_atomic(&args.out.join("summary.json"), &summary)?;
    println!(
        "dm-sim: {:?} scene, {} frames, {} particles, {:.1} s ({:.1} frames/s)",
        bundle.meta.category,
        frames,
        n,
        seconds,
        (frames - 1) as f64 / seconds
    );
    println!(
        "  track error (mm)  train {:.1}  test {:.1}   chamfer (mm)  train {:.1}  test {:.1}",
        1e3 * summary.track_error_m.train,
        1e3 * summary.track_error_m.test,
        1e3 * summary.chamfer_m.train,
        1e3 * summary.chamfer_m.test
    );
    let which = if args.model_dir.is_some() {
        "fitted"
    } else {
        "untrained"
    };
    println!("  {which} material: E {e_median:.3e} Pa, nu {nu_median:.2}");
    println!(
        "  wrote {}, {}, {}",
        rollout_path.display(),
        args.out.join("summary.json").display(),
        preview_path.display()
    );
    println!("  preview: top row = observed camera 0, bottom row = model, frames {shown:?}");
    Ok(())
}
