//! Conversions between the libraries' point lists and NumPy arrays.

use numpy::{IntoPyArray, PyArray2, PyArray3, PyReadonlyArray2, PyReadonlyArray3};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

/// `(N, 3)` array of points.
pub fn points_to_array<'py, T: numpy::Element + Copy>(
    py: Python<'py>,
    points: &[[T; 3]],
) -> Bound<'py, PyArray2<T>> {
    let flat: Vec<T> = points.iter().flatten().copied().collect();
    ndarray::Array2::from_shape_vec((points.len(), 3), flat)
        .expect("N×3 values make an (N, 3) array")
        .into_pyarray(py)
}

/// `(T, N, 3)` array of point lists of equal length.
pub fn frames_to_array<'py>(
    py: Python<'py>,
    frames: &[Vec<[f32; 3]>],
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let n = frames.first().map_or(0, Vec::len);
    let flat: Vec<f32> = frames.iter().flatten().flatten().copied().collect();
    let array = ndarray::Array3::from_shape_vec((frames.len(), n, 3), flat)
        .map_err(|_| PyValueError::new_err("frames differ in point count"))?;
    Ok(array.into_pyarray(py))
}

/// Points from an `(N, 3)` array; `name` is the argument named in errors.
pub fn points_from_array(array: &PyReadonlyArray2<'_, f64>, name: &str) -> PyResult<Vec<[f64; 3]>> {
    let view = array.as_array();
    if view.ncols() != 3 {
        return Err(PyValueError::new_err(format!(
            "`{name}` must have shape (N, 3), got {:?}",
            view.shape()
        )));
    }
    let points: Vec<[f64; 3]> = view
        .outer_iter()
        .map(|row| [row[0], row[1], row[2]])
        .collect();
    if let Some(i) = points.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
        return Err(PyValueError::new_err(format!(
            "`{name}` row {i} is not finite"
        )));
    }
    Ok(points)
}

/// Point lists from a `(T, N, 3)` array.
pub fn frames_from_array(
    array: &PyReadonlyArray3<'_, f64>,
    name: &str,
) -> PyResult<Vec<Vec<[f64; 3]>>> {
    let view = array.as_array();
    if view.shape()[2] != 3 {
        return Err(PyValueError::new_err(format!(
            "`{name}` must have shape (T, N, 3), got {:?}",
            view.shape()
        )));
    }
    let frames: Vec<Vec<[f64; 3]>> = view
        .outer_iter()
        .map(|frame| {
            frame
                .outer_iter()
                .map(|row| [row[0], row[1], row[2]])
                .collect()
        })
        .collect();
    for (t, frame) in frames.iter().enumerate() {
        if let Some(i) = frame.iter().position(|p| p.iter().any(|c| !c.is_finite())) {
            return Err(PyValueError::new_err(format!(
                "`{name}` frame {t} row {i} is not finite"
            )));
        }
    }
    Ok(frames)
}
