//! Scene bundles (docs/bundle.md) read into NumPy arrays and written from
//! them, through dm-bundle's validating reader and atomic writer.

use std::path::PathBuf;

use dm_bundle::{Bundle, BundleMeta, BundleWriter, FirstFrameParticles, MaskKind, Tracks};
use image::{GrayImage, RgbImage};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray2, PyReadonlyArray3,
    PyReadonlyArray4, PyUntypedArrayMethods, ToPyArray,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::{BundleError, bundle_error, guarded};

/// A scene bundle read from disk (validated on reading).
#[pyclass(name = "Bundle", module = "deformmaster", frozen)]
#[derive(Debug)]
pub struct PyBundle {
    pub inner: Bundle,
}

pub(crate) fn to_json_object<'py>(
    py: Python<'py>,
    value: &impl serde::Serialize,
) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(value)
        .map_err(|e| BundleError::new_err(format!("encoding JSON: {e}")))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// A `ValueError` unless `index < count` (`what`: camera, frame).
fn check_index(what: &str, index: usize, count: usize) -> PyResult<()> {
    if index >= count {
        return Err(PyValueError::new_err(format!(
            "{what} {index} does not exist; the bundle has {count} {what}s"
        )));
    }
    Ok(())
}

impl PyBundle {
    fn check_camera(&self, camera: usize) -> PyResult<()> {
        check_index("camera", camera, self.inner.meta.cameras.len())
    }

    fn check_frame(&self, frame: usize) -> PyResult<()> {
        check_index("frame", frame, self.inner.frame_count())
    }

    /// The four images of one camera and frame.
    fn frame_images(
        &self,
        camera: usize,
        frame: usize,
    ) -> PyResult<(RgbImage, Vec<f32>, GrayImage, GrayImage)> {
        let b = &self.inner;
        Ok((
            b.load_rgb(camera, frame).map_err(bundle_error)?,
            b.load_depth_m(camera, frame).map_err(bundle_error)?,
            b.load_mask(camera, frame, MaskKind::Object)
                .map_err(bundle_error)?,
            b.load_mask(camera, frame, MaskKind::Hand)
                .map_err(bundle_error)?,
        ))
    }
}

#[pymethods]
impl PyBundle {
    /// The bundle's directory.
    #[getter]
    fn path(&self) -> PathBuf {
        self.inner.root.clone()
    }

    /// `bundle.json` as a dict.
    #[getter]
    fn meta<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_json_object(py, &self.inner.meta)
    }

    #[getter]
    fn frame_count(&self) -> usize {
        self.inner.frame_count()
    }

    #[getter]
    fn camera_count(&self) -> usize {
        self.inner.meta.cameras.len()
    }

    /// The track arrays by file stem: object_points (T, M, 3) float32,
    /// object_visibility and object_motion_valid (T, M) bool, hand_points
    /// (T, H, 3) float32, hand_visibility (T, H) bool.
    #[getter]
    fn tracks<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let t = &self.inner.tracks;
        let d = PyDict::new(py);
        d.set_item("object_points", t.object_points.to_pyarray(py))?;
        d.set_item("object_visibility", t.object_visibility.to_pyarray(py))?;
        d.set_item("object_motion_valid", t.object_motion_valid.to_pyarray(py))?;
        d.set_item("hand_points", t.hand_points.to_pyarray(py))?;
        d.set_item("hand_visibility", t.hand_visibility.to_pyarray(py))?;
        Ok(d)
    }

    /// The first-frame particles by file stem: surface_points,
    /// surface_colors, interior_points, interior_colors, each (N, 3) float32.
    #[getter]
    fn particles<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let p = &self.inner.particles;
        let d = PyDict::new(py);
        d.set_item("surface_points", p.surface_points.to_pyarray(py))?;
        d.set_item("surface_colors", p.surface_colors.to_pyarray(py))?;
        d.set_item("interior_points", p.interior_points.to_pyarray(py))?;
        d.set_item("interior_colors", p.interior_colors.to_pyarray(py))?;
        Ok(d)
    }

    /// Which anchors form each hand: `(start, end)` ranges of the anchors,
    /// in order (`Simulation.plan(rigid_hands=...)`).
    #[getter]
    fn hand_ranges(&self) -> Vec<(usize, usize)> {
        self.inner
            .meta
            .hands
            .iter()
            .map(|h| (h.anchor_range[0], h.anchor_range[1]))
            .collect()
    }

    /// Hand anchor positions of `frame`, (H, 3) float64 metres.
    fn hand_anchors<'py>(
        &self,
        py: Python<'py>,
        frame: usize,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        self.check_frame(frame)?;
        Ok(crate::arrays::points_to_array(
            py,
            &dm_model::hand_anchors(&self.inner, frame),
        ))
    }

    /// RGB image of `camera` at `frame`, (height, width, 3) uint8.
    fn rgb<'py>(
        &self,
        py: Python<'py>,
        camera: usize,
        frame: usize,
    ) -> PyResult<Bound<'py, PyArray3<u8>>> {
        self.check_camera(camera)?;
        self.check_frame(frame)?;
        let image = self.inner.load_rgb(camera, frame).map_err(bundle_error)?;
        let (w, h) = image.dimensions();
        let array = ndarray::Array3::from_shape_vec((h as usize, w as usize, 3), image.into_raw())
            .map_err(|e| BundleError::new_err(e.to_string()))?;
        Ok(array.into_pyarray(py))
    }

    /// Depth of `camera` at `frame` in metres, (height, width) float32,
    /// NaN where there is no measurement.
    fn depth<'py>(
        &self,
        py: Python<'py>,
        camera: usize,
        frame: usize,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        self.check_camera(camera)?;
        self.check_frame(frame)?;
        let spec = &self.inner.meta.cameras[camera];
        let depth = self
            .inner
            .load_depth_m(camera, frame)
            .map_err(bundle_error)?;
        let array =
            ndarray::Array2::from_shape_vec((spec.height as usize, spec.width as usize), depth)
                .map_err(|e| BundleError::new_err(e.to_string()))?;
        Ok(array.into_pyarray(py))
    }

    /// Object (`kind="object"`) or hand (`kind="hand"`) mask of `camera` at
    /// `frame`, (height, width) bool.
    #[pyo3(signature = (camera, frame, kind = "object"))]
    fn mask<'py>(
        &self,
        py: Python<'py>,
        camera: usize,
        frame: usize,
        kind: &str,
    ) -> PyResult<Bound<'py, PyArray2<bool>>> {
        self.check_camera(camera)?;
        self.check_frame(frame)?;
        let kind = match kind {
            "object" => MaskKind::Object,
            "hand" => MaskKind::Hand,
            other => {
                return Err(PyValueError::new_err(format!(
                    "mask kind `{other}`: use \"object\" or \"hand\""
                )));
            }
        };
        let mask = self
            .inner
            .load_mask(camera, frame, kind)
            .map_err(bundle_error)?;
        Ok(gray_to_array(&mask).into_pyarray(py))
    }

    /// Every image of `camera` stacked over frames: rgb (T, h, w, 3) uint8,
    /// depth (T, h, w) float32 metres (NaN: none), mask_object and
    /// mask_hand (T, h, w) bool — what `write_bundle` takes per camera.
    fn images<'py>(&self, py: Python<'py>, camera: usize) -> PyResult<Bound<'py, PyDict>> {
        self.check_camera(camera)?;
        let spec = &self.inner.meta.cameras[camera];
        let (h, w, frames) = (
            spec.height as usize,
            spec.width as usize,
            self.inner.frame_count(),
        );
        let mut rgb = ndarray::Array4::<u8>::zeros((frames, h, w, 3));
        let mut depth = ndarray::Array3::<f32>::zeros((frames, h, w));
        let mut object = ndarray::Array3::<bool>::from_elem((frames, h, w), false);
        let mut hand = ndarray::Array3::<bool>::from_elem((frames, h, w), false);
        for t in 0..frames {
            let (c, d, mo, mh) = self.frame_images(camera, t)?;
            for (dst, src) in rgb
                .index_axis_mut(ndarray::Axis(0), t)
                .iter_mut()
                .zip(c.as_raw())
            {
                *dst = *src;
            }
            for (dst, src) in depth.index_axis_mut(ndarray::Axis(0), t).iter_mut().zip(&d) {
                *dst = *src;
            }
            for (mask, image) in [(&mut object, &mo), (&mut hand, &mh)] {
                for (dst, src) in mask
                    .index_axis_mut(ndarray::Axis(0), t)
                    .iter_mut()
                    .zip(image.as_raw())
                {
                    *dst = *src > 0;
                }
            }
        }
        let dict = PyDict::new(py);
        dict.set_item("rgb", rgb.into_pyarray(py))?;
        dict.set_item("depth", depth.into_pyarray(py))?;
        dict.set_item("mask_object", object.into_pyarray(py))?;
        dict.set_item("mask_hand", hand.into_pyarray(py))?;
        Ok(dict)
    }

    /// Camera `camera` of bundle.json as a dict (intrinsics, world_to_camera).
    fn camera<'py>(&self, py: Python<'py>, camera: usize) -> PyResult<Bound<'py, PyAny>> {
        self.check_camera(camera)?;
        to_json_object(py, &self.inner.meta.cameras[camera])
    }

    fn __repr__(&self) -> String {
        format!(
            "Bundle('{}', {:?}, {} frames, {} cameras, {} tracked points)",
            self.inner.root.display(),
            self.inner.meta.category,
            self.inner.frame_count(),
            self.inner.meta.cameras.len(),
            self.inner.tracks.object_point_count()
        )
    }
}

fn gray_to_array(image: &GrayImage) -> ndarray::Array2<bool> {
    let (w, h) = image.dimensions();
    ndarray::Array2::from_shape_fn((h as usize, w as usize), |(y, x)| {
        image.get_pixel(x as u32, y as u32)[0] > 0
    })
}

fn array_to_gray(mask: ndarray::ArrayView2<'_, bool>) -> GrayImage {
    let (h, w) = mask.dim();
    GrayImage::from_fn(w as u32, h as u32, |x, y| {
        image::Luma([if mask[[y as usize, x as usize]] {
            255
        } else {
            0
        }])
    })
}

/// Reads and validates the bundle in `path`.
#[pyfunction]
fn read_bundle(py: Python<'_>, path: PathBuf) -> PyResult<PyBundle> {
    guarded("read_bundle", || {
        let inner = py.detach(|| Bundle::open(&path)).map_err(bundle_error)?;
        Ok(PyBundle { inner })
    })
}

/// One camera's images for `write_bundle`, typed by the Python layer.
#[derive(FromPyObject)]
struct CameraImages<'py> {
    #[pyo3(item)]
    rgb: PyReadonlyArray4<'py, u8>,
    #[pyo3(item)]
    depth: PyReadonlyArray3<'py, f32>,
    #[pyo3(item)]
    mask_object: PyReadonlyArray3<'py, bool>,
    #[pyo3(item)]
    mask_hand: PyReadonlyArray3<'py, bool>,
}

/// Writes a bundle to `path` (a temporary sibling renamed into place once
/// it validates; an existing `path` is replaced only with `overwrite`).
/// `meta_json` is bundle.json's text; arrays as `Bundle.tracks`,
/// `Bundle.particles` and `Bundle.images(camera)` give them.
#[pyfunction]
#[pyo3(signature = (path, meta_json, object_points, object_visibility, object_motion_valid, hand_points, hand_visibility, surface_points, surface_colors, interior_points, interior_colors, images, overwrite = false))]
fn write_bundle_arrays(
    path: PathBuf,
    meta_json: &str,
    object_points: PyReadonlyArray3<'_, f32>,
    object_visibility: PyReadonlyArray2<'_, bool>,
    object_motion_valid: PyReadonlyArray2<'_, bool>,
    hand_points: PyReadonlyArray3<'_, f32>,
    hand_visibility: PyReadonlyArray2<'_, bool>,
    surface_points: PyReadonlyArray2<'_, f32>,
    surface_colors: PyReadonlyArray2<'_, f32>,
    interior_points: PyReadonlyArray2<'_, f32>,
    interior_colors: PyReadonlyArray2<'_, f32>,
    images: Vec<CameraImages<'_>>,
    overwrite: bool,
) -> PyResult<PyBundle> {
    guarded("write_bundle", || {
        let json_path = path.join(dm_bundle::BUNDLE_JSON);
        let meta: BundleMeta =
            dm_bundle::parse_json(meta_json, &json_path).map_err(bundle_error)?;
        if images.len() != meta.cameras.len() {
            return Err(BundleError::new_err(format!(
                "{}: cameras lists {} cameras but images were given for {}",
                json_path.display(),
                meta.cameras.len(),
                images.len()
            )));
        }
        for (c, set) in images.iter().enumerate() {
            let spec = &meta.cameras[c];
            let expected = [meta.frame_count, spec.height as usize, spec.width as usize];
            let shapes = [
                ("rgb", set.rgb.shape()),
                ("depth", set.depth.shape()),
                ("mask_object", set.mask_object.shape()),
                ("mask_hand", set.mask_hand.shape()),
            ];
            for (name, shape) in shapes {
                if shape[..3] != expected {
                    return Err(BundleError::new_err(format!(
                        "images[{c}][\"{name}\"] has shape {shape:?}; camera \"{}\" needs (frames, height, width) = {expected:?}",
                        spec.name
                    )));
                }
            }
        }
        let tracks = Tracks {
            object_points: object_points.as_array().to_owned(),
            object_visibility: object_visibility.as_array().to_owned(),
            object_motion_valid: object_motion_valid.as_array().to_owned(),
            hand_points: hand_points.as_array().to_owned(),
            hand_visibility: hand_visibility.as_array().to_owned(),
        };
        let particles = FirstFrameParticles {
            surface_points: surface_points.as_array().to_owned(),
            surface_colors: surface_colors.as_array().to_owned(),
            interior_points: interior_points.as_array().to_owned(),
            interior_colors: interior_colors.as_array().to_owned(),
        };
        let mut writer = if overwrite {
            BundleWriter::create_overwrite(&path, meta)
        } else {
            BundleWriter::create(&path, meta)
        }
        .map_err(bundle_error)?;
        writer.write_tracks(&tracks).map_err(bundle_error)?;
        writer.write_particles(&particles).map_err(bundle_error)?;
        for (c, set) in images.iter().enumerate() {
            let (rgb, depth) = (set.rgb.as_array(), set.depth.as_array());
            let (object, hand) = (set.mask_object.as_array(), set.mask_hand.as_array());
            for t in 0..rgb.shape()[0] {
                let frame = rgb.index_axis(ndarray::Axis(0), t);
                let (h, w) = (frame.shape()[0] as u32, frame.shape()[1] as u32);
                let raw: Vec<u8> = frame.iter().copied().collect();
                let rgb_image = RgbImage::from_raw(w, h, raw).ok_or_else(|| {
                    PyValueError::new_err(format!(
                        "images[{c}][\"rgb\"] frame {t} is not (h, w, 3)"
                    ))
                })?;
                let depth_m: Vec<f32> = depth
                    .index_axis(ndarray::Axis(0), t)
                    .iter()
                    .copied()
                    .collect();
                writer
                    .write_frame_images(
                        c,
                        t,
                        &rgb_image,
                        &depth_m,
                        &array_to_gray(object.index_axis(ndarray::Axis(0), t)),
                        &array_to_gray(hand.index_axis(ndarray::Axis(0), t)),
                    )
                    .map_err(bundle_error)?;
            }
        }
        let inner = writer.finish().map_err(bundle_error)?;
        Ok(PyBundle { inner })
    })
}

/// Frame numbers of a split as the `range` they cover.
#[pyfunction]
fn split_frames<'py>(
    py: Python<'py>,
    bundle: &PyBundle,
    split: &str,
) -> PyResult<Bound<'py, PyArray1<usize>>> {
    let s = &bundle.inner.meta.split;
    let range = match split {
        "train" => s.train,
        "test" => s.test,
        other => {
            return Err(PyValueError::new_err(format!(
                "split `{other}`: use \"train\" or \"test\""
            )));
        }
    };
    Ok(ndarray::Array1::from_iter(range[0]..range[1]).into_pyarray(py))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyBundle>()?;
    m.add_function(wrap_pyfunction!(read_bundle, m)?)?;
    m.add_function(wrap_pyfunction!(write_bundle_arrays, m)?)?;
    m.add_function(wrap_pyfunction!(split_frames, m)?)?;
    Ok(())
}
