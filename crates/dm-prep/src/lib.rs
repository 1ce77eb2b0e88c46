//! Preprocessing into scene bundles (`docs/bundle.md`, `docs/prep.md`).
//!
//! Importing a PhysTwin case directory (method.md §10) with
//! [`import_phystwin`]. PhysTwin stores its tracks and calibration as Python
//! pickles of numpy arrays; [`pickle`] reads them without Python.
//!
//! Preparing a multi-view RGB-D capture ([`capture`], docs/capture.md)
//! with classical fallbacks that need no model weights: [`segment`],
//! [`track2d`], [`lift`], [`fill`], run and cached by [`stages`]; [`score`]
//! compares the resulting tracks with a reference bundle's.
//!
//! A monocular clip becomes a one-camera capture with [`monocular`]
//! (depth frames or a depth network; the floor sets the world frame).
//!
//! Model stages: [`models`] (`models_manifest/` and the ONNX adapters:
//! segmentation, point tracking, monocular depth) and [`scale`] (metric
//! scale of monocular depth by median absolute residual).

pub mod capture;
pub mod fill;
pub mod lift;
pub mod models;
pub mod monocular;
pub mod ndarray_raw;
pub mod phystwin;
pub mod pickle;
pub mod prior;
pub mod scale;
pub mod score;
pub mod segment;
pub mod stages;
pub mod track2d;
pub mod video;

pub use ndarray_raw::{ArrayData, ByteOrder, Element, NdArray};
pub use phystwin::{ImportOptions, ImportSummary, MaskSource, import_phystwin, read_pickle_file};
pub use pickle::{Limits, PickleError, Value};
