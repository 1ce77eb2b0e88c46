use std::path::PathBuf;
use thiserror::Error;

/// Errors of the splat library: bad Gaussian parameters, mismatched buffers,
/// unreadable PLY files, LBS bindings that do not fit the particles.
#[derive(Debug, Error)]
pub enum SplatError {
    #[error("Gaussian arrays differ in length: {0}")]
    LengthMismatch(String),
    #[error("Gaussian {index}: {field} is not finite")]
    NonFinite { index: usize, field: &'static str },
    #[error("Gaussian {index}: rotation quaternion has (near) zero length")]
    ZeroQuaternion { index: usize },
    #[error("image gradient has {got} pixels, the render has {expected}")]
    GradientSize { got: usize, expected: usize },
    #[error("camera image size must be non-zero, got {width}x{height}")]
    EmptyImage { width: u32, height: u32 },
    #[error("render settings: {0}")]
    InvalidSettings(String),
    #[error("PLY {path}: {message}")]
    Ply { path: PathBuf, message: String },
    #[error("PLY {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("LBS: {0}")]
    Lbs(String),
}
