//! dm-splat: a differentiable Gaussian-splat rasterizer on the CPU.
//!
//! The pipeline follows 3D Gaussian Splatting (Kerbl et al. 2023) and the
//! gsplat formulation, written from the equations:
//!
//! 1. [`project`]: EWA splatting — each Gaussian's mean goes to camera space
//!    (dm-view [`Camera`](dm_view::Camera), OpenCV axes), its 3D covariance
//!    `R S Sᵀ Rᵀ` is pushed through the Jacobian of the perspective map, a
//!    0.3 px² low-pass is added, and the inverse (the conic) and a 3σ pixel
//!    radius are kept. Gaussians at or behind the near plane are culled.
//! 2. [`tiles`]: every visible Gaussian is listed in the 16×16 pixel tiles
//!    its 3σ square overlaps; each tile's list is sorted by depth, ties by
//!    index, so the order never depends on threads.
//! 3. [`rasterize`]: front-to-back alpha compositing per pixel
//!    (α = min(0.99, o·exp(power)), skipped below 1/255, stop once the
//!    transmittance would fall below 1e-4), then the background.
//!
//! Every forward file has its reverse-mode twin beside it
//! (`project_backward.rs`, `rasterize_backward.rs`); [`render`] chains
//! them. Kernels are generic over [`Real`](dm_mpm::real::Real) (f32 for
//! speed, f64 for finite-difference checks) and parallel over tiles /
//! Gaussians with rayon; every sum has a fixed order, so results are
//! bitwise independent of the thread count.
//!
//! Colour is degree-0 only: one RGB value per Gaussian (no view-dependent
//! spherical harmonics). The PLY export writes it as the DC coefficient
//! `f_dc = (rgb − 0.5) / C0`, which is what 3DGS viewers expect.
//!
//! Conventions (as dm-view): pixel `(x, y)` covers `[x, x+1) × [y, y+1)`,
//! its centre is `(x + 0.5, y + 0.5)`; images are row-major RGB in `[0, 1]`
//! (values are not clamped).

pub mod error;
pub mod fit;
pub mod gaussians;
pub mod lbs;
pub mod lbs_backward;
pub mod ply;
pub mod project;
pub mod project_backward;
pub mod rasterize;
pub mod rasterize_backward;
pub mod render;
pub mod ssim;
pub mod tiles;

pub use error::SplatError;
pub use fit::{FitSettings, FitStep, FitView, LearningRates, fit_gaussians};
pub use gaussians::{GaussianGrads, Gaussians};
pub use render::{RenderOutput, RenderSettings, render, render_backward};
