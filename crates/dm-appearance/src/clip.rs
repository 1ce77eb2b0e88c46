//! A rendered clip: the Gaussians following a rollout (or at rest), seen
//! by the chosen cameras, written as PNG frames and an MP4.
//!
//! The MP4 is written by OpenCV's `VideoWriter` (feature `video`; H.264
//! as `avc1`, MPEG-4 part 2 as `mp4v` where OpenCV's FFmpeg has no H.264
//! encoder), from the PNG frames just written.

use std::path::{Path, PathBuf};

use dm_bundle::write_file_atomic;
use dm_splat::{RenderSettings, render};
use dm_view::Camera;

use crate::AppearanceError;
use crate::follow::SplatFollower;
use crate::quality::to_rgb8;

/// Name of frame `t`'s PNG in the output directory.
pub fn frame_file_name(t: usize) -> String {
    format!("frame_{t:05}.png")
}

pub const VIDEO_FILE: &str = "render.mp4";

/// Renders frames `range` (clip frame indices) and writes one PNG each
/// into `out_dir`. `positions[t]` are the particles of clip frame `t`
/// (frame 0 first; `None`: the Gaussians stay at rest), `cameras[k]` the
/// camera of the k-th rendered frame. Returns the written paths.
pub fn render_frames(
    follower: &mut SplatFollower,
    positions: Option<&[Vec<[f32; 3]>]>,
    range: std::ops::Range<usize>,
    cameras: &[Camera],
    background: [f64; 3],
    out_dir: &Path,
    progress: &mut dyn FnMut(usize),
) -> Result<Vec<PathBuf>, AppearanceError> {
    let settings = RenderSettings {
        background,
        ..RenderSettings::default()
    };
    let mut written = Vec::with_capacity(range.len());
    let mut at = 0usize;
    for (k, t) in range.clone().enumerate() {
        if let Some(positions) = positions {
            // Skinning is incremental: walk every frame up to t.
            while at < t {
                at += 1;
                follower.advance(&positions[at])?;
            }
        }
        let camera = &cameras[k.min(cameras.len().saturating_sub(1))];
        let out = render(follower.gaussians(), camera, &settings)?;
        let image = to_rgb8(out.image(), camera.width, camera.height);
        let path = out_dir.join(frame_file_name(t));
        write_file_atomic(&path, |tmp| {
            image
                .save_with_format(tmp, image::ImageFormat::Png)
                .map_err(std::io::Error::other)
        })?;
        written.push(path);
        progress(k + 1);
    }
    Ok(written)
}

/// Encodes `out_dir/frame_NNNNN.png` for clip frames `frames` into
/// `out_dir/render.mp4` (written under a temporary name, then renamed).
#[cfg(feature = "video")]
pub fn encode_mp4(
    out_dir: &Path,
    frames: std::ops::Range<usize>,
    fps: f64,
) -> Result<PathBuf, AppearanceError> {
    use opencv::core::Size;
    use opencv::prelude::{MatTraitConst, VideoWriterTrait, VideoWriterTraitConst};
    use opencv::{imgcodecs, videoio};

    let path = out_dir.join(VIDEO_FILE);
    // OpenCV picks the container from the extension: keep `.mp4` last.
    let tmp = out_dir.join(format!(".{}.tmp.{VIDEO_FILE}", std::process::id()));
    let video_err = |problem: String| AppearanceError::Video {
        path: path.clone(),
        problem,
    };
    let cv = |what: &str, e: opencv::Error| video_err(format!("OpenCV {what}: {e}"));
    let read = |t: usize| -> Result<opencv::core::Mat, AppearanceError> {
        let frame = out_dir.join(frame_file_name(t));
        let name = frame
            .to_str()
            .ok_or_else(|| video_err(format!("frame path {} is not UTF-8", frame.display())))?;
        let image =
            imgcodecs::imread(name, imgcodecs::IMREAD_COLOR).map_err(|e| cv("imread", e))?;
        if image.empty() {
            return Err(video_err(format!(
                "could not read frame {}",
                frame.display()
            )));
        }
        Ok(image)
    };
    let first = read(frames.start)?;
    let size = first.size().map_err(|e| cv("frame size", e))?;
    let tmp_name = tmp
        .to_str()
        .ok_or_else(|| video_err("output path is not UTF-8".into()))?
        .to_string();
    let mut writer = None;
    for code in [['a', 'v', 'c', '1'], ['m', 'p', '4', 'v']] {
        let fourcc = videoio::VideoWriter::fourcc(code[0], code[1], code[2], code[3])
            .map_err(|e| cv("fourcc", e))?;
        let candidate = videoio::VideoWriter::new(
            &tmp_name,
            fourcc,
            fps,
            Size::new(size.width, size.height),
            true,
        )
        .map_err(|e| cv("VideoWriter", e))?;
        if candidate.is_opened().map_err(|e| cv("VideoWriter", e))? {
            writer = Some(candidate);
            break;
        }
    }
    let Some(mut writer) = writer else {
        let _ = std::fs::remove_file(&tmp);
        return Err(video_err(
            "OpenCV could open no MP4 encoder (avc1, mp4v); is libopencv-dev built with FFmpeg? (`make setup`)".into(),
        ));
    };
    let mut write_all = || -> Result<(), AppearanceError> {
        writer.write(&first).map_err(|e| cv("write", e))?;
        for t in frames.start + 1..frames.end {
            writer.write(&read(t)?).map_err(|e| cv("write", e))?;
        }
        writer.release().map_err(|e| cv("release", e))
    };
    if let Err(e) = write_all() {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    std::fs::rename(&tmp, &path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        video_err(format!("renaming the encoded video into place: {e}"))
    })?;
    Ok(path)
}

/// Without the `video` feature there is no encoder: an error saying so.
#[cfg(not(feature = "video"))]
pub fn encode_mp4(
    out_dir: &Path,
    _frames: std::ops::Range<usize>,
    _fps: f64,
) -> Result<PathBuf, AppearanceError> {
    Err(AppearanceError::Video {
        path: out_dir.join(VIDEO_FILE),
        problem: "built without the `video` feature (OpenCV); rebuild with it or pass --no-video"
            .into(),
    })
}

/// What [`render_clip`] renders.
#[derive(Clone, Debug, PartialEq)]
pub struct ClipRequest {
    pub view: crate::ViewChoice,
    /// Clip frames `[start, end)`; `None`: the whole clip with a bundle,
    /// else frame 0 alone (orbit: [`STATIC_ORBIT_FRAMES`] frames at rest).
    pub frames: Option<(usize, usize)>,
    pub background: [f64; 3],
    /// Encode `render.mp4` (needs the `video` feature).
    pub video: bool,
    /// Frames per second of the video (`None`: the scene's).
    pub fps: Option<f64>,
    /// Where the rollout's MPM world and residual network run.
    pub device: dm_model::device::Device,
}

/// Frames of an orbit around the object at rest (no bundle to roll out).
pub const STATIC_ORBIT_FRAMES: usize = 60;

/// What [`render_clip`] wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct ClipSummary {
    pub frames: Vec<PathBuf>,
    pub video: Option<PathBuf>,
    /// Whether the Gaussians followed a rollout driven by the bundle's
    /// hand track (else they stayed in their frame-0 pose).
    pub rolled_out: bool,
}

/// The most frames one render writes: an hour at 30 fps (without a bundle
/// nothing else bounds the range).
pub const MAX_RENDER_FRAMES: usize = 108_000;

/// Parses `A:B` (clip frames `A..B`, B exclusive).
pub fn parse_frame_range(s: &str) -> Result<(usize, usize), String> {
    let bad = || format!("`{s}` is not a frame range: use A:B with A < B (B exclusive), e.g. 0:24");
    let (a, b) = s.split_once(':').ok_or_else(bad)?;
    let (a, b): (usize, usize) = (
        a.trim().parse().map_err(|_| bad())?,
        b.trim().parse().map_err(|_| bad())?,
    );
    if a >= b {
        return Err(bad());
    }
    if b - a > MAX_RENDER_FRAMES {
        return Err(format!(
            "`{s}` asks for {} frames, more than the {MAX_RENDER_FRAMES} one render writes",
            b - a
        ));
    }
    Ok((a, b))
}

/// Renders the fitted splats of the model in `model_dir` as the request
/// asks: with a bundle the model is rolled out from frame 0 driven by its
/// hand track and the Gaussians follow by LBS; without one they stay at
/// rest. Writes PNG frames (and the MP4) into `out_dir`, which must exist.
pub fn render_clip(
    model_dir: &Path,
    model: &dm_model::WorldModel,
    bundle: Option<&dm_bundle::Bundle>,
    request: &ClipRequest,
    out_dir: &Path,
    progress: &mut dyn FnMut(&'static str, usize, usize),
) -> Result<ClipSummary, AppearanceError> {
    let (gaussians, record) = crate::store::load_appearance(model_dir, model)?;
    let camera_specs = match bundle {
        Some(b) => b.meta.cameras.clone(),
        None => record.cameras.clone(),
    };
    let cameras: Vec<Camera> = camera_specs
        .iter()
        .enumerate()
        .map(|(i, spec)| crate::views::camera_from_spec(spec, i))
        .collect::<Result<_, _>>()?;
    let up = bundle.map_or(record.up, |b| b.meta.up_axis.unit_vector());
    let clip_frames = bundle.map(dm_bundle::Bundle::frame_count);
    let (start, end) = match (request.frames, clip_frames) {
        (Some((a, b)), Some(t)) if b > t => {
            return Err(AppearanceError::InvalidOption {
                option: "--frames".into(),
                problem: format!("{a}:{b} ends after the clip's {t} frames"),
            });
        }
        (Some(range), _) => range,
        (None, Some(t)) => (0, t),
        (None, None) if request.view == crate::ViewChoice::Orbit => (0, STATIC_ORBIT_FRAMES),
        (None, None) => (0, 1),
    };
    let centre = crate::views::particle_centre(&model.particles);
    let view_cameras = crate::views::cameras_for(request.view, &cameras, &centre, up, end - start)?;
    let positions = match bundle {
        Some(b) => Some(model.rollout_on(b, end, request.device, &mut |t| {
            progress("rollout", t, end - 1)
        })?),
        None => None,
    };
    let mut follower = SplatFollower::new(gaussians, &model.particles)?;
    let total = end - start;
    let frames = render_frames(
        &mut follower,
        positions.as_deref(),
        start..end,
        &view_cameras,
        request.background,
        out_dir,
        &mut |k| progress("render", k, total),
    )?;
    let video = if request.video {
        let fps = request
            .fps
            .unwrap_or_else(|| bundle.map_or(record.fps, |b| b.meta.fps));
        Some(encode_mp4(out_dir, start..end, fps)?)
    } else {
        None
    };
    Ok(ClipSummary {
        frames,
        video,
        rolled_out: bundle.is_some(),
    })
}
