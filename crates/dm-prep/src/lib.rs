//! Preprocessing of RGB-D captures into scene bundles (`docs/bundle.md`,
//! `docs/prep.md`, `docs/capture.md`): the capture stages and their
//! orchestration.
//!
//! A multi-view RGB-D capture (read with `dm-capture`) goes through
//! classical stages that need no model weights, [`segment`], [`track2d`],
//! [`lift`], [`fill`], or the ONNX model stages of `dm-prep-models`, run and
//! cached by [`stages`]; [`score`] compares the resulting tracks with a
//! reference bundle's.
//!
//! A monocular clip becomes a one-camera capture with [`monocular`]
//! (depth frames or a depth network; the floor sets the world frame).
//!
//! The `dm-prep` tool also drives `dm-phystwin` (PhysTwin case import) and
//! `dm-shape-prior` (the mesh shape prior).

pub mod affine_lk;
pub mod fill;
pub mod lift;
pub mod monocular;
pub mod score;
pub mod segment;
pub mod stages;
pub mod track2d;
