//! Where the splats of a model live: `MODEL_DIR/gaussians.ply` (3DGS
//! layout, `dm_splat::ply`) beside `model.json`, and
//! `MODEL_DIR/appearance.json`, the record of the fit that made them (the
//! cameras it saw, the particles the Gaussians are bound to, its PSNR).

use std::path::Path;

use dm_bundle::{CameraSpec, read_json, write_json_atomic};
use dm_model::WorldModel;
use dm_splat::Gaussians;
use serde::{Deserialize, Serialize};

use crate::AppearanceError;

pub const GAUSSIANS_FILE: &str = "gaussians.ply";
pub const APPEARANCE_JSON: &str = "appearance.json";

/// PSNR of one camera at frame 0 after the fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraPsnr {
    pub camera: usize,
    pub name: String,
    /// Whether the fit saw this camera.
    pub train: bool,
    /// dB, masked pair (docs/metrics.md), 8-bit render.
    pub psnr_db: f64,
}

/// What `appearance.json` holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AppearanceRecord {
    /// The scene the splats were fitted to.
    pub bundle: String,
    /// Every camera of that bundle (dm-render's `train:I` views without a bundle).
    pub cameras: Vec<CameraSpec>,
    /// World up axis of the bundle (novel and orbit views circle it).
    pub up: [f64; 3],
    pub fps: f64,
    pub train_cameras: Vec<usize>,
    pub held_out_camera: Option<usize>,
    /// The Gaussians are bound (LBS) to the model's first-frame particles;
    /// this many of them, checked on load.
    pub particle_count: usize,
    pub gaussian_count: usize,
    pub iterations: usize,
    pub lambda_dssim: f64,
    /// Loss of the first and last step.
    pub loss_start: f64,
    pub loss_end: f64,
    pub psnr: Vec<CameraPsnr>,
    pub mean_train_psnr_db: f64,
    pub held_out_psnr_db: Option<f64>,
    pub fit_seconds: f64,
}

/// Writes the Gaussians and their record into `model_dir` (each file
/// atomically; the record last, so its presence means both are complete).
pub fn save_appearance(
    model_dir: &Path,
    gaussians: &Gaussians<f32>,
    record: &AppearanceRecord,
) -> Result<(), AppearanceError> {
    dm_splat::ply::write_ply(&model_dir.join(GAUSSIANS_FILE), gaussians)?;
    write_json_atomic(&model_dir.join(APPEARANCE_JSON), record)?;
    Ok(())
}

/// Whether `model_dir` has fitted splats.
pub fn has_appearance(model_dir: &Path) -> bool {
    model_dir.join(GAUSSIANS_FILE).is_file() && model_dir.join(APPEARANCE_JSON).is_file()
}

/// Reads the Gaussians and their record and checks that they belong to
/// `model` (same particle count, a Gaussian count as recorded).
pub fn load_appearance(
    model_dir: &Path,
    model: &WorldModel,
) -> Result<(Gaussians<f32>, AppearanceRecord), AppearanceError> {
    let record_path = model_dir.join(APPEARANCE_JSON);
    let record: AppearanceRecord = read_json(&record_path)?;
    let gaussians = dm_splat::ply::read_ply::<f32>(&model_dir.join(GAUSSIANS_FILE))?;
    if record.particle_count != model.particles.len() {
        return Err(AppearanceError::File {
            path: record_path,
            problem: format!(
                "particle_count is {} but model.json has {} particles: the splats were fitted for another model",
                record.particle_count,
                model.particles.len()
            ),
        });
    }
    if record.gaussian_count != gaussians.len() {
        return Err(AppearanceError::File {
            path: model_dir.join(GAUSSIANS_FILE),
            problem: format!(
                "{} Gaussians, {APPEARANCE_JSON} records gaussian_count {}",
                gaussians.len(),
                record.gaussian_count
            ),
        });
    }
    Ok((gaussians, record))
}
