//! Renders of a simulated frame: the fitted splats (RGB, expected depth,
//! silhouette) or, without splats, the particles as spheres over a floor
//! (dm-model's preview renderer, which gives depth and labels directly).

use dm_appearance::quality::{SILHOUETTE_ALPHA, to_rgb8};
use dm_model::WorldModel;
use dm_model::preview::{OBJECT_LABEL, particle_frame};
use dm_splat::{Gaussians, RenderSettings, render};
use dm_view::Camera;
use nalgebra::{Point3, Vector3};
use numpy::IntoPyArray;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::ModelError;

/// A camera given from Python as a dict (the keys of bundle.json's cameras).
#[derive(FromPyObject)]
pub struct CameraArg {
    #[pyo3(item)]
    width: u32,
    #[pyo3(item)]
    height: u32,
    #[pyo3(item)]
    fx: f64,
    #[pyo3(item)]
    fy: f64,
    #[pyo3(item)]
    cx: f64,
    #[pyo3(item)]
    cy: f64,
    #[pyo3(item)]
    world_to_camera: Vec<Vec<f64>>,
}

impl CameraArg {
    pub fn to_camera(&self) -> PyResult<Camera> {
        let m = &self.world_to_camera;
        if m.len() != 4 || m.iter().any(|row| row.len() != 4) {
            return Err(PyValueError::new_err(
                "camera world_to_camera must be a 4×4 matrix",
            ));
        }
        let matrix: [[f64; 4]; 4] = std::array::from_fn(|r| std::array::from_fn(|c| m[r][c]));
        Camera::from_matrix_4x4(
            self.width,
            self.height,
            self.fx,
            self.fy,
            self.cx,
            self.cy,
            matrix,
        )
        .map_err(|e| PyValueError::new_err(format!("camera: {e}")))
    }
}

/// A rendered view, row-major.
pub struct View {
    width: usize,
    height: usize,
    rgb: Vec<u8>,
    depth: Vec<f32>,
    mask: Vec<bool>,
}

impl View {
    pub fn into_dict(self, py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
        let (h, w) = (self.height, self.width);
        let shape_error = |e: ndarray::ShapeError| ModelError::new_err(e.to_string());
        let d = PyDict::new(py);
        d.set_item(
            "rgb",
            ndarray::Array3::from_shape_vec((h, w, 3), self.rgb)
                .map_err(shape_error)?
                .into_pyarray(py),
        )?;
        d.set_item(
            "depth",
            ndarray::Array2::from_shape_vec((h, w), self.depth)
                .map_err(shape_error)?
                .into_pyarray(py),
        )?;
        d.set_item(
            "mask",
            ndarray::Array2::from_shape_vec((h, w), self.mask)
                .map_err(shape_error)?
                .into_pyarray(py),
        )?;
        Ok(d)
    }
}

/// Renders `positions` (with `hands` as balls when no splats are given).
pub fn render_view(
    model: &WorldModel,
    splats: Option<&Gaussians<f32>>,
    positions: &[[f32; 3]],
    hands: &[[f32; 3]],
    camera: &Camera,
    background: [f64; 3],
) -> PyResult<View> {
    match splats {
        Some(gaussians) => render_splats(gaussians, camera, background)
            .map_err(|e| ModelError::new_err(format!("rendering the splats: {e}"))),
        None => {
            let (up, floor_height) = up_and_floor(model);
            let frame = particle_frame(
                camera,
                positions,
                &model.colors,
                model.splat_radius(),
                hands,
                up,
                floor_height,
            );
            let rgb = frame.to_rgb8().into_raw();
            Ok(View {
                width: frame.width as usize,
                height: frame.height as usize,
                rgb,
                depth: frame
                    .depth
                    .iter()
                    .map(|&d| if d.is_finite() { d } else { f32::NAN })
                    .collect(),
                mask: frame.label.iter().map(|&l| l == OBJECT_LABEL).collect(),
            })
        }
    }
}

/// The up axis (the floor's normal, else against gravity) and the floor's
/// height along it.
fn up_and_floor(model: &WorldModel) -> ([f64; 3], f64) {
    if let Some(floor) = &model.physics.floor {
        return (floor.up, floor.height);
    }
    let g = model.physics.gravity;
    let norm = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
    if norm > 0.0 {
        (g.map(|c| -c / norm), 0.0)
    } else {
        ([0.0, 0.0, 1.0], 0.0)
    }
}

/// The splats' colour render, and their expected depth: each Gaussian's
/// camera-space z composited as its colour over a zero background, over
/// the coverage (defined where the coverage reaches the silhouette's).
fn render_splats(
    gaussians: &Gaussians<f32>,
    camera: &Camera,
    background: [f64; 3],
) -> Result<View, dm_splat::SplatError> {
    let settings = RenderSettings {
        background,
        ..RenderSettings::default()
    };
    let colour = render(gaussians, camera, &settings)?;
    let alpha = colour.alpha();
    let mut depth_splats = gaussians.clone();
    depth_splats.colors = gaussians
        .means
        .iter()
        .map(|m| {
            let p = Point3::new(f64::from(m.x), f64::from(m.y), f64::from(m.z));
            Vector3::repeat((camera.world_to_camera * p).z as f32)
        })
        .collect();
    let depth_render = render(
        &depth_splats,
        camera,
        &RenderSettings {
            background: [0.0; 3],
            ..settings
        },
    )?;
    let depth = depth_render
        .image()
        .iter()
        .zip(&alpha)
        .map(|(z, &a)| {
            if a >= SILHOUETTE_ALPHA {
                z[0] / a
            } else {
                f32::NAN
            }
        })
        .collect();
    Ok(View {
        width: camera.width as usize,
        height: camera.height as usize,
        rgb: to_rgb8(colour.image(), camera.width, camera.height).into_raw(),
        depth,
        mask: alpha.iter().map(|&a| a >= SILHOUETTE_ALPHA).collect(),
    })
}

/// A camera at `eye` looking at `target` with `up` up the image, of the
/// given size and vertical field of view (degrees), as a camera dict.
#[pyfunction]
#[pyo3(signature = (eye, target, up = (0.0, 0.0, 1.0), width = 320, height = 240, fov_deg = 50.0))]
fn look_at<'py>(
    py: Python<'py>,
    eye: (f64, f64, f64),
    target: (f64, f64, f64),
    up: (f64, f64, f64),
    width: u32,
    height: u32,
    fov_deg: f64,
) -> PyResult<Bound<'py, PyDict>> {
    if width == 0 || height == 0 {
        return Err(PyValueError::new_err("width and height must be positive"));
    }
    let camera = Camera::look_at(
        Point3::new(eye.0, eye.1, eye.2),
        Point3::new(target.0, target.1, target.2),
        Vector3::new(up.0, up.1, up.2),
        width,
        height,
        fov_deg,
    );
    let d = PyDict::new(py);
    d.set_item("width", camera.width)?;
    d.set_item("height", camera.height)?;
    d.set_item("fx", camera.fx)?;
    d.set_item("fy", camera.fy)?;
    d.set_item("cx", camera.cx)?;
    d.set_item("cy", camera.cy)?;
    let m = camera.to_matrix_4x4();
    let flat: Vec<f64> = m.iter().flatten().copied().collect();
    let array = ndarray::Array2::from_shape_vec((4, 4), flat)
        .map_err(|e| ModelError::new_err(e.to_string()))?;
    d.set_item("world_to_camera", array.into_pyarray(py))?;
    Ok(d)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(look_at, m)?)?;
    Ok(())
}
