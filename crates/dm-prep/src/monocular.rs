//! A monocular clip → a one-camera RGB-D capture (docs/capture.md) that the
//! capture stages turn into a bundle. Per-frame metric depth comes from the
//! clip's own depth frames (a phone's LiDAR, an RGB-D camera) or from a
//! monocular depth network; the intrinsics from the field of view unless
//! given; the world frame from the floor, fitted as the dominant plane of
//! frame 0's depth (RANSAC, then least squares on its inliers), with +z up
//! and the origin below the camera — what the capture's segmentation needs
//! (height above the floor).

use std::path::{Path, PathBuf};

use dm_bundle::{BundleError, CameraSpec, UpAxis};
use dm_view::Camera;
use image::RgbImage;
use nalgebra::{Isometry3, Matrix3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use dm_capture::{
    CAPTURE_FORMAT, CAPTURE_VERSION, Calibration, CaptureError, CaptureWriter, read_depth_png_m,
};
use dm_prep_models::ModelError;
use dm_prep_models::depth::DepthEstimator;

/// The one camera's name in the capture.
pub const MONOCULAR_CAMERA: &str = "cam0";
/// RANSAC draws of the floor fit.
const FLOOR_RANSAC_ITERATIONS: usize = 400;
/// A point within this fraction of its depth (at least
/// [`FLOOR_MIN_THRESHOLD_M`]) of the plane is an inlier: depth noise grows
/// with distance, for sensors and networks alike.
const FLOOR_RELATIVE_THRESHOLD: f64 = 0.006;
const FLOOR_MIN_THRESHOLD_M: f64 = 0.003;
/// Fewer inliers than this fraction of the valid pixels: no floor in view.
const FLOOR_MIN_INLIER_FRACTION: f64 = 0.2;
/// Every n-th pixel (both axes) goes into the floor fit.
const FLOOR_PIXEL_STRIDE: usize = 2;

/// How the clip becomes a capture: the options of `dm-prep VIDEO` (its
/// command line) and the cache record of the capture.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct MonocularOptions {
    /// Horizontal field of view in degrees (when --intrinsics is not given).
    #[arg(long = "fov-deg", value_name = "FOV_DEG", default_value_t = 60.0)]
    pub horizontal_fov_deg: f64,
    /// Pinhole intrinsics fx,fy,cx,cy in pixels.
    #[arg(long, value_parser = parse_intrinsics)]
    pub intrinsics: Option<[f64; 4]>,
    /// Frames per second (default: the video's own).
    #[arg(long)]
    pub fps: Option<f64>,
    /// Metres per unit of the depth network's output (1 for metric models).
    #[arg(
        long = "depth-scale",
        value_name = "DEPTH_SCALE",
        default_value_t = 1.0
    )]
    pub network_depth_scale: f64,
    /// The camera's height above the table or floor in metres: rescales the
    /// depth so the fitted floor is this far below (for depth known only up
    /// to scale).
    #[arg(long)]
    pub camera_height_m: Option<f64>,
    /// Seed of the floor fit's RANSAC.
    #[arg(skip)]
    pub seed: u64,
}

/// Pinhole intrinsics `fx,fy,cx,cy` in pixels, as the command lines give them.
pub fn parse_intrinsics(text: &str) -> Result<[f64; 4], String> {
    let values: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>().map_err(|e| format!("{v:?}: {e}")))
        .collect::<Result<_, _>>()?;
    match values.as_slice() {
        &[fx, fy, cx, cy] if fx > 0.0 && fy > 0.0 && values.iter().all(|v| v.is_finite()) => {
            Ok([fx, fy, cx, cy])
        }
        _ => Err("expected fx,fy,cx,cy (four finite numbers, fx and fy > 0)".into()),
    }
}

impl Default for MonocularOptions {
    fn default() -> Self {
        Self {
            horizontal_fov_deg: 60.0,
            intrinsics: None,
            fps: None,
            network_depth_scale: 1.0,
            camera_height_m: None,
            seed: 0,
        }
    }
}

/// Where each frame's depth comes from.
#[derive(Debug)]
pub enum DepthSource<'a> {
    /// `DIR/<frame>.png`, 16-bit millimetres (docs/capture.md's encoding).
    Frames(PathBuf),
    /// A monocular depth network (models_manifest/), in its own units.
    Network(&'a mut DepthEstimator),
}

#[derive(Debug, thiserror::Error)]
pub enum MonocularError {
    #[error(transparent)]
    Capture(#[from] CaptureError),
    #[error(transparent)]
    Bundle(#[from] BundleError),
    /// Boxed: a model error is large and rare.
    #[error(transparent)]
    Model(Box<ModelError>),
    #[error("{}: {problem}", path.display())]
    Clip { path: PathBuf, problem: String },
}

impl From<ModelError> for MonocularError {
    fn from(error: ModelError) -> Self {
        Self::Model(Box::new(error))
    }
}

/// The floor in camera coordinates: `normal · p + offset_m = 0`, the camera
/// on the positive side (`offset_m` is its height above the floor).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FloorPlane {
    pub normal: [f64; 3],
    pub offset_m: f64,
    /// Fraction of the sampled valid pixels within the inlier threshold.
    pub inlier_fraction: f64,
}

/// Fits the dominant plane of `points` (camera frame, metres), or `None`
/// when there are fewer than 3 points or no plane holds
/// [`FLOOR_MIN_INLIER_FRACTION`] of them.
pub fn fit_floor(points: &[[f64; 3]], seed: u64) -> Option<FloorPlane> {
    if points.len() < 3 {
        return None;
    }
    let points: Vec<Vector3<f64>> = points.iter().map(|p| Vector3::from(*p)).collect();
    let threshold = |p: &Vector3<f64>| (FLOOR_RELATIVE_THRESHOLD * p.z).max(FLOOR_MIN_THRESHOLD_M);
    let inliers_of = |normal: &Vector3<f64>, offset: f64| -> Vec<usize> {
        (0..points.len())
            .filter(|&i| (normal.dot(&points[i]) + offset).abs() <= threshold(&points[i]))
            .collect()
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut best: Vec<usize> = Vec::new();
    for _ in 0..FLOOR_RANSAC_ITERATIONS {
        let [a, b, c] = [0; 3].map(|_| points[rng.random_range(0..points.len())]);
        let cross = (b - a).cross(&(c - a));
        let Some(normal) = cross.try_normalize(1e-12) else {
            continue;
        };
        let inliers = inliers_of(&normal, -normal.dot(&a));
        if inliers.len() > best.len() {
            best = inliers;
        }
    }
    let (normal, offset) = least_squares_plane(&points, &best)?;
    // One refit on the refined plane's inliers settles the boundary points.
    let refined = inliers_of(&normal, offset);
    let (mut normal, mut offset) = least_squares_plane(&points, &refined)?;
    let inlier_fraction = refined.len() as f64 / points.len() as f64;
    if inlier_fraction < FLOOR_MIN_INLIER_FRACTION {
        return None;
    }
    if offset < 0.0 {
        normal = -normal;
        offset = -offset;
    }
    Some(FloorPlane {
        normal: normal.into(),
        offset_m: offset,
        inlier_fraction,
    })
}

/// The plane through the centroid of `points[indices]` normal to their
/// direction of least spread.
fn least_squares_plane(points: &[Vector3<f64>], indices: &[usize]) -> Option<(Vector3<f64>, f64)> {
    if indices.len() < 3 {
        return None;
    }
    let centroid = indices.iter().map(|&i| points[i]).sum::<Vector3<f64>>() / indices.len() as f64;
    let scatter = indices.iter().fold(Matrix3::zeros(), |acc, &i| {
        let d = points[i] - centroid;
        acc + d * d.transpose()
    });
    let eigen = scatter.symmetric_eigen();
    let smallest = eigen.eigenvalues.imin();
    let normal = eigen
        .eigenvectors
        .column(smallest)
        .into_owned()
        .try_normalize(1e-12)?;
    Some((normal, -normal.dot(&centroid)))
}

/// The world-to-camera transform of a world with the floor at z = 0, +z
/// up, its origin below the camera and +x along the camera's x axis as
/// seen on the floor (row-major, bundle convention).
pub fn world_to_camera_from_floor(floor: &FloorPlane) -> [[f64; 4]; 4] {
    let up = Vector3::from(floor.normal);
    let along_x = Vector3::x() - up * up.x;
    // A camera whose x axis is the floor normal (rolled 90°) uses its y axis.
    let x_axis = along_x
        .try_normalize(1e-6)
        .unwrap_or_else(|| (Vector3::y() - up * up.y).normalize());
    let y_axis = up.cross(&x_axis);
    let origin = -up * floor.offset_m;
    // camera = [x y up] · world + origin
    let mut matrix = [[0.0; 4]; 4];
    for r in 0..3 {
        matrix[r] = [x_axis[r], y_axis[r], up[r], origin[r]];
    }
    matrix[3] = [0.0, 0.0, 0.0, 1.0];
    matrix
}

/// Pinhole intrinsics `[fx, fy, cx, cy]` of a `width`-pixel image.
pub fn intrinsics(options: &MonocularOptions, width: u32, height: u32) -> [f64; 4] {
    options.intrinsics.unwrap_or_else(|| {
        let f = 0.5 * f64::from(width) / (0.5 * options.horizontal_fov_deg.to_radians()).tan();
        [f, f, 0.5 * f64::from(width), 0.5 * f64::from(height)]
    })
}

/// Camera-frame points of every `stride`-th pixel (at its centre) with a
/// valid depth.
fn unproject(
    depth_m: &[f32],
    width: u32,
    height: u32,
    [fx, fy, cx, cy]: [f64; 4],
    stride: usize,
) -> Vec<[f64; 3]> {
    // The camera frame is the world here: identity extrinsics.
    let camera = Camera {
        width,
        height,
        fx,
        fy,
        cx,
        cy,
        world_to_camera: Isometry3::identity(),
    };
    let width = width as usize;
    depth_m
        .iter()
        .enumerate()
        .filter(|(i, d)| {
            (i / width).is_multiple_of(stride)
                && (i % width).is_multiple_of(stride)
                && d.is_finite()
                && **d > 0.0
        })
        .map(|(i, &d)| {
            let (u, v) = ((i % width) as f64 + 0.5, (i / width) as f64 + 0.5);
            camera.unproject(u, v, f64::from(d)).coords.into()
        })
        .collect()
}

/// Writes the one-camera capture of `frames` (at `fps`) to `out_dir` (which
/// must not exist; written under a temporary name and renamed) and returns
/// its calibration and the fitted floor.
pub fn write_monocular_capture(
    clip: &Path,
    frames: &[RgbImage],
    fps: f64,
    mut depth: DepthSource<'_>,
    options: &MonocularOptions,
    out_dir: &Path,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<(Calibration, FloorPlane), MonocularError> {
    let clip_error = |problem: String| MonocularError::Clip {
        path: clip.to_path_buf(),
        problem,
    };
    let Some(first) = frames.first() else {
        return Err(clip_error("has no frames".into()));
    };
    let (width, height) = first.dimensions();
    if let Some(t) = frames
        .iter()
        .position(|f| f.dimensions() != (width, height))
    {
        return Err(clip_error(format!(
            "frame {t} is not {width}x{height} like frame 0"
        )));
    }
    let k = intrinsics(options, width, height);
    let mut depth_of = |t: usize, rgb: &RgbImage| -> Result<Vec<f32>, MonocularError> {
        match &mut depth {
            DepthSource::Frames(dir) => Ok(read_depth_png_m(
                &dir.join(format!("{t:05}.png")),
                width,
                height,
            )?),
            DepthSource::Network(network) => Ok(network
                .estimate(rgb)?
                .iter()
                .map(|&d| d * options.network_depth_scale as f32)
                .collect()),
        }
    };
    let mut depth0 = depth_of(0, first)?;
    let mut floor = fit_floor(
        &unproject(&depth0, width, height, k, FLOOR_PIXEL_STRIDE),
        options.seed,
    )
        .ok_or_else(|| {
            clip_error(format!(
                "frame 0: no floor plane in the depth (fewer than {:.0} % of the pixels on one plane); the capture stages need the table or floor in view",
                100.0 * FLOOR_MIN_INLIER_FRACTION
            ))
        })?;
    // Scaling depth scales the floor's distance and keeps its normal.
    let rescale = options
        .camera_height_m
        .map_or(1.0, |height| (height / floor.offset_m) as f32);
    if rescale != 1.0 {
        depth0.iter_mut().for_each(|d| *d *= rescale);
        floor.offset_m *= f64::from(rescale);
    }
    let calibration = Calibration {
        format: CAPTURE_FORMAT.into(),
        version: CAPTURE_VERSION,
        fps,
        frame_count: frames.len(),
        depth_unit: "millimetres".into(),
        up_axis: UpAxis::PosZ,
        floor_height_m: 0.0,
        cameras: vec![CameraSpec {
            name: MONOCULAR_CAMERA.into(),
            width,
            height,
            fx: k[0],
            fy: k[1],
            cx: k[2],
            cy: k[3],
            world_to_camera: world_to_camera_from_floor(&floor),
            axes: "opencv".into(),
        }],
    };
    let mut writer = CaptureWriter::create(out_dir, calibration.clone())?;
    writer.write_frame(0, 0, first, &depth0)?;
    progress(1, frames.len());
    for (t, rgb) in frames.iter().enumerate().skip(1) {
        let mut depth_m = depth_of(t, rgb)?;
        depth_m.iter_mut().for_each(|d| *d *= rescale);
        writer.write_frame(0, t, rgb, &depth_m)?;
        progress(t + 1, frames.len());
    }
    writer.finish()?;
    Ok((calibration, floor))
}

/// A clip to make into a capture: the video, its depth frames (or a depth
/// network of the built-in `models_manifest/` from `models_dir`, by default
/// the one the capture stages use), and the options.
#[derive(Clone, Copy, Debug)]
pub struct ClipSource<'a> {
    pub video: &'a Path,
    pub depth_frames: Option<&'a Path>,
    pub models_dir: Option<&'a Path>,
    pub options: &'a MonocularOptions,
}

/// What [`prepare_clip_capture`] did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ClipCapture {
    /// The capture was already made from the same clip, depth and options.
    Cached,
    /// The capture was (re)written.
    Written {
        frames: usize,
        fps: f64,
        floor: FloorPlane,
    },
}

/// Makes `source` a one-camera capture at `capture`, unless `record_path`
/// shows the capture there was made from the same clip and depth frames
/// (size and modification time of each file) with the same options; a
/// stale capture is replaced. `progress(done, total)` follows the depth.
pub fn prepare_clip_capture(
    source: &ClipSource<'_>,
    capture: &Path,
    record_path: &Path,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<ClipCapture, MonocularError> {
    let record = serde_json::json!({
        "video": file_stamp_json(source.video)?,
        "depth": source.depth_frames.map(dir_stamp_json).transpose()?,
        "options": source.options,
    });
    let cached = capture.is_dir()
        && std::fs::read_to_string(record_path)
            .ok()
            .and_then(|text| serde_json::from_str::<serde_json::Value>(&text).ok())
            .is_some_and(|old| old == record);
    if cached {
        return Ok(ClipCapture::Cached);
    }
    let written = write_clip_capture(source, capture, progress)?;
    dm_bundle::write_json_atomic(record_path, &record)?;
    Ok(written)
}

fn write_clip_capture(
    source: &ClipSource<'_>,
    capture: &Path,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<ClipCapture, MonocularError> {
    let video = source.video;
    let (frames, video_fps) = dm_capture::video::decode_video_with_fps(video)?;
    let fps = source
        .options
        .fps
        .or(video_fps)
        .ok_or_else(|| MonocularError::Clip {
            path: video.to_path_buf(),
            problem: "the video does not state its frame rate; give --fps".into(),
        })?;
    let mut network;
    let depth = match source.depth_frames {
        Some(dir) => DepthSource::Frames(dir.to_path_buf()),
        None => {
            let manifest = dm_prep_models::Manifest::builtin()?;
            let models_dir = source
                .models_dir
                .map_or_else(dm_prep_models::default_models_dir, Path::to_path_buf);
            network = dm_prep_models::load_depth_network(&manifest, &models_dir).map_err(|e| {
                MonocularError::Clip {
                    path: video.to_path_buf(),
                    problem: format!(
                        "no depth frames given, so a monocular depth network is needed: {e}"
                    ),
                }
            })?;
            DepthSource::Network(&mut network)
        }
    };
    if capture.exists() {
        std::fs::remove_dir_all(capture)
            .map_err(|e| BundleError::io(capture, "removing the stale capture", &e))?;
    }
    if let Some(parent) = capture.parent() {
        std::fs::create_dir_all(parent).map_err(|e| BundleError::io(parent, "creating", &e))?;
    }
    let (_, floor) = write_monocular_capture(
        video,
        &frames,
        fps,
        depth,
        source.options,
        capture,
        progress,
    )?;
    Ok(ClipCapture::Written {
        frames: frames.len(),
        fps,
        floor,
    })
}

/// Size and modification time of `path` (what the capture cache compares).
fn file_stamp_json(path: &Path) -> Result<serde_json::Value, BundleError> {
    let (bytes, modified_ns) = crate::stages::file_stamp(path)?;
    Ok(serde_json::json!({
        "path": path.display().to_string(),
        "bytes": bytes,
        "modified_ns": modified_ns.to_string(),
    }))
}

/// The stamps of every file in `dir`, sorted by name (depth frames edited
/// in place rebuild the capture).
fn dir_stamp_json(dir: &Path) -> Result<serde_json::Value, BundleError> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| BundleError::io(dir, "reading", &e))?
        .map(|entry| entry.map(|e| e.path()))
        .collect::<std::io::Result<_>>()
        .map_err(|e| BundleError::io(dir, "reading", &e))?;
    files.sort();
    Ok(serde_json::Value::Array(
        files
            .iter()
            .map(|f| file_stamp_json(f))
            .collect::<Result<_, _>>()?,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera 0.5 m above a floor, looking down at 40°, with 30 % of the
    /// points on a box standing on the floor: the plane comes back within
    /// 0.1° and 1 mm, and the world frame puts the floor at z = 0.
    #[test]
    fn the_floor_is_found_under_clutter_and_sets_the_world_frame() {
        let tilt = 40f64.to_radians();
        // Camera frame: the floor normal points up (−y) and towards the camera (−z).
        let normal = Vector3::new(0.0, -tilt.cos(), -tilt.sin());
        let height = 0.5;
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut points = Vec::new();
        while points.len() < 4000 {
            let p = Vector3::new(
                rng.random_range(-0.5..0.5),
                rng.random_range(-0.4..0.4),
                rng.random_range(0.3..1.5),
            );
            // Move p along the viewing ray onto the floor: normal·(s p) + height = 0.
            let s = -height / normal.dot(&p);
            if s <= 0.0 {
                continue;
            }
            let on_floor = p * s + Vector3::new(0.0, 0.0, rng.random_range(-0.001..0.001));
            if points.len() % 10 < 3 {
                // A box 8 cm tall above this floor point.
                points.push((on_floor + normal * rng.random_range(0.01..0.08)).into());
            } else {
                points.push(on_floor.into());
            }
        }
        let floor = fit_floor(&points, 7).expect("a floor");
        let angle = Vector3::from(floor.normal).angle(&normal).to_degrees();
        assert!(angle < 0.1, "normal off by {angle}°");
        assert!(
            (floor.offset_m - height).abs() < 1e-3,
            "height {}",
            floor.offset_m
        );
        assert!(
            (0.6..0.8).contains(&floor.inlier_fraction),
            "{}",
            floor.inlier_fraction
        );
        let world_to_camera = world_to_camera_from_floor(&floor);
        // Camera-to-world of a floor point has z ≈ 0; the camera sits at (0, 0, height).
        let m = nalgebra::Matrix4::from_fn(|r, c| world_to_camera[r][c]);
        let inverse = m.try_inverse().expect("rigid");
        let floor_point = points[5];
        let world = inverse.transform_point(&nalgebra::Point3::from(floor_point));
        assert!(world.z.abs() < 2e-3, "floor point at z {}", world.z);
        let eye = inverse.transform_point(&nalgebra::Point3::origin());
        assert!(
            (eye.coords - Vector3::new(0.0, 0.0, height)).norm() < 1e-3,
            "{eye}"
        );
    }

    #[test]
    fn no_plane_in_scattered_points_is_none() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let points: Vec<[f64; 3]> = (0..2000)
            .map(|_| [0; 3].map(|_| rng.random_range(0.0..1.0)))
            .collect();
        assert_eq!(fit_floor(&points, 0), None);
    }
}
