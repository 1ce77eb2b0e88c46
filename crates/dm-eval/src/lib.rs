//! Future-prediction metrics of the PhysTwin benchmark (method.md §9;
//! contract in docs/metrics.md): one open-loop rollout from frame 0 driven
//! by the observed hand track, scored per frame and per split with
//! Chamfer, Track, IoU, PSNR, SSIM and LPIPS, reported as `metrics.json`,
//! a Markdown table and per-frame plots.

pub mod evaluate;
pub mod image_metrics;
pub mod lpips;
pub mod report;

pub use evaluate::{
    EvalOptions, Evaluation, evaluate, render_prediction, render_splat_prediction, renderer_name,
};
pub use image_metrics::ImageMetricError;
pub use lpips::{Lpips, LpipsError, LpipsPaths};

use serde::{Deserialize, Deserializer, Serialize};

/// Why an evaluation could not be done.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error(transparent)]
    Bundle(#[from] dm_bundle::BundleError),
    #[error(transparent)]
    Model(#[from] dm_model::ModelError),
    #[error("frame {frame}: {source}")]
    Image {
        frame: usize,
        source: ImageMetricError,
    },
    #[error(transparent)]
    Lpips(Box<LpipsError>),
    #[error("splats: {0}")]
    Splat(#[from] dm_splat::SplatError),
    #[error(transparent)]
    Chart(#[from] dm_view::ViewError),
    #[error("invalid option `{option}`: {problem}")]
    InvalidOption { option: String, problem: String },
}

impl From<LpipsError> for EvalError {
    fn from(e: LpipsError) -> Self {
        Self::Lpips(Box::new(e))
    }
}

/// The metrics of one frame. NaN (`null` in JSON) where a metric is
/// undefined: Chamfer without visible observed points, Track without valid
/// tracked points, IoU when both masks are empty; PSNR is +∞ (`null`) for
/// identical images. `lpips` is `None` when LPIPS was skipped.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FrameMetrics {
    pub frame: usize,
    /// The split the frame belongs to (`null`: neither).
    pub split: Option<SplitName>,
    /// Metres (L1 norm, observed → predicted surface).
    pub chamfer: f64,
    /// Metres (Euclidean).
    pub track: f64,
    pub iou: f64,
    /// dB.
    pub psnr: f64,
    pub ssim: f64,
    pub lpips: Option<f64>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SplitName {
    Train,
    Test,
}

/// Means over a split's frames of each metric's finite per-frame values.
/// NaN is written as `null` (serde_json) and read back as NaN.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SplitMetrics {
    #[serde(deserialize_with = "nan_if_null")]
    pub chamfer: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub track: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub iou: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub psnr: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub ssim: f64,
    pub lpips: Option<f64>,
}

fn nan_if_null<'de, D: Deserializer<'de>>(deserializer: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(deserializer)?.unwrap_or(f64::NAN))
}

/// Everything `metrics.json` holds about the scores.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Metrics {
    pub train: SplitMetrics,
    pub test: SplitMetrics,
    pub frames: Vec<FrameMetrics>,
}
