//! The appearance of a world model (method.md §6).
//!
//! * [`fit`]: the first-frame Gaussian-splat fit to a bundle's multi-view
//!   images (masked L1 + 0.2 D-SSIM, `dm_splat::fit`), initialised from
//!   the model's first-frame surface particles with colours read from the
//!   images, one camera held out to measure novel-view quality.
//! * [`store`]: where the splats live — `MODEL_DIR/gaussians.ply` (the
//!   standard 3DGS layout) and `MODEL_DIR/appearance.json` (the fit's
//!   record: cameras, binding, PSNR).
//! * [`follow`]: the Gaussians moved along any rollout by the LBS bridge.
//! * [`views`]: train, novel and orbit cameras.
//! * [`clip`]: a rendered clip as PNG frames and an MP4.

pub mod clip;
pub mod fit;
pub mod follow;
pub mod quality;
pub mod store;
pub mod views;

use std::path::PathBuf;

/// Why an appearance step failed; every variant names the file or option.
#[derive(Debug, thiserror::Error)]
pub enum AppearanceError {
    #[error(transparent)]
    Bundle(#[from] dm_bundle::BundleError),
    #[error(transparent)]
    Model(#[from] dm_model::ModelError),
    #[error(transparent)]
    Splat(#[from] dm_splat::SplatError),
    #[error("{path}: {problem}")]
    File { path: PathBuf, problem: String },
    #[error("invalid option `{option}`: {problem}")]
    InvalidOption { option: String, problem: String },
    #[error("video {path}: {problem}")]
    Video { path: PathBuf, problem: String },
}

pub use fit::{AppearanceOptions, fit_appearance};
pub use follow::SplatFollower;
pub use store::{
    APPEARANCE_JSON, AppearanceRecord, GAUSSIANS_FILE, load_appearance, save_appearance,
};
pub use views::ViewChoice;
