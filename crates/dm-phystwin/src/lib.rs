//! Importing a PhysTwin case directory (method.md §10) into a scene bundle.
//!
//! The mapping, and every choice the case format leaves open, is documented
//! in `docs/bundle.md` ("Importing PhysTwin cases"). In short:
//!
//! | case | bundle |
//! |---|---|
//! | `final_data.pkl` `object_points`, `object_visibilities`, `object_motions_valid` | `tracks/object_*` |
//! | `controller_points` (T, M, 3) | `tracks/hand_points`, one hand `controller`, all visible |
//! | `object_points[0]` + `surface_points`; `interior_points` | `particles/surface_*`; `particles/interior_*` |
//! | `object_colors[0]` (nearest tracked point for prior points) | particle colours |
//! | `calibrate.pkl` camera-to-world (inverted) + `metadata.json` `intrinsics`, `WH`, `fps` | `cameras`, `fps` |
//! | `split.json` `train`, `test` | `split` |
//! | `color/<c>/<t>.png`, `depth/<c>/<t>.npy` (millimetres) | `views/cam<c>/rgb`, `depth` |
//! | `mask/mask_info_<c>.json` + `mask/<c>/<id>/<t>.png`, else tracks projected | `mask_object`, `mask_hand` |
//!
//! World frame: the calibration board, metres, table at z = 0, objects at
//! z < 0, so the bundle's `up_axis` is `-z` with the floor at height 0.

use std::fs;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use dm_bundle::{
    Bundle, BundleError, BundleMeta, BundleWriter, CameraSpec, Category, FirstFrameParticles,
    HandSpec, Provenance, ROTATION_TOLERANCE, Split, Tracks, UpAxis, shape_string,
};
use dm_numpy::ndarray_raw::{NdArray, parse_descriptor};
use dm_numpy::pickle::{self, Value};
use image::{GrayImage, RgbImage};
use nalgebra::{Matrix3, Matrix4, SymmetricEigen, Vector3};
use ndarray::{Array2, Array3};
use ndarray_npy::npy::header::Header;
use serde_json::Value as Json;

pub const FINAL_DATA_FILE: &str = "final_data.pkl";
pub const CALIBRATE_FILE: &str = "calibrate.pkl";
pub const METADATA_FILE: &str = "metadata.json";
pub const SPLIT_FILE: &str = "split.json";
pub const COLOR_DIR: &str = "color";
pub const DEPTH_DIR: &str = "depth";
pub const MASK_DIR: &str = "mask";

/// The label PhysTwin's segmentation gives the hands (its `controller_name`).
pub const DEFAULT_CONTROLLER_LABEL: &str = "hand";
/// Name of the single hand the controller points become.
pub const CONTROLLER_HAND_NAME: &str = "controller";
/// Depth `.npy` values per metre (the case stores millimetres).
const DEPTH_NPY_UNITS_PER_METRE: f64 = 1000.0;
/// Tolerance on the camera-to-world matrices' last row `[0, 0, 0, 1]`.
const HOMOGENEOUS_ROW_TOLERANCE: f64 = 1e-6;
/// Tolerance on the intrinsics' fixed entries (zero skew, last row `[0, 0, 1]`).
const INTRINSICS_TOLERANCE: f64 = 1e-6;
/// Category heuristic: an axis counts as thin when its spread is below this
/// fraction of the next larger one.
const THIN_AXIS_RATIO: f64 = 0.25;

type Result<T, E = BundleError> = std::result::Result<T, E>;

/// Choices the case itself does not record.
#[derive(Debug, Clone)]
pub struct ImportOptions {
    /// Object category; inferred from the first-frame points when `None`.
    pub category: Option<Category>,
    /// Segmentation label of the hands in `mask/mask_info_<c>.json`.
    pub controller_label: String,
    /// Replace an existing bundle (only once the new one is complete).
    pub overwrite: bool,
}

impl Default for ImportOptions {
    fn default() -> Self {
        ImportOptions {
            category: None,
            controller_label: DEFAULT_CONTROLLER_LABEL.to_owned(),
            overwrite: false,
        }
    }
}

/// Where the bundle's masks came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MaskSource {
    /// PhysTwin's segmentation, `mask/<c>/<id>/<t>.png`.
    Segmentation,
    /// No `mask/` directory: tracked points splatted into each camera.
    ProjectedTracks,
}

/// What an import produced.
#[derive(Debug, Clone)]
pub struct ImportSummary {
    pub bundle: Bundle,
    pub mask_source: MaskSource,
    /// True when the category was inferred rather than given.
    pub category_inferred: bool,
}

/// Reads the PhysTwin case at `case_dir` and writes a validated bundle at
/// `out` (atomically: `out` appears complete or not at all). The case is only read.
pub fn import_phystwin(
    case_dir: &Path,
    out: &Path,
    options: &ImportOptions,
) -> Result<ImportSummary> {
    if !case_dir.is_dir() {
        return Err(BundleError::new(
            case_dir,
            dm_bundle::IO_FIELD,
            "PhysTwin case directory does not exist",
        ));
    }
    let tracks = read_final_data(&case_dir.join(FINAL_DATA_FILE))?;
    let frame_count = tracks.frame_count;
    let metadata = read_metadata(&case_dir.join(METADATA_FILE), frame_count)?;
    let camera_to_world = read_calibration(&case_dir.join(CALIBRATE_FILE))?;
    if camera_to_world.len() != metadata.intrinsics.len() {
        return Err(BundleError::new(
            case_dir.join(METADATA_FILE),
            "intrinsics",
            format!(
                "has {} cameras but {CALIBRATE_FILE} has {}",
                metadata.intrinsics.len(),
                camera_to_world.len()
            ),
        ));
    }
    let split = read_split(&case_dir.join(SPLIT_FILE), frame_count)?;
    let cameras: Vec<CameraSpec> = camera_to_world
        .iter()
        .zip(&metadata.intrinsics)
        .enumerate()
        .map(|(c, (pose, k))| CameraSpec {
            name: format!("cam{c}"),
            width: metadata.width,
            height: metadata.height,
            fx: k[0][0],
            fy: k[1][1],
            cx: k[0][2],
            cy: k[1][2],
            world_to_camera: *pose,
            axes: dm_bundle::CAMERA_AXES_OPENCV.to_owned(),
        })
        .collect();

    let mask_dir = case_dir.join(MASK_DIR);
    let mask_source = if mask_dir.is_dir() {
        MaskSource::Segmentation
    } else {
        MaskSource::ProjectedTracks
    };
    let (category, category_inferred) = match options.category {
        Some(category) => (category, false),
        None => (infer_category(&tracks), true),
    };

    let mut meta = BundleMeta::new(frame_count, metadata.fps, category, cameras);
    meta.split = split;
    meta.up_axis = UpAxis::NegZ;
    meta.floor_height_m = 0.0;
    let hand_count = tracks.controller_points.shape()[1];
    if hand_count > 0 {
        meta.hands = vec![HandSpec {
            name: CONTROLLER_HAND_NAME.to_owned(),
            anchor_range: [0, hand_count],
        }];
    }
    meta.provenance = Provenance {
        tool: format!("dm-prep {}", env!("CARGO_PKG_VERSION")),
        source: format!("PhysTwin case {}", absolute(case_dir).display()),
        created_unix_s: SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_secs()),
        notes: provenance_notes(mask_source, category_inferred, &options.controller_label),
    };

    let mut writer = if options.overwrite {
        BundleWriter::create_overwrite(out, meta)?
    } else {
        BundleWriter::create(out, meta)?
    };
    let mask_labels = match mask_source {
        MaskSource::Segmentation => Some(
            (0..camera_to_world.len())
                .map(|c| read_mask_info(&mask_dir, c, &options.controller_label))
                .collect::<Result<Vec<_>>>()?,
        ),
        MaskSource::ProjectedTracks => None,
    };
    let cameras = writer.meta().cameras.clone();
    let object_spacing = typical_spacing(&tracks.object_points);
    let controller_spacing = typical_spacing(&tracks.controller_points);
    let controller_visible = all_visible(&tracks.controller_points);
    for (c, camera) in cameras.iter().enumerate() {
        for t in 0..frame_count {
            let rgb = read_color(&case_dir.join(COLOR_DIR), c, t, camera)?;
            let depth_m = read_depth(&case_dir.join(DEPTH_DIR), c, t, camera)?;
            let (mask_object, mask_hand) = match &mask_labels {
                Some(labels) => (
                    read_mask_union(&mask_dir, c, t, &[labels[c].object], camera)?,
                    read_mask_union(&mask_dir, c, t, &labels[c].hands, camera)?,
                ),
                None => (
                    project_points(
                        camera,
                        &tracks.object_points,
                        &tracks.visibility,
                        t,
                        object_spacing,
                    ),
                    project_points(
                        camera,
                        &tracks.controller_points,
                        &controller_visible,
                        t,
                        controller_spacing,
                    ),
                ),
            };
            writer.write_frame_images(c, t, &rgb, &depth_m, &mask_object, &mask_hand)?;
        }
    }
    writer.write_tracks(&Tracks {
        object_points: tracks.object_points.clone(),
        object_visibility: tracks.visibility.clone(),
        object_motion_valid: tracks.motion_valid.clone(),
        hand_points: tracks.controller_points.clone(),
        hand_visibility: all_visible(&tracks.controller_points),
    })?;
    writer.write_particles(&first_frame_particles(&tracks))?;
    let bundle = writer.finish()?;
    Ok(ImportSummary {
        bundle,
        mask_source,
        category_inferred,
    })
}

fn absolute(path: &Path) -> PathBuf {
    fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf())
}

fn provenance_notes(mask_source: MaskSource, category_inferred: bool, label: &str) -> String {
    let masks = match mask_source {
        MaskSource::Segmentation => format!("masks from mask/ (hand label \"{label}\")"),
        MaskSource::ProjectedTracks => {
            "no mask/ in the case: masks are visible tracked points and controller points \
             splatted into each camera (approximate)"
                .to_owned()
        }
    };
    let category = if category_inferred {
        "category inferred from the first-frame points"
    } else {
        "category given"
    };
    format!(
        "PhysTwin import: hand = controller_points (always visible); surface particles = \
         object_points[0] + surface_points; {masks}; {category}"
    )
}

/// The arrays of `final_data.pkl`, checked and in bundle types.
#[derive(Debug)]
struct CaseTracks {
    frame_count: usize,
    object_points: Array3<f32>,
    object_colors: Array3<f32>,
    visibility: Array2<bool>,
    motion_valid: Array2<bool>,
    controller_points: Array3<f32>,
    surface_points: Array2<f32>,
    interior_points: Array2<f32>,
}

/// Reads a pickle file into a value; errors name the file and the byte offset.
pub fn read_pickle_file(path: &Path) -> Result<Value> {
    let limits = pickle::Limits::default();
    let size = fs::metadata(path)
        .map_err(|e| BundleError::io(path, "reading", &e))?
        .len();
    if usize::try_from(size).map_or(true, |s| s > limits.max_input_bytes) {
        return Err(BundleError::new(
            path,
            "(pickle)",
            format!(
                "file is {size} bytes, more than the limit of {}",
                limits.max_input_bytes
            ),
        ));
    }
    let bytes = fs::read(path).map_err(|e| BundleError::io(path, "reading", &e))?;
    pickle::from_slice_with_limits(&bytes, &limits)
        .map_err(|e| BundleError::new(path, "(pickle)", format!("cannot unpickle: {e}")))
}

/// One numeric array of `final_data.pkl` with its dimensions checked.
/// `dims` are the expected sizes (`None` = any); `names` name them for messages.
fn dict_array<'a>(data: &'a Value, path: &Path, key: &str) -> Result<&'a NdArray> {
    let Value::Dict(items) = data else {
        return Err(BundleError::new(
            path,
            "(top level)",
            format!("expected a dict of numpy arrays, found {}", data.describe()),
        ));
    };
    match data.get(key) {
        Some(Value::Array(array)) => Ok(array),
        Some(other) => Err(BundleError::new(
            path,
            key,
            format!("expected a numpy array, found {}", other.describe()),
        )),
        None => {
            let present: Vec<String> = items
                .iter()
                .map(|(k, _)| match k {
                    Value::Str(s) => s.clone(),
                    other => other.describe(),
                })
                .collect();
            Err(BundleError::new(
                path,
                key,
                format!("missing (keys present: {})", present.join(", ")),
            ))
        }
    }
}

fn check_shape(
    array: &NdArray,
    path: &Path,
    key: &str,
    dims: &[Option<usize>],
    spelled: &str,
) -> Result<()> {
    let shape = array.shape();
    let fits = shape.len() == dims.len()
        && shape
            .iter()
            .zip(dims)
            .all(|(&d, want)| want.is_none_or(|w| w == d));
    if fits {
        Ok(())
    } else {
        Err(BundleError::new(
            path,
            key,
            format!("expected shape {spelled}, found {}", shape_string(shape)),
        ))
    }
}

/// Index of a flat C-order position as `[i,j,k]`, for messages.
fn index_string(shape: &[usize], mut flat: usize) -> String {
    let mut index = vec![0; shape.len()];
    for (axis, &dim) in shape.iter().enumerate().rev() {
        if dim > 0 {
            index[axis] = flat % dim;
            flat /= dim;
        }
    }
    index
        .iter()
        .map(usize::to_string)
        .collect::<Vec<_>>()
        .join(",")
}

/// A float32/float64 array as finite f32 values.
fn float_values(array: &NdArray, path: &Path, key: &str) -> Result<Vec<f32>> {
    if !array.element().is_float() {
        return Err(BundleError::new(
            path,
            key,
            format!("expected float32 or float64, found {}", array.element()),
        ));
    }
    let values = array.to_f64_vec().unwrap_or_default();
    values
        .iter()
        .enumerate()
        .map(|(i, &v)| {
            let single = v as f32;
            if single.is_finite() {
                Ok(single)
            } else {
                Err(BundleError::new(
                    path,
                    format!("{key}[{}]", index_string(array.shape(), i)),
                    format!("must be finite (as float32), found {v}"),
                ))
            }
        })
        .collect()
}

/// A bool array; integer arrays holding only 0 and 1 are accepted as bools too.
fn bool_values(array: &NdArray, path: &Path, key: &str) -> Result<Vec<bool>> {
    if let Some(bools) = array.as_bools() {
        return Ok(bools.to_vec());
    }
    if array.element().is_integer() {
        let values = array.to_f64_vec().unwrap_or_default();
        return values
            .iter()
            .enumerate()
            .map(|(i, &v)| match v {
                0.0 => Ok(false),
                1.0 => Ok(true),
                _ => Err(BundleError::new(
                    path,
                    format!("{key}[{}]", index_string(array.shape(), i)),
                    format!("a validity flag must be 0 or 1, found {v}"),
                )),
            })
            .collect();
    }
    Err(BundleError::new(
        path,
        key,
        format!("expected bool, found {}", array.element()),
    ))
}

fn to_array3(values: Vec<f32>, shape: &[usize], path: &Path, key: &str) -> Result<Array3<f32>> {
    Array3::from_shape_vec((shape[0], shape[1], shape[2]), values)
        .map_err(|e| BundleError::new(path, key, e.to_string()))
}

fn to_points2(values: Vec<f32>, shape: &[usize], path: &Path, key: &str) -> Result<Array2<f32>> {
    Array2::from_shape_vec((shape[0], shape[1]), values)
        .map_err(|e| BundleError::new(path, key, e.to_string()))
}

fn to_bool2(values: Vec<bool>, shape: &[usize], path: &Path, key: &str) -> Result<Array2<bool>> {
    Array2::from_shape_vec((shape[0], shape[1]), values)
        .map_err(|e| BundleError::new(path, key, e.to_string()))
}

fn read_final_data(path: &Path) -> Result<CaseTracks> {
    let data = read_pickle_file(path)?;

    let key = "object_points";
    let points = dict_array(&data, path, key)?;
    check_shape(points, path, key, &[None, None, Some(3)], "(T, N, 3)")?;
    let (frame_count, n) = (points.shape()[0], points.shape()[1]);
    if frame_count < 2 {
        return Err(BundleError::new(
            path,
            key,
            format!("needs at least 2 frames, found {frame_count}"),
        ));
    }
    if n == 0 {
        return Err(BundleError::new(path, key, "has no points (N = 0)"));
    }
    let object_points = to_array3(float_values(points, path, key)?, points.shape(), path, key)?;

    let key = "object_colors";
    let colors = dict_array(&data, path, key)?;
    check_shape(
        colors,
        path,
        key,
        &[Some(frame_count), Some(n), Some(3)],
        &format!("({frame_count}, {n}, 3)"),
    )?;
    let color_values = float_values(colors, path, key)?;
    if let Some(i) = color_values.iter().position(|c| !(0.0..=1.0).contains(c)) {
        return Err(BundleError::new(
            path,
            format!("{key}[{}]", index_string(colors.shape(), i)),
            format!("colours must be in [0, 1], found {}", color_values[i]),
        ));
    }
    let object_colors = to_array3(color_values, colors.shape(), path, key)?;

    let mut flags = Vec::new();
    for key in ["object_visibilities", "object_motions_valid"] {
        let array = dict_array(&data, path, key)?;
        check_shape(
            array,
            path,
            key,
            &[Some(frame_count), Some(n)],
            &format!("({frame_count}, {n})"),
        )?;
        flags.push(to_bool2(
            bool_values(array, path, key)?,
            array.shape(),
            path,
            key,
        )?);
    }
    let motion_valid = flags.pop().unwrap_or_default();
    let visibility = flags.pop().unwrap_or_default();

    let key = "controller_points";
    let controller = dict_array(&data, path, key)?;
    check_shape(
        controller,
        path,
        key,
        &[Some(frame_count), None, Some(3)],
        &format!("({frame_count}, M, 3)"),
    )?;
    let controller_points = to_array3(
        float_values(controller, path, key)?,
        controller.shape(),
        path,
        key,
    )?;

    let mut clouds = Vec::new();
    for key in ["surface_points", "interior_points"] {
        let array = dict_array(&data, path, key)?;
        check_shape(array, path, key, &[None, Some(3)], "(K, 3)")?;
        clouds.push(to_points2(
            float_values(array, path, key)?,
            array.shape(),
            path,
            key,
        )?);
    }
    let interior_points = clouds.pop().unwrap_or_else(|| Array2::zeros((0, 3)));
    let surface_points = clouds.pop().unwrap_or_else(|| Array2::zeros((0, 3)));

    Ok(CaseTracks {
        frame_count,
        object_points,
        object_colors,
        visibility,
        motion_valid,
        controller_points,
        surface_points,
        interior_points,
    })
}

/// `calibrate.pkl`: camera-to-world 4x4 matrices, returned as world-to-camera.
fn read_calibration(path: &Path) -> Result<Vec<[[f64; 4]; 4]>> {
    let value = read_pickle_file(path)?;
    let matrices: Vec<(String, Vec<f64>)> = match &value {
        Value::List(items) | Value::Tuple(items) => items
            .iter()
            .enumerate()
            .map(|(c, item)| match item {
                Value::Array(a) if a.shape() == [4, 4] && a.element().is_float() => {
                    Ok((format!("[{c}]"), a.to_f64_vec().unwrap_or_default()))
                }
                Value::Array(a) => Err(BundleError::new(
                    path,
                    format!("[{c}]"),
                    format!(
                        "expected a float 4x4 camera-to-world matrix, found {}",
                        a.describe()
                    ),
                )),
                other => Err(BundleError::new(
                    path,
                    format!("[{c}]"),
                    format!("expected a numpy 4x4 matrix, found {}", other.describe()),
                )),
            })
            .collect::<Result<_>>()?,
        Value::Array(a)
            if a.shape().len() == 3 && a.shape()[1..] == [4, 4] && a.element().is_float() =>
        {
            let all = a.to_f64_vec().unwrap_or_default();
            all.chunks_exact(16)
                .enumerate()
                .map(|(c, m)| (format!("[{c}]"), m.to_vec()))
                .collect()
        }
        other => {
            return Err(BundleError::new(
                path,
                "(top level)",
                format!(
                    "expected a list of 4x4 camera-to-world matrices, found {}",
                    other.describe()
                ),
            ));
        }
    };
    if matrices.is_empty() {
        return Err(BundleError::new(path, "(top level)", "no cameras"));
    }
    matrices
        .iter()
        .map(|(field, m)| world_to_camera(m, path, field))
        .collect()
}

/// Inverts a rigid camera-to-world transform after checking it is one.
fn world_to_camera(m: &[f64], path: &Path, field: &str) -> Result<[[f64; 4]; 4]> {
    let err = |problem: String| BundleError::new(path, field, problem);
    if let Some(v) = m.iter().find(|v| !v.is_finite()) {
        return Err(err(format!("must be finite, found {v}")));
    }
    let pose = Matrix4::from_row_slice(m);
    let last_row = [pose[(3, 0)], pose[(3, 1)], pose[(3, 2)], pose[(3, 3)]];
    if last_row
        .iter()
        .zip([0.0, 0.0, 0.0, 1.0])
        .any(|(a, b)| (a - b).abs() > HOMOGENEOUS_ROW_TOLERANCE)
    {
        return Err(err(format!(
            "last row must be [0, 0, 0, 1], found {last_row:?}"
        )));
    }
    let rotation: Matrix3<f64> = pose.fixed_view::<3, 3>(0, 0).into_owned();
    let orthogonality = (rotation * rotation.transpose() - Matrix3::identity())
        .abs()
        .max();
    if orthogonality > ROTATION_TOLERANCE || rotation.determinant() <= 0.0 {
        return Err(err(format!(
            "rotation part is not a proper rotation (|R Rᵀ - I| = {orthogonality:.2e}, det = {:.4})",
            rotation.determinant()
        )));
    }
    let translation: Vector3<f64> = pose.fixed_view::<3, 1>(0, 3).into_owned();
    let inverse_rotation = rotation.transpose();
    let inverse_translation = -(inverse_rotation * translation);
    let mut out = [[0.0; 4]; 4];
    for r in 0..3 {
        for c in 0..3 {
            out[r][c] = inverse_rotation[(r, c)];
        }
        out[r][3] = inverse_translation[r];
    }
    out[3] = [0.0, 0.0, 0.0, 1.0];
    Ok(out)
}

#[derive(Debug)]
struct Metadata {
    intrinsics: Vec<[[f64; 3]; 3]>,
    width: u32,
    height: u32,
    fps: f64,
}

fn read_json_file(path: &Path) -> Result<Json> {
    let text = fs::read_to_string(path).map_err(|e| BundleError::io(path, "reading", &e))?;
    serde_json::from_str(&text).map_err(|e| BundleError::new(path, "(json syntax)", e.to_string()))
}

fn json_number(value: &Json, path: &Path, field: &str) -> Result<f64> {
    value
        .as_f64()
        .filter(|v| v.is_finite())
        .ok_or_else(|| BundleError::new(path, field, format!("expected a number, found {value}")))
}

fn json_count(value: &Json, path: &Path, field: &str) -> Result<usize> {
    value
        .as_u64()
        .and_then(|v| usize::try_from(v).ok())
        .ok_or_else(|| {
            BundleError::new(
                path,
                field,
                format!("expected a non-negative integer, found {value}"),
            )
        })
}

fn json_key<'a>(root: &'a Json, path: &Path, key: &str) -> Result<&'a Json> {
    if !root.is_object() {
        return Err(BundleError::new(
            path,
            "(top level)",
            "expected a JSON object",
        ));
    }
    root.get(key)
        .ok_or_else(|| BundleError::new(path, key, "missing"))
}

fn json_array<'a>(
    value: &'a Json,
    path: &Path,
    field: &str,
    len: Option<usize>,
) -> Result<&'a Vec<Json>> {
    match value.as_array() {
        Some(items) if len.is_none_or(|l| l == items.len()) => Ok(items),
        _ => Err(BundleError::new(
            path,
            field,
            match len {
                Some(l) => format!("expected an array of {l}, found {value}"),
                None => format!("expected an array, found {value}"),
            },
        )),
    }
}

fn read_metadata(path: &Path, frame_count: usize) -> Result<Metadata> {
    let root = read_json_file(path)?;
    let mut intrinsics = Vec::new();
    for (c, k) in json_array(
        json_key(&root, path, "intrinsics")?,
        path,
        "intrinsics",
        None,
    )?
    .iter()
    .enumerate()
    {
        let field = format!("intrinsics[{c}]");
        let mut matrix = [[0.0; 3]; 3];
        for (r, row) in json_array(k, path, &field, Some(3))?.iter().enumerate() {
            let row_field = format!("{field}[{r}]");
            for (col, v) in json_array(row, path, &row_field, Some(3))?
                .iter()
                .enumerate()
            {
                matrix[r][col] = json_number(v, path, &format!("{row_field}[{col}]"))?;
            }
        }
        let fixed = [
            (0, 1, 0.0),
            (1, 0, 0.0),
            (2, 0, 0.0),
            (2, 1, 0.0),
            (2, 2, 1.0),
        ];
        if let Some(&(r, col, want)) = fixed
            .iter()
            .find(|&&(r, col, want)| (matrix[r][col] - want).abs() > INTRINSICS_TOLERANCE)
        {
            return Err(BundleError::new(
                path,
                format!("{field}[{r}][{col}]"),
                format!(
                    "a pinhole without skew needs {want} here, found {}",
                    matrix[r][col]
                ),
            ));
        }
        for (r, name) in [(0, "fx"), (1, "fy")] {
            if matrix[r][r] <= 0.0 {
                return Err(BundleError::new(
                    path,
                    format!("{field}[{r}][{r}]"),
                    format!("focal length {name} must be > 0, found {}", matrix[r][r]),
                ));
            }
        }
        intrinsics.push(matrix);
    }
    if intrinsics.is_empty() {
        return Err(BundleError::new(path, "intrinsics", "no cameras"));
    }
    let wh = json_array(json_key(&root, path, "WH")?, path, "WH", Some(2))?;
    let mut size = [0u32; 2];
    for (i, v) in wh.iter().enumerate() {
        let field = format!("WH[{i}]");
        size[i] = json_count(v, path, &field)?
            .try_into()
            .ok()
            .filter(|&s: &u32| s > 0)
            .ok_or_else(|| {
                BundleError::new(
                    path,
                    &field,
                    format!("image size must be 1..2^32, found {v}"),
                )
            })?;
    }
    let fps = json_number(json_key(&root, path, "fps")?, path, "fps")?;
    if fps <= 0.0 {
        return Err(BundleError::new(
            path,
            "fps",
            format!("must be > 0, found {fps}"),
        ));
    }
    let frame_num = json_count(json_key(&root, path, "frame_num")?, path, "frame_num")?;
    if frame_num != frame_count {
        return Err(BundleError::new(
            path,
            "frame_num",
            format!("is {frame_num} but {FINAL_DATA_FILE} object_points has {frame_count} frames"),
        ));
    }
    Ok(Metadata {
        intrinsics,
        width: size[0],
        height: size[1],
        fps,
    })
}

fn read_split(path: &Path, frame_count: usize) -> Result<Split> {
    let root = read_json_file(path)?;
    let frame_len = json_count(json_key(&root, path, "frame_len")?, path, "frame_len")?;
    if frame_len != frame_count {
        return Err(BundleError::new(
            path,
            "frame_len",
            format!("is {frame_len} but {FINAL_DATA_FILE} object_points has {frame_count} frames"),
        ));
    }
    let mut ranges = [[0usize; 2]; 2];
    for (range, key) in ranges.iter_mut().zip(["train", "test"]) {
        let items = json_array(json_key(&root, path, key)?, path, key, Some(2))?;
        for (slot, (i, v)) in range.iter_mut().zip(items.iter().enumerate()) {
            *slot = json_count(v, path, &format!("{key}[{i}]"))?;
        }
        if !(range[0] < range[1] && range[1] <= frame_count) {
            return Err(BundleError::new(
                path,
                key,
                format!(
                    "must be a non-empty range [start, end) within [0, {frame_count}], found {range:?}"
                ),
            ));
        }
    }
    let [train, test] = ranges;
    if train[0] < test[1] && test[0] < train[1] {
        return Err(BundleError::new(
            path,
            "test",
            format!("overlaps train {train:?}: {test:?}"),
        ));
    }
    Ok(Split { train, test })
}

fn frame_path(root: &Path, camera: usize, frame: usize, extension: &str) -> PathBuf {
    root.join(camera.to_string())
        .join(format!("{frame}.{extension}"))
}

fn decode_image(path: &Path, camera: &CameraSpec) -> Result<image::DynamicImage> {
    let bytes = fs::read(path).map_err(|e| BundleError::io(path, "reading", &e))?;
    let image = image::load_from_memory(&bytes)
        .map_err(|e| BundleError::new(path, "png", format!("cannot decode: {e}")))?;
    if (image.width(), image.height()) != (camera.width, camera.height) {
        return Err(BundleError::new(
            path,
            "size",
            format!(
                "image is {}x{} but metadata.json WH is {}x{}",
                image.width(),
                image.height(),
                camera.width,
                camera.height
            ),
        ));
    }
    Ok(image)
}

fn read_color(root: &Path, c: usize, t: usize, camera: &CameraSpec) -> Result<RgbImage> {
    Ok(decode_image(&frame_path(root, c, t, "png"), camera)?.to_rgb8())
}

/// `depth/<c>/<t>.npy` in millimetres (any integer or float dtype) as metres;
/// 0, negative and non-finite values mean "no measurement".
fn read_depth(root: &Path, c: usize, t: usize, camera: &CameraSpec) -> Result<Vec<f32>> {
    let path = frame_path(root, c, t, "npy");
    let bytes = fs::read(&path).map_err(|e| BundleError::io(&path, "reading", &e))?;
    let mut data: &[u8] = &bytes;
    let header = Header::from_reader(&mut data)
        .map_err(|e| BundleError::new(&path, "header", format!("cannot parse .npy header: {e}")))?;
    let descriptor = header.type_descriptor.as_string().map(String::as_str);
    let Some((element, order)) = descriptor
        .and_then(parse_descriptor)
        .filter(|(e, _)| *e != dm_numpy::Element::Bool)
    else {
        return Err(BundleError::new(
            &path,
            "dtype",
            format!(
                "expected a numeric depth in millimetres (e.g. uint16), found {}",
                header.type_descriptor
            ),
        ));
    };
    let expected = [camera.height as usize, camera.width as usize];
    if header.shape != expected {
        return Err(BundleError::new(
            &path,
            "shape",
            format!(
                "expected (H, W) = {} from metadata.json WH, found {}",
                shape_string(&expected),
                shape_string(&header.shape)
            ),
        ));
    }
    let array = NdArray::from_raw(
        element,
        order,
        header.shape.clone(),
        header.layout.is_fortran(),
        data,
    )
    .map_err(|e| BundleError::new(&path, "data", e))?;
    Ok(array
        .to_f64_vec()
        .unwrap_or_default()
        .into_iter()
        .map(|mm| {
            if mm.is_finite() && mm > 0.0 {
                (mm / DEPTH_NPY_UNITS_PER_METRE) as f32
            } else {
                f32::NAN
            }
        })
        .collect())
}

/// Which segmentation ids of one camera are the object and the hands.
#[derive(Debug)]
struct MaskLabels {
    object: u64,
    hands: Vec<u64>,
}

fn read_mask_info(mask_dir: &Path, camera: usize, controller_label: &str) -> Result<MaskLabels> {
    let path = mask_dir.join(format!("mask_info_{camera}.json"));
    let root = read_json_file(&path)?;
    let Some(entries) = root.as_object() else {
        return Err(BundleError::new(
            &path,
            "(top level)",
            "expected an object {id: label}",
        ));
    };
    let mut objects = Vec::new();
    let mut hands = Vec::new();
    for (id_text, label) in entries {
        let id: u64 = id_text.parse().map_err(|_| {
            BundleError::new(&path, id_text, "mask ids must be non-negative integers")
        })?;
        match label.as_str() {
            Some(l) if l == controller_label => hands.push(id),
            Some(_) => objects.push(id),
            None => {
                return Err(BundleError::new(
                    &path,
                    id_text,
                    format!("label must be a string, found {label}"),
                ));
            }
        }
    }
    match objects.as_slice() {
        [object] => Ok(MaskLabels {
            object: *object,
            hands,
        }),
        _ => Err(BundleError::new(
            &path,
            "(top level)",
            format!(
                "expected exactly one object label besides \"{controller_label}\", found {} ({:?})",
                objects.len(),
                entries
            ),
        )),
    }
}

/// Union of the masks `mask/<c>/<id>/<t>.png` over `ids` (non-zero = inside), as 0/255.
fn read_mask_union(
    mask_dir: &Path,
    c: usize,
    t: usize,
    ids: &[u64],
    camera: &CameraSpec,
) -> Result<GrayImage> {
    let mut union = GrayImage::new(camera.width, camera.height);
    for id in ids {
        let path = mask_dir
            .join(c.to_string())
            .join(id.to_string())
            .join(format!("{t}.png"));
        let mask = decode_image(&path, camera)?.to_luma8();
        for (out, inside) in union.pixels_mut().zip(mask.pixels()) {
            if inside.0[0] != 0 {
                out.0[0] = 255;
            }
        }
    }
    Ok(union)
}

fn all_visible(points: &Array3<f32>) -> Array2<bool> {
    Array2::from_elem((points.shape()[0], points.shape()[1]), true)
}

/// Mean distance from each frame-0 point to its nearest neighbour: the
/// spacing of the tracked samples, used as the splat size of projected masks.
fn typical_spacing(points: &Array3<f32>) -> f64 {
    let n = points.shape()[1];
    if n < 2 {
        return 0.005;
    }
    let p = |i: usize| {
        Vector3::new(points[[0, i, 0]], points[[0, i, 1]], points[[0, i, 2]]).cast::<f64>()
    };
    let total: f64 = (0..n)
        .map(|i| {
            (0..n)
                .filter(|&j| j != i)
                .map(|j| (p(i) - p(j)).norm())
                .fold(f64::INFINITY, f64::min)
        })
        .sum();
    total / n as f64
}

/// A mask from the visible points of frame `t`, each a disc as wide as the
/// point spacing at its depth (at least one pixel).
fn project_points(
    camera: &CameraSpec,
    points: &Array3<f32>,
    visible: &Array2<bool>,
    t: usize,
    spacing: f64,
) -> GrayImage {
    let mut mask = GrayImage::new(camera.width, camera.height);
    for n in 0..points.shape()[1] {
        if !visible[[t, n]] {
            continue;
        }
        let world = [0, 1, 2].map(|k| f64::from(points[[t, n, k]]));
        let depth = camera.world_to_camera_point(world)[2];
        let Some([u, v]) = camera.project(world) else {
            continue;
        };
        let radius = (camera.fx * spacing / depth).max(1.0);
        let (x0, x1) = (
            (u - radius).floor().max(0.0),
            (u + radius).ceil().min(f64::from(camera.width) - 1.0),
        );
        let (y0, y1) = (
            (v - radius).floor().max(0.0),
            (v + radius).ceil().min(f64::from(camera.height) - 1.0),
        );
        if x0 > x1 || y0 > y1 {
            continue;
        }
        for y in y0 as u32..=y1 as u32 {
            for x in x0 as u32..=x1 as u32 {
                let (dx, dy) = (f64::from(x) + 0.5 - u, f64::from(y) + 0.5 - v);
                if dx * dx + dy * dy <= radius * radius {
                    mask.put_pixel(x, y, image::Luma([255]));
                }
            }
        }
    }
    mask
}

/// Surface = tracked points at frame 0 then the shape prior's surface points;
/// colours from `object_colors[0]`, prior points taking their nearest tracked point's.
fn first_frame_particles(tracks: &CaseTracks) -> FirstFrameParticles {
    let n = tracks.object_points.shape()[1];
    let tracked: Vec<[f32; 3]> = (0..n)
        .map(|i| [0, 1, 2].map(|k| tracks.object_points[[0, i, k]]))
        .collect();
    let tracked_colors: Vec<[f32; 3]> = (0..n)
        .map(|i| [0, 1, 2].map(|k| tracks.object_colors[[0, i, k]]))
        .collect();
    let nearest_color = |p: [f32; 3]| {
        let distance = |q: &[f32; 3]| (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f32>();
        let best = (0..n)
            .min_by(|&a, &b| distance(&tracked[a]).total_cmp(&distance(&tracked[b])))
            .unwrap_or(0);
        tracked_colors[best]
    };
    let rows = |cloud: &Array2<f32>| -> Vec<[f32; 3]> {
        cloud
            .rows()
            .into_iter()
            .map(|r| [r[0], r[1], r[2]])
            .collect()
    };
    let prior_surface = rows(&tracks.surface_points);
    let interior = rows(&tracks.interior_points);

    let mut surface_points = tracked.clone();
    surface_points.extend(&prior_surface);
    let mut surface_colors = tracked_colors.clone();
    surface_colors.extend(prior_surface.iter().map(|&p| nearest_color(p)));
    let interior_colors: Vec<[f32; 3]> = interior.iter().map(|&p| nearest_color(p)).collect();

    let to_array = |v: Vec<[f32; 3]>| {
        let len = v.len();
        Array2::from_shape_vec((len, 3), v.into_iter().flatten().collect())
            .unwrap_or_else(|_| Array2::zeros((0, 3)))
    };
    FirstFrameParticles {
        surface_points: to_array(surface_points),
        surface_colors: to_array(surface_colors),
        interior_points: to_array(interior),
        interior_colors: to_array(interior_colors),
    }
}

/// Volumetric when PhysTwin filled an interior (it does so only for volumetric
/// objects, method.md §8); otherwise from the spread of the first-frame
/// points: one dominant axis is linear, one thin axis planar.
fn infer_category(tracks: &CaseTracks) -> Category {
    if tracks.interior_points.nrows() > 0 {
        return Category::Volumetric;
    }
    let mut points: Vec<Vector3<f64>> = (0..tracks.object_points.shape()[1])
        .map(|i| Vector3::from_fn(|k, _| f64::from(tracks.object_points[[0, i, k]])))
        .collect();
    points.extend(
        tracks
            .surface_points
            .rows()
            .into_iter()
            .map(|r| Vector3::new(r[0], r[1], r[2]).cast::<f64>()),
    );
    let mean = points.iter().sum::<Vector3<f64>>() / points.len().max(1) as f64;
    let covariance = points
        .iter()
        .map(|p| (p - mean) * (p - mean).transpose())
        .sum::<Matrix3<f64>>()
        / points.len().max(1) as f64;
    let mut spread: Vec<f64> = SymmetricEigen::new(covariance)
        .eigenvalues
        .iter()
        .map(|v| v.max(0.0).sqrt())
        .collect();
    spread.sort_by(|a, b| b.total_cmp(a));
    if spread[1] < THIN_AXIS_RATIO * spread[0] {
        Category::Linear
    } else if spread[2] < THIN_AXIS_RATIO * spread[1] {
        Category::Planar
    } else {
        Category::Volumetric
    }
}
