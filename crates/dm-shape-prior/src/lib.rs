//! Shape prior (method.md §8): a mesh of the object, posed in the first
//! frame and fitted to the first-frame points.
//!
//! 1. [`mesh`]: load OBJ (tobj) or glTF/GLB (gltf) with vertex colours.
//! 2. [`raster`]: render candidate views on the CPU, each pixel knowing its
//!    mesh point.
//! 3. [`pnp`]: ORB keypoints of the first-frame crop matched (Hamming,
//!    ratio test) to each candidate render; OpenCV `solvePnPRansac` on the
//!    2D–3D matches; the view with most inliers wins.
//! 4. [`arap`]: rigid ICP, then as-rigid-as-possible deformation of the
//!    posed mesh onto the first-frame points.

pub mod arap;
pub mod mesh;
pub mod pnp;
pub mod raster;

use std::path::{Path, PathBuf};

use image::{GrayImage, RgbImage};
use nalgebra::Vector3;

pub use arap::{FitOptions, FitResult};
pub use mesh::Mesh;
pub use pnp::{PnpOptions, PnpPose};
pub use raster::{Intrinsics, Render, render};

#[derive(Debug, thiserror::Error)]
pub enum PriorError {
    #[error("{}: {problem}", path.display())]
    Mesh { path: PathBuf, problem: String },
    #[error("shape prior: {0}")]
    Input(String),
    #[error("shape prior: OpenCV: {0}")]
    OpenCv(String),
    #[error("shape prior pose: {0}")]
    Pose(String),
    #[error("shape prior fit: {0}")]
    Fit(String),
}

/// The prior's result.
#[derive(Clone, Debug)]
pub struct PriorResult {
    pub pnp: PnpPose,
    pub fit: FitResult,
    /// Welded triangles over `fit.vertices`.
    pub triangles: Vec<[u32; 3]>,
}

/// Files [`PriorResult::write`] puts in its output directory.
pub const PRIOR_VERTICES_NPY: &str = "prior_vertices.npy";
pub const PRIOR_TRIANGLES_NPY: &str = "prior_triangles.npy";
pub const PRIOR_JSON: &str = "prior.json";

impl PriorResult {
    /// Writes the fitted mesh (`prior_vertices.npy` float32 (V, 3), camera
    /// frame; `prior_triangles.npy` int32 (T, 3)) and `prior.json` (the PnP,
    /// ICP and ARAP poses, match counts and point distances) into `out`,
    /// each file under a temporary name and renamed. `mesh` is recorded.
    pub fn write(&self, out: &Path, mesh: &Path) -> Result<(), dm_bundle::BundleError> {
        std::fs::create_dir_all(out)
            .map_err(|e| dm_bundle::BundleError::io(out, "creating", &e))?;
        let pose_json = |pose: &nalgebra::Isometry3<f64>| {
            let rotation = pose.rotation.to_rotation_matrix();
            serde_json::json!({
                "rotation": (0..3).map(|r| (0..3).map(|c| rotation[(r, c)]).collect::<Vec<_>>()).collect::<Vec<_>>(),
                "translation_m": pose.translation.vector.iter().copied().collect::<Vec<_>>(),
            })
        };
        let report = serde_json::json!({
            "mesh": mesh.display().to_string(),
            "pnp_mesh_to_camera": pose_json(&self.pnp.mesh_to_camera),
            "pnp_view": self.pnp.view,
            "pnp_matches": self.pnp.matches,
            "pnp_inliers": self.pnp.inliers,
            "icp_mesh_to_camera": pose_json(&self.fit.rigid_pose),
            "arap_mesh_to_camera": pose_json(&self.fit.deformed_pose),
            "median_distance_before_m": self.fit.median_distance_before_m,
            "median_distance_after_m": self.fit.median_distance_after_m,
        });
        let vertices = ndarray::Array2::from_shape_fn((self.fit.vertices.len(), 3), |(i, k)| {
            self.fit.vertices[i][k] as f32
        });
        let triangles = ndarray::Array2::from_shape_fn((self.triangles.len(), 3), |(i, k)| {
            self.triangles[i][k] as i32
        });
        dm_bundle::write_npy_file(&out.join(PRIOR_VERTICES_NPY), &vertices)?;
        dm_bundle::write_npy_file(&out.join(PRIOR_TRIANGLES_NPY), &triangles)?;
        dm_bundle::write_json_atomic(&out.join(PRIOR_JSON), &report)
    }
}

/// Poses `mesh` in `frame` by PnP, then fits it to `observations` (camera
/// frame first-frame points of the object).
pub fn fit_prior(
    mesh: &Mesh,
    frame: &RgbImage,
    mask: Option<&GrayImage>,
    intrinsics: &Intrinsics,
    observations: &[Vector3<f64>],
    pnp_options: &PnpOptions,
    fit_options: &FitOptions,
) -> Result<PriorResult, PriorError> {
    let pnp = pnp::solve_pose(mesh, frame, mask, intrinsics, pnp_options)?;
    let (rest, triangles, _) = mesh.welded();
    let fit = arap::fit_to_points(
        &rest,
        &triangles,
        &pnp.mesh_to_camera,
        observations,
        fit_options,
    )?;
    Ok(PriorResult {
        pnp,
        fit,
        triangles,
    })
}
