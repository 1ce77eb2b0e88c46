use thiserror::Error;

/// Errors from building cameras out of external (file / user) data, and
/// from drawing charts.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum ViewError {
    #[error("invalid intrinsics: {0}")]
    InvalidIntrinsics(String),
    #[error("matrix contains non-finite values")]
    NonFiniteMatrix,
    #[error("last row of a rigid 4x4 transform must be [0, 0, 0, 1], got {0:?}")]
    InvalidHomogeneousRow([f64; 4]),
    #[error("rotation block is not orthonormal (max |R^T R - I| = {max_error:e})")]
    NonOrthonormalRotation { max_error: f64 },
    #[error("rotation block has determinant {determinant} (reflection, not a rotation)")]
    NotProperRotation { determinant: f64 },
    #[error("drawing a chart: {0}")]
    Chart(String),
}
