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

use std::path::PathBuf;

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
