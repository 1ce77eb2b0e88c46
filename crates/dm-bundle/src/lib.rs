//! Scene bundle v1: the on-disk contract between capture / synthesis and the
//! physics world model. See `docs/bundle.md` for the format itself.
//!
//! A bundle is a directory readable with numpy and PIL alone: `bundle.json`,
//! `.npy` tracks and particles, and per-camera PNG images. [`Bundle::open`]
//! reads and validates everything but the images; [`BundleWriter`] produces a
//! bundle atomically.

mod bundle;
mod error;
mod meta;
mod npy;
mod writer;

pub use bundle::{
    BUNDLE_JSON, Bundle, DEFAULT_MESH_FILE, DEPTH_PNG_UNITS_PER_METRE, FirstFrameParticles,
    HAND_POINTS_FILE, HAND_VISIBILITY_FILE, INTERIOR_COLORS_FILE, INTERIOR_POINTS_FILE, ImageKind,
    MaskKind, OBJECT_MOTION_VALID_FILE, OBJECT_POINTS_FILE, OBJECT_VISIBILITY_FILE, PARTICLES_DIR,
    SURFACE_COLORS_FILE, SURFACE_POINTS_FILE, TRACKS_DIR, Tracks, VIEWS_DIR, frame_file_name,
    mask_box,
};
pub use error::{BundleError, IO_FIELD, Result};
pub use meta::{
    BundleMeta, CAMERA_AXES_OPENCV, CameraSpec, Category, DEPTH_ENCODING, DEPTH_UNIT, DepthSpec,
    FORMAT_NAME, FORMAT_VERSION, HandSpec, Provenance, ROTATION_TOLERANCE, Split, UNITS, UpAxis,
    parse_json, read_json, remove_abandoned_temporaries, write_file_atomic, write_json_atomic,
};
pub use npy::{BundleElement, read_npy_checked, shape_string, write_npy_file};
pub use writer::{BundleWriter, depth_m_to_png_mm};
