//! `.npy` reading and writing with errors that name the file and what was expected.
//!
//! The header is inspected before the data is read because ndarray-npy allocates
//! the full array the header announces: a corrupted shape must not turn into a
//! huge allocation, and a wrong dtype deserves a message naming the expected one.

use std::fs;
use std::io::{BufWriter, Write};
use std::path::Path;

use ndarray::{ArrayBase, DataOwned, Dimension};
use ndarray_npy::npy::header::Header;
use ndarray_npy::{ReadNpyExt, ReadableElement, WritableElement, WriteNpyExt};

use crate::error::{BundleError, Result};

/// An element type used in bundles, with the numpy descriptors ndarray-npy accepts for it.
pub trait BundleElement: ReadableElement + WritableElement {
    /// numpy name, for messages.
    const DTYPE_NAME: &'static str;
    const DESCRIPTORS: &'static [&'static str];
    const ITEM_SIZE: usize;
}

impl BundleElement for f32 {
    const DTYPE_NAME: &'static str = "float32 ('<f4')";
    const DESCRIPTORS: &'static [&'static str] = &["<f4", ">f4"];
    const ITEM_SIZE: usize = 4;
}

impl BundleElement for bool {
    const DTYPE_NAME: &'static str = "bool ('|b1')";
    const DESCRIPTORS: &'static [&'static str] = &["|b1"];
    const ITEM_SIZE: usize = 1;
}

/// Formats a shape like numpy does: `(5, 7, 3)`, `(4,)`.
pub fn shape_string(shape: &[usize]) -> String {
    match shape {
        [single] => format!("({single},)"),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(usize::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        ),
    }
}

/// Refuses a header whose announced length runs past the file: the
/// header parser allocates that length before reading it.
fn check_header_length(path: &Path, bytes: &[u8]) -> Result<()> {
    // Magic (6 bytes), version (2), then the length: 2 bytes in version 1,
    // 4 in versions 2 and 3 (little-endian).
    let (announced, prefix) = match bytes.get(6) {
        Some(1) => (
            bytes
                .get(8..10)
                .map(|b| usize::from(u16::from_le_bytes([b[0], b[1]]))),
            10,
        ),
        Some(2 | 3) => (
            bytes
                .get(8..12)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize),
            12,
        ),
        // Not a version this reader knows: the header parser says so.
        _ => return Ok(()),
    };
    match announced {
        Some(length) if length <= bytes.len().saturating_sub(prefix) => Ok(()),
        _ => Err(BundleError::new(
            path,
            "header",
            format!(
                "the .npy header announces {} bytes but the file has {} after its prefix (truncated or not a .npy file)",
                announced.map_or("?".into(), |l| l.to_string()),
                bytes.len().saturating_sub(prefix)
            ),
        )),
    }
}

/// Reads a `.npy` file whose dtype and number of dimensions must match `A` and `D`.
pub fn read_npy_checked<A, S, D>(path: &Path) -> Result<ArrayBase<S, D>>
where
    A: BundleElement,
    S: DataOwned<Elem = A>,
    D: Dimension,
{
    let bytes = fs::read(path).map_err(|e| BundleError::io(path, "reading", &e))?;
    check_header_length(path, &bytes)?;
    let mut after_header: &[u8] = &bytes;
    let header = Header::from_reader(&mut after_header).map_err(|e| {
        BundleError::new(
            path,
            "header",
            format!("cannot parse .npy header (truncated or not a .npy file): {e}"),
        )
    })?;

    let descriptor = header.type_descriptor.as_string().map(String::as_str);
    if !descriptor.is_some_and(|d| A::DESCRIPTORS.contains(&d)) {
        return Err(BundleError::new(
            path,
            "dtype",
            format!(
                "expected {}, found {}",
                A::DTYPE_NAME,
                header.type_descriptor
            ),
        ));
    }
    if let Some(ndim) = D::NDIM
        && header.shape.len() != ndim
    {
        return Err(BundleError::new(
            path,
            "shape",
            format!(
                "expected {ndim} dimensions, found shape {}",
                shape_string(&header.shape)
            ),
        ));
    }
    let expected_bytes = header
        .shape
        .iter()
        .try_fold(A::ITEM_SIZE, |acc, &dim| acc.checked_mul(dim))
        .ok_or_else(|| {
            BundleError::new(
                path,
                "shape",
                format!("{} is too large", shape_string(&header.shape)),
            )
        })?;
    let present_bytes = after_header.len();
    if present_bytes != expected_bytes {
        let what = if present_bytes < expected_bytes {
            "truncated"
        } else {
            "has trailing bytes"
        };
        return Err(BundleError::new(
            path,
            "data",
            format!(
                "file is {what}: shape {} needs {expected_bytes} data bytes, found {present_bytes}",
                shape_string(&header.shape)
            ),
        ));
    }
    ArrayBase::<S, D>::read_npy(bytes.as_slice())
        .map_err(|e| BundleError::new(path, "data", e.to_string()))
}

/// Writes an array as a standard little-endian C-order `.npy` file.
pub fn write_npy_file<A, S, D>(path: &Path, array: &ArrayBase<S, D>) -> Result<()>
where
    A: WritableElement,
    S: ndarray::Data<Elem = A>,
    D: Dimension,
{
    let file = fs::File::create(path).map_err(|e| BundleError::io(path, "creating", &e))?;
    let mut writer = BufWriter::new(file);
    array
        .write_npy(&mut writer)
        .map_err(|e| BundleError::new(path, "data", format!("writing .npy failed: {e}")))?;
    writer
        .flush()
        .map_err(|e| BundleError::io(path, "writing", &e))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A version-2 header announcing 3 GiB in a 64-byte file is refused
    /// before anything is allocated for it, naming the header.
    #[test]
    fn a_header_longer_than_its_file_is_refused() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("points.npy");
        let mut bytes = b"\x93NUMPY\x02\x00".to_vec();
        bytes.extend_from_slice(&(3u32 << 30).to_le_bytes());
        bytes.resize(64, b' ');
        fs::write(&path, &bytes).expect("write");
        let error = read_npy_checked::<f32, ndarray::OwnedRepr<f32>, ndarray::Ix1>(&path)
            .expect_err("refused");
        assert!(error.to_string().contains("header"), "{error}");
    }
}
