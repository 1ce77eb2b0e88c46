//! Preprocessing into scene bundles (`docs/bundle.md`, `docs/prep.md`).
//!
//! * [`import_phystwin`]: a PhysTwin case directory (method.md §10). PhysTwin
//!   stores its tracks and calibration as Python pickles of numpy arrays;
//!   [`pickle`] reads them without Python.
//! * [`models`]: `models_manifest/` and the ONNX adapters (segmentation,
//!   point tracking, monocular depth).
//! * [`scale`]: metric scale of monocular depth by median absolute residual.

pub mod models;
pub mod ndarray_raw;
pub mod phystwin;
pub mod pickle;
pub mod scale;

pub use ndarray_raw::{ArrayData, ByteOrder, Element, NdArray};
pub use phystwin::{ImportOptions, ImportSummary, MaskSource, import_phystwin, read_pickle_file};
pub use pickle::{Limits, PickleError, Value};
