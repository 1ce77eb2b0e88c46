//! Preprocessing into scene bundles (`docs/bundle.md`, `docs/prep.md`).
//!
//! PhysTwin case directories are imported by `dm-phystwin`.
//!
//! Preparing a multi-view RGB-D capture (`dm-capture`, docs/capture.md)
//! with classical fallbacks that need no model weights: [`segment`],
//! [`track2d`], [`lift`], [`fill`], run and cached by [`stages`]; [`score`]
//! compares the resulting tracks with a reference bundle's.
//!
//! A monocular clip becomes a one-camera capture with [`monocular`]
//! (depth frames or a depth network; the floor sets the world frame).
//!
//! Model stages: `dm-prep-models` (`models_manifest/` and the ONNX adapters:
//! segmentation, point tracking, monocular depth; metric scale of monocular
//! depth by median absolute residual).

pub mod fill;
pub mod lift;
pub mod monocular;
pub mod prior;
pub mod score;
pub mod segment;
pub mod stages;
pub mod track2d;
