//! `dm-render`: renders a world model's fitted Gaussian splats
//! from a bundle camera, a novel viewpoint or an orbit, following a
//! rollout driven by the bundle's hand track; PNG frames and an MP4.

use anyhow::{Context, Result};
use clap::Parser;
use dm_appearance::ViewChoice;
use dm_appearance::clip::{ClipRequest, parse_frame_range, render_clip};
use dm_bundle::Bundle;
use dm_model::WorldModel;
use dm_model::device::Device;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

#[derive(Parser, Debug)]
#[command(
    name = "dm-render",
    about = "Render a world model's Gaussian splats (made by dm-appearance) along a rollout: PNG frames and an MP4"
)]
struct RenderArgs {
    /// Model directory with model.json, gaussians.ply and appearance.json.
    model_dir: PathBuf,
    /// Scene bundle: roll the model out driven by its hand track (without
    /// it the object stays in its first-frame pose).
    #[arg(long)]
    bundle: Option<PathBuf>,
    /// train:I (bundle camera I), novel (an unseen viewpoint in the widest
    /// gap between the cameras) or orbit (a full circle over the frames).
    #[arg(long, value_parser = clap::value_parser!(ViewChoice))]
    view: ViewChoice,
    /// Clip frames A:B (B exclusive; default: the whole clip, or frame 0
    /// without a bundle, 60 frames for an orbit).
    #[arg(long, value_parser = parse_frame_range)]
    frames: Option<(usize, usize)>,
    /// Output directory (created; frames are frame_NNNNN.png, the video render.mp4).
    #[arg(long)]
    out: PathBuf,
    /// Frames per second of the video (default: the scene's).
    #[arg(long)]
    fps: Option<f64>,
    /// Write PNG frames only (no MP4).
    #[arg(long)]
    no_video: bool,
    /// Where the rollout's MPM world and residual network run (cuda: the
    /// first NVIDIA GPU; the splats are rendered on the CPU).
    #[arg(long, value_enum, default_value_t = Device::Cpu)]
    device: Device,
}

fn main() -> Result<()> {
    let args = RenderArgs::parse();
    let model_json = args.model_dir.join("model.json");
    let model = WorldModel::load(&model_json)
        .with_context(|| format!("reading the model in {}", args.model_dir.display()))?;
    if !dm_appearance::store::has_appearance(&args.model_dir) {
        anyhow::bail!(
            "{} has no fitted splats ({} and {}); run `dm-appearance {} BUNDLE` first",
            args.model_dir.display(),
            dm_appearance::GAUSSIANS_FILE,
            dm_appearance::APPEARANCE_JSON,
            args.model_dir.display()
        );
    }
    let bundle = match &args.bundle {
        Some(path) => {
            Some(Bundle::open(path).with_context(|| format!("reading bundle {}", path.display()))?)
        }
        None => None,
    };
    if let Some(fps) = args.fps
        && !(fps.is_finite() && fps > 0.0)
    {
        anyhow::bail!("--fps must be positive, got {fps}");
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let request = ClipRequest {
        view: args.view,
        frames: args.frames,
        background: [0.0; 3],
        video: !args.no_video,
        fps: args.fps,
        device: args.device,
    };
    let bar = ProgressBar::new(1);
    bar.set_style(
        ProgressStyle::with_template("{msg:8} [{bar:40}] {pos}/{len} {elapsed}")?
            .progress_chars("=> "),
    );
    let summary = render_clip(
        &args.model_dir,
        &model,
        bundle.as_ref(),
        &request,
        &args.out,
        &mut |stage, done, total| {
            bar.set_message(stage);
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        },
    )
    .with_context(|| format!("rendering the splats of {}", args.model_dir.display()))?;
    bar.finish_and_clear();
    println!(
        "dm-render: {} frames ({}) in {}{}",
        summary.frames.len(),
        if summary.rolled_out {
            "following the rollout"
        } else {
            "object at rest"
        },
        args.out.display(),
        summary
            .video
            .map(|v| format!(", video {}", v.display()))
            .unwrap_or_default()
    );
    Ok(())
}
