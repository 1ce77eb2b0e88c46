//! The single error type of the crate.
//!
//! Every failure names the exact file and the field inside it, so that a user
//! who receives a broken bundle can fix it without reading this crate.

use std::io;
use std::path::{Path, PathBuf};

/// Field name used when a whole file could not be read or written.
pub const IO_FIELD: &str = "file";

/// A problem with one field of one file of a bundle.
///
/// Displayed as ``{path}: field `{field}`: {problem}``.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{}: field `{field}`: {problem}", path.display())]
pub struct BundleError {
    /// The file (or directory) concerned, as a full path.
    pub path: PathBuf,
    /// The field inside the file: a JSON key path such as `cameras[1].fx`, an
    /// array element such as `object_points[12,3,1]`, `shape`, `dtype`, or
    /// [`IO_FIELD`] for I/O failures.
    pub field: String,
    /// What is wrong, in words.
    pub problem: String,
}

impl BundleError {
    pub fn new(
        path: impl Into<PathBuf>,
        field: impl Into<String>,
        problem: impl Into<String>,
    ) -> Self {
        Self {
            path: path.into(),
            field: field.into(),
            problem: problem.into(),
        }
    }

    /// An I/O failure on `path`; `action` says what was attempted ("reading", "creating", ...).
    pub fn io(path: impl AsRef<Path>, action: &str, err: &io::Error) -> Self {
        Self::new(path.as_ref(), IO_FIELD, format!("{action} failed: {err}"))
    }

    /// True when this error is an I/O failure rather than invalid content.
    pub fn is_io(&self) -> bool {
        self.field == IO_FIELD
    }
}

pub type Result<T, E = BundleError> = std::result::Result<T, E>;
