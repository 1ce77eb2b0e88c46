//! The neural residual of DeformMaster (method.md §5): a bounded
//! velocity correction Δv predicted after each frame's MPM substeps,
//! v ← ṽ + Δv, x ← x̃ + Δv·Δt_frame.
//!
//! * [`ResidualKind::Pgnd`]: the particle-grid network (PNPGD). A PointNet
//!   encoder turns each particle's 27 input channels into a feature; the
//!   features go to the grid nodes of the particles' B-spline supports
//!   (weighted means with the MPM weights), a decoder with a Fourier
//!   encoding of each node's position predicts a bounded node velocity,
//!   and the MPM weights bring it back to the particles.
//! * [`ResidualKind::Mlp`]: the paper's ablation, a per-particle MLP with
//!   no spatial structure.
//!
//! The network's layers and their backward passes are written out by hand
//! over row-major matrices (`kernels`, `transfer`; the choice and its
//! measurements are in docs/decisions/0018-residual-framework.md), with
//! finite-difference checks in f64. Training goes through the physics
//! adjoint: the fit hands [`Residual::vjp`] the adjoint of Δv and gets back the
//! parameter gradient and the adjoints of the network's physical inputs
//! (x̃, ṽ, x_t), which it adds to the MPM state adjoint.

pub mod features;
mod kernels;
pub mod network;
mod transfer;

pub use features::{CHANNELS, FrameInputs, HISTORY};
pub use network::{NetworkSize, Precision, Residual, ResidualGrads, ResidualKind, ResidualSpec};

use std::path::PathBuf;

/// Why the residual could not be built, run, saved or loaded.
#[derive(Debug, thiserror::Error)]
pub enum ResidualError {
    #[error("{}: {problem}", path.display())]
    File { path: PathBuf, problem: String },
    #[error("residual input `{field}`: {problem}")]
    Input { field: String, problem: String },
}
