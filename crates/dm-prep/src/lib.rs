//! Preprocessing into scene bundles (`docs/bundle.md`).
//!
//! Today: importing a PhysTwin case directory (method.md §10) with
//! [`import_phystwin`]. PhysTwin stores its tracks and calibration as Python
//! pickles of numpy arrays; [`pickle`] reads them without Python.

pub mod ndarray_raw;
pub mod phystwin;
pub mod pickle;

pub use ndarray_raw::{ArrayData, ByteOrder, Element, NdArray};
pub use phystwin::{ImportOptions, ImportSummary, MaskSource, import_phystwin, read_pickle_file};
pub use pickle::{Limits, PickleError, Value};
