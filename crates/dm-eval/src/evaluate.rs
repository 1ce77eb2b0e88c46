//! One open-loop rollout from frame 0 driven by the observed hand track,
//! and the benchmark's metrics for every frame (method.md §9).

use crate::image_metrics::{benchmark_pair, iou, psnr, ssim, without_hand};
use crate::lpips::Lpips;
use crate::{EvalError, FrameMetrics, Metrics, SplitMetrics, SplitName};
use dm_appearance::SplatFollower;
use dm_appearance::quality::{alpha_mask, to_rgb8};
use dm_bundle::{Bundle, MaskKind};
use dm_model::WorldModel;
use dm_model::device::Device;
use dm_model::metrics::{frame_errors, split_mean};
use dm_model::preview::bundle_camera;
use dm_view::{Camera, RenderOptions, Splat, render};
use image::{GrayImage, RgbImage};
use std::time::Instant;

/// What to evaluate.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EvalOptions {
    /// Index of the camera of the image metrics (the protocol's camera 0).
    pub camera: usize,
    /// Frames to roll out and score (`None`: the whole clip).
    pub frames: Option<usize>,
    /// The model's fitted first-frame Gaussian splats, moved
    /// along the rollout by LBS and rendered for the image metrics; `None`:
    /// the particles are drawn as spheres ([`render_prediction`]).
    pub splats: Option<dm_splat::Gaussians<f32>>,
    /// Where the rollout's MPM world and residual network run.
    pub device: Device,
}

/// Which renderer made the predicted images (`run.renderer` in metrics.json).
pub fn renderer_name(options: &EvalOptions) -> &'static str {
    if options.splats.is_some() {
        "gaussian_splats"
    } else {
        "particle_spheres"
    }
}

/// The fitted splats at one frame seen by the camera, on black: the 8-bit
/// image and the silhouette (coverage ≥ 0.5, `dm_appearance::quality`).
pub fn render_splat_prediction(
    camera: &Camera,
    gaussians: &dm_splat::Gaussians<f32>,
) -> Result<(RgbImage, GrayImage), dm_splat::SplatError> {
    let out = dm_splat::render(gaussians, camera, &dm_splat::RenderSettings::default())?;
    let alpha = out.alpha();
    Ok((
        to_rgb8(out.image(), camera.width, camera.height),
        alpha_mask(&alpha, camera.width, camera.height),
    ))
}

/// The model's prediction as the camera sees it: the particles as splats of
/// the model's splat radius (until Gaussian splats exist), lit as in the
/// previews, on black, no floor. Returns the image and the alpha mask.
pub fn render_prediction(
    camera: &Camera,
    model: &WorldModel,
    positions: &[[f32; 3]],
    up: [f64; 3],
) -> (RgbImage, GrayImage) {
    let radius = model.splat_radius();
    let splats: Vec<Splat> = positions
        .iter()
        .zip(&model.colors)
        .map(|(&position, &color)| Splat {
            position,
            radius,
            color,
            label: 1,
        })
        .collect();
    let options = RenderOptions {
        background: [0.0; 3],
        floor: None,
        ..RenderOptions::studio(up, 0.0)
    };
    let frame = render(camera, &splats, &options);
    (frame.to_rgb8(), frame.mask(1))
}

/// Scores and where the time went.
#[derive(Clone, Debug, PartialEq)]
pub struct Evaluation {
    pub metrics: Metrics,
    pub rollout_seconds: f64,
    /// Time inside the LPIPS network (0 when skipped).
    pub lpips_seconds: f64,
}

/// Rolls `model` out over `bundle` and scores every frame. `lpips` is
/// `None` when the caller chose to skip it (then every LPIPS value is
/// `None`). `progress(stage, frame)` reports the frame done per stage
/// (`"rollout"`, `"images"`).
pub fn evaluate(
    model: &WorldModel,
    bundle: &Bundle,
    options: &EvalOptions,
    mut lpips: Option<&mut Lpips>,
    progress: &mut dyn FnMut(&'static str, usize),
) -> Result<Evaluation, EvalError> {
    let camera_count = bundle.meta.cameras.len();
    if options.camera >= camera_count {
        return Err(EvalError::InvalidOption {
            option: "--camera".into(),
            problem: format!(
                "camera {} does not exist; the bundle has {camera_count}",
                options.camera
            ),
        });
    }
    let frames = options
        .frames
        .unwrap_or(bundle.frame_count())
        .min(bundle.frame_count());
    if frames < 2 {
        return Err(EvalError::InvalidOption {
            option: "--frames".into(),
            problem: "need at least 2 frames".into(),
        });
    }
    let start = Instant::now();
    let rollout = model.rollout_on(bundle, frames, options.device, &mut |t| {
        progress("rollout", t)
    })?;
    let rollout_seconds = start.elapsed().as_secs_f64();
    let mut lpips_seconds = 0.0;
    let errors = frame_errors(&rollout, model.surface_count, &bundle.tracks);

    let camera = bundle_camera(bundle, options.camera)?;
    let up = bundle.meta.up_axis.unit_vector();
    let split = bundle.meta.split;
    let mut follower = match &options.splats {
        Some(g) => Some(SplatFollower::new(g.clone(), &model.particles)?),
        None => None,
    };
    let mut per_frame = Vec::with_capacity(frames);
    for (t, positions) in rollout.iter().enumerate() {
        let image_error = |source| EvalError::Image { frame: t, source };
        let observed = bundle.load_rgb(options.camera, t)?;
        let object_mask = bundle.load_mask(options.camera, t, MaskKind::Object)?;
        let hand_mask = bundle.load_mask(options.camera, t, MaskKind::Hand)?;
        let (rendered, alpha) = match follower.as_mut() {
            Some(follower) => {
                if t > 0 {
                    follower.advance(positions)?;
                }
                render_splat_prediction(&camera, follower.gaussians())?
            }
            None => render_prediction(&camera, model, positions, up),
        };
        let (truth, prediction) =
            benchmark_pair(&observed, &object_mask, &hand_mask, &rendered).map_err(image_error)?;
        let alpha = without_hand(&alpha, &hand_mask).map_err(image_error)?;
        let lpips_value = match lpips.as_deref_mut() {
            Some(network) => {
                let start = Instant::now();
                let value = network.distance(&truth, &prediction)?;
                lpips_seconds += start.elapsed().as_secs_f64();
                Some(value)
            }
            None => None,
        };
        per_frame.push(FrameMetrics {
            frame: t,
            split: split_of(t, split.train, split.test),
            chamfer: errors.chamfer[t],
            track: errors.track[t],
            iou: iou(&object_mask, &alpha).map_err(image_error)?,
            psnr: psnr(&truth, &prediction).map_err(image_error)?,
            ssim: ssim(&truth, &prediction).map_err(image_error)?,
            lpips: lpips_value,
        });
        progress("images", t + 1);
    }
    let clip = |r: [usize; 2]| [r[0].min(frames), r[1].min(frames)];
    Ok(Evaluation {
        metrics: Metrics {
            train: SplitMetrics::mean_over(&per_frame, clip(split.train)),
            test: SplitMetrics::mean_over(&per_frame, clip(split.test)),
            frames: per_frame,
        },
        rollout_seconds,
        lpips_seconds,
    })
}

fn split_of(t: usize, train: [usize; 2], test: [usize; 2]) -> Option<SplitName> {
    if (train[0]..train[1]).contains(&t) {
        Some(SplitName::Train)
    } else if (test[0]..test[1]).contains(&t) {
        Some(SplitName::Test)
    } else {
        None
    }
}

impl SplitMetrics {
    /// Means over the frames `range` of each metric's finite values (NaN
    /// when none); LPIPS is `None` when it was not computed.
    pub fn mean_over(frames: &[FrameMetrics], range: [usize; 2]) -> Self {
        let column = |f: fn(&FrameMetrics) -> f64| -> f64 {
            split_mean(&frames.iter().map(f).collect::<Vec<_>>(), range)
        };
        let lpips_computed = frames.iter().any(|f| f.lpips.is_some());
        Self {
            chamfer: column(|f| f.chamfer),
            track: column(|f| f.track),
            iou: column(|f| f.iou),
            psnr: column(|f| f.psnr),
            ssim: column(|f| f.ssim),
            lpips: lpips_computed.then(|| column(|f| f.lpips.unwrap_or(f64::NAN))),
        }
    }
}
