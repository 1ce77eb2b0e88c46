//! `bundle.json`: types, (de)serialisation and validation of the metadata alone.

use std::collections::HashSet;
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use crate::error::{BundleError, Result};

pub const FORMAT_NAME: &str = "deformmaster-bundle";
pub const FORMAT_VERSION: u32 = 1;
pub const UNITS: &str = "metres";
pub const DEPTH_ENCODING: &str = "png_u16";
pub const DEPTH_UNIT: &str = "millimetres";
pub const CAMERA_AXES_OPENCV: &str = "opencv";

/// Tolerance on `R Rᵀ = I` for camera rotations.
pub const ROTATION_TOLERANCE: f64 = 1e-4;

/// Default training split: the first 7/10 of the frames.
const DEFAULT_TRAIN_FRACTION_TENTHS: usize = 7;

/// Shape class of the manipulated object; selects simulation priors downstream.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Category {
    /// Ropes, cables: one long dimension.
    Linear,
    /// Cloth, paper: one thin dimension.
    Planar,
    /// Sponges, dough, plush toys.
    Volumetric,
}

/// World axis pointing up (against gravity).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum UpAxis {
    #[serde(rename = "+x")]
    PosX,
    #[serde(rename = "-x")]
    NegX,
    #[serde(rename = "+y")]
    PosY,
    #[serde(rename = "-y")]
    NegY,
    #[serde(rename = "+z")]
    PosZ,
    #[serde(rename = "-z")]
    NegZ,
}

impl UpAxis {
    /// Unit vector of the up direction in world coordinates.
    pub fn unit_vector(&self) -> [f64; 3] {
        match self {
            UpAxis::PosX => [1.0, 0.0, 0.0],
            UpAxis::NegX => [-1.0, 0.0, 0.0],
            UpAxis::PosY => [0.0, 1.0, 0.0],
            UpAxis::NegY => [0.0, -1.0, 0.0],
            UpAxis::PosZ => [0.0, 0.0, 1.0],
            UpAxis::NegZ => [0.0, 0.0, -1.0],
        }
    }
}

/// Half-open frame ranges `[start, end)` for fitting and for evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Split {
    pub train: [usize; 2],
    pub test: [usize; 2],
}

impl Split {
    /// Train on the first `floor(0.7 T)` frames, test on the rest.
    ///
    /// The boundary is clamped to `[1, T-1]` so both parts are non-empty whenever
    /// `T >= 2`; for `T < 2` no valid split exists and validation will say so.
    pub fn default_for(frame_count: usize) -> Self {
        let mut boundary = frame_count * DEFAULT_TRAIN_FRACTION_TENTHS / 10;
        if frame_count >= 2 {
            boundary = boundary.clamp(1, frame_count - 1);
        }
        Split {
            train: [0, boundary],
            test: [boundary, frame_count],
        }
    }
}

/// Where the bundle came from; free text except the timestamp.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Provenance {
    pub tool: String,
    pub source: String,
    pub created_unix_s: u64,
    #[serde(default)]
    pub notes: String,
}

/// Depth image encoding; only one is defined in v1.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DepthSpec {
    pub encoding: String,
    pub unit: String,
}

impl Default for DepthSpec {
    fn default() -> Self {
        DepthSpec {
            encoding: DEPTH_ENCODING.to_owned(),
            unit: DEPTH_UNIT.to_owned(),
        }
    }
}

/// A pinhole camera without distortion (images are assumed undistorted).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraSpec {
    /// Also the directory name under `views/`.
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Row-major rigid transform: camera-frame metres = R * world metres + t.
    pub world_to_camera: [[f64; 4]; 4],
    /// Camera axis convention; only `"opencv"` (x right, y down, z forward).
    pub axes: String,
}

impl CameraSpec {
    /// Maps a world point (metres) into this camera's frame (metres).
    pub fn world_to_camera_point(&self, p: [f64; 3]) -> [f64; 3] {
        let m = &self.world_to_camera;
        let mut out = [0.0; 3];
        for (r, o) in out.iter_mut().enumerate() {
            *o = m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3];
        }
        out
    }

    /// Pixel coordinates `[u, v]` (u right, v down, same origin as `cx, cy`) of a
    /// world point, or `None` when the point is not in front of the camera.
    pub fn project(&self, p_world: [f64; 3]) -> Option<[f64; 2]> {
        let [x, y, z] = self.world_to_camera_point(p_world);
        (z > 0.0).then(|| [self.fx * x / z + self.cx, self.fy * y / z + self.cy])
    }

    /// Number of pixels, as used for depth buffers.
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// Which columns `[start, end)` of `hand_points` belong to one hand or actuator.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct HandSpec {
    pub name: String,
    pub anchor_range: [usize; 2],
}

/// Everything in `bundle.json`. Key names are part of the contract.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BundleMeta {
    pub format: String,
    pub version: u32,
    pub units: String,
    pub up_axis: UpAxis,
    pub fps: f64,
    pub frame_count: usize,
    pub category: Category,
    pub split: Split,
    pub provenance: Provenance,
    pub depth: DepthSpec,
    pub cameras: Vec<CameraSpec>,
    pub hands: Vec<HandSpec>,
    pub floor_height_m: f64,
    /// Path of an optional OBJ mesh relative to the bundle root; `null` or absent when none.
    #[serde(default)]
    pub mesh: Option<String>,
}

impl BundleMeta {
    /// Metadata with the fixed contract fields filled in, `+z` up, floor at 0,
    /// the default split, no hands and no mesh; adjust fields afterwards.
    pub fn new(frame_count: usize, fps: f64, category: Category, cameras: Vec<CameraSpec>) -> Self {
        BundleMeta {
            format: FORMAT_NAME.to_owned(),
            version: FORMAT_VERSION,
            units: UNITS.to_owned(),
            up_axis: UpAxis::PosZ,
            fps,
            frame_count,
            category,
            split: Split::default_for(frame_count),
            provenance: Provenance::default(),
            depth: DepthSpec::default(),
            cameras,
            hands: Vec::new(),
            floor_height_m: 0.0,
            mesh: None,
        }
    }

    /// Reads and parses `bundle.json` (no semantic validation).
    pub fn read(json_path: &Path) -> Result<Self> {
        read_json(json_path)
    }

    /// Checks everything that can be checked from the metadata alone.
    /// `json_path` is only used to name the file in errors.
    pub fn validate(&self, json_path: &Path) -> Result<()> {
        let err = |field: &str, problem: String| BundleError::new(json_path, field, problem);
        let expect_str = |field: &str, found: &str, expected: &str| {
            if found == expected {
                Ok(())
            } else {
                Err(err(
                    field,
                    format!("expected \"{expected}\", found \"{found}\""),
                ))
            }
        };
        expect_str("format", &self.format, FORMAT_NAME)?;
        if self.version != FORMAT_VERSION {
            return Err(err(
                "version",
                format!(
                    "this reader supports version {FORMAT_VERSION}, found {}",
                    self.version
                ),
            ));
        }
        expect_str("units", &self.units, UNITS)?;
        expect_str("depth.encoding", &self.depth.encoding, DEPTH_ENCODING)?;
        expect_str("depth.unit", &self.depth.unit, DEPTH_UNIT)?;
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return Err(err(
                "fps",
                format!("must be finite and > 0, found {}", self.fps),
            ));
        }
        if !self.floor_height_m.is_finite() {
            return Err(err(
                "floor_height_m",
                format!("must be finite, found {}", self.floor_height_m),
            ));
        }
        // Two frames is the least that allows non-empty train and test parts.
        if self.frame_count < 2 {
            return Err(err(
                "frame_count",
                format!("must be >= 2, found {}", self.frame_count),
            ));
        }
        self.validate_split(json_path)?;
        self.validate_cameras(json_path)?;
        self.validate_hand_names(json_path)?;
        if let Some(mesh) = &self.mesh {
            validate_relative_path(mesh).map_err(|problem| err("mesh", problem))?;
        }
        Ok(())
    }

    fn validate_split(&self, json_path: &Path) -> Result<()> {
        let t = self.frame_count;
        for (field, [start, end]) in [
            ("split.train", self.split.train),
            ("split.test", self.split.test),
        ] {
            if start >= end || end > t {
                return Err(BundleError::new(
                    json_path,
                    field,
                    format!(
                        "[{start}, {end}) must be a non-empty range within [0, {t}) (frame_count {t})"
                    ),
                ));
            }
        }
        let [a0, a1] = self.split.train;
        let [b0, b1] = self.split.test;
        if a0 < b1 && b0 < a1 {
            return Err(BundleError::new(
                json_path,
                "split.test",
                format!("[{b0}, {b1}) overlaps split.train [{a0}, {a1})"),
            ));
        }
        Ok(())
    }

    fn validate_cameras(&self, json_path: &Path) -> Result<()> {
        if self.cameras.is_empty() {
            return Err(BundleError::new(
                json_path,
                "cameras",
                "at least one camera is required",
            ));
        }
        let mut seen_names = HashSet::new();
        for (i, cam) in self.cameras.iter().enumerate() {
            let err = |key: &str, problem: String| {
                BundleError::new(json_path, format!("cameras[{i}].{key}"), problem)
            };
            validate_path_component(&cam.name).map_err(|p| err("name", p))?;
            if !seen_names.insert(cam.name.as_str()) {
                return Err(err(
                    "name",
                    format!("duplicate camera name \"{}\"", cam.name),
                ));
            }
            if cam.width == 0 || cam.height == 0 {
                return Err(err(
                    "width",
                    format!(
                        "image size must be positive, found {}x{}",
                        cam.width, cam.height
                    ),
                ));
            }
            for (key, value) in [("fx", cam.fx), ("fy", cam.fy)] {
                if !(value.is_finite() && value > 0.0) {
                    return Err(err(key, format!("must be finite and > 0, found {value}")));
                }
            }
            for (key, value) in [("cx", cam.cx), ("cy", cam.cy)] {
                if !value.is_finite() {
                    return Err(err(key, format!("must be finite, found {value}")));
                }
            }
            if cam.axes != CAMERA_AXES_OPENCV {
                return Err(err(
                    "axes",
                    format!("expected \"{CAMERA_AXES_OPENCV}\", found \"{}\"", cam.axes),
                ));
            }
            check_rigid_transform(&cam.world_to_camera).map_err(|p| err("world_to_camera", p))?;
        }
        Ok(())
    }

    fn validate_hand_names(&self, json_path: &Path) -> Result<()> {
        let mut seen = HashSet::new();
        for (i, hand) in self.hands.iter().enumerate() {
            if hand.name.is_empty() || !seen.insert(hand.name.as_str()) {
                return Err(BundleError::new(
                    json_path,
                    format!("hands[{i}].name"),
                    format!("must be non-empty and unique, found \"{}\"", hand.name),
                ));
            }
        }
        Ok(())
    }

    /// Checks that the hand ranges tile `[0, anchor_count)` exactly (in any order).
    pub fn validate_hand_ranges(&self, json_path: &Path, anchor_count: usize) -> Result<()> {
        let mut order: Vec<usize> = (0..self.hands.len()).collect();
        order.sort_by_key(|&i| self.hands[i].anchor_range);
        let mut covered_to = 0;
        for i in order {
            let [start, end] = self.hands[i].anchor_range;
            let field = format!("hands[{i}].anchor_range");
            if start >= end || end > anchor_count {
                return Err(BundleError::new(
                    json_path,
                    field,
                    format!(
                        "[{start}, {end}) must be non-empty and within [0, {anchor_count}) (hand_points has {anchor_count} anchors)"
                    ),
                ));
            }
            if start != covered_to {
                let problem = if start < covered_to {
                    format!("[{start}, {end}) overlaps another hand's range")
                } else {
                    format!("anchors [{covered_to}, {start}) belong to no hand")
                };
                return Err(BundleError::new(json_path, field, problem));
            }
            covered_to = end;
        }
        if covered_to != anchor_count {
            return Err(BundleError::new(
                json_path,
                "hands",
                format!("anchors [{covered_to}, {anchor_count}) of hand_points belong to no hand"),
            ));
        }
        Ok(())
    }
}

/// Camera names become directory names, so keep them portable and unable to escape `views/`.
fn validate_path_component(name: &str) -> Result<(), String> {
    let portable = name
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'));
    if name.is_empty() || name.starts_with('.') || !portable {
        return Err(format!(
            "\"{name}\" must be non-empty, use only [A-Za-z0-9_.-] and not start with '.' (it is a directory name)"
        ));
    }
    Ok(())
}

/// A path inside the bundle: relative, '/'-separated, no `..`.
fn validate_relative_path(path: &str) -> Result<(), String> {
    let escapes = path
        .split('/')
        .any(|part| part.is_empty() || part == "." || part == "..");
    if path.starts_with('/') || path.contains('\\') || escapes {
        return Err(format!(
            "\"{path}\" must be a relative '/'-separated path inside the bundle without '.' or '..'"
        ));
    }
    Ok(())
}

fn check_rigid_transform(m: &[[f64; 4]; 4]) -> Result<(), String> {
    if let Some((r, c)) = (0..4)
        .flat_map(|r| (0..4).map(move |c| (r, c)))
        .find(|&(r, c)| !m[r][c].is_finite())
    {
        return Err(format!("element [{r}][{c}] is not finite ({})", m[r][c]));
    }
    if m[3] != [0.0, 0.0, 0.0, 1.0] {
        return Err(format!("last row must be [0, 0, 0, 1], found {:?}", m[3]));
    }
    for a in 0..3 {
        for b in 0..3 {
            let dot: f64 = (0..3).map(|k| m[a][k] * m[b][k]).sum();
            let expected = if a == b { 1.0 } else { 0.0 };
            if (dot - expected).abs() > ROTATION_TOLERANCE {
                return Err(format!(
                    "rotation part is not orthonormal within {ROTATION_TOLERANCE}: (R Rᵀ)[{a}][{b}] = {dot}"
                ));
            }
        }
    }
    let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    // A reflection is orthonormal too but would flip handedness of the world.
    if det <= 0.0 {
        return Err(format!(
            "rotation part has determinant {det}; a proper rotation (det +1) is required"
        ));
    }
    Ok(())
}

/// Reads a JSON file into `T`; errors name the offending key path (e.g. `cameras[1].fx`).
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T> {
    let text = fs::read_to_string(path).map_err(|e| BundleError::io(path, "reading", &e))?;
    parse_json(&text, path)
}

/// Parses JSON `text` meant for the file at `path`; errors name that file
/// and the offending key as [`read_json`]'s do.
pub fn parse_json<T: DeserializeOwned>(text: &str, path: &Path) -> Result<T> {
    let mut deserializer = serde_json::Deserializer::from_str(text);
    let value: T =
        serde_path_to_error::deserialize(&mut deserializer).map_err(|e| json_error(path, e))?;
    deserializer
        .end()
        .map_err(|e| BundleError::new(path, "(document)", format!("trailing content: {e}")))?;
    Ok(value)
}

fn json_error(path: &Path, err: serde_path_to_error::Error<serde_json::Error>) -> BundleError {
    let parent = err.path().to_string();
    let inner = err.into_inner();
    let message = inner.to_string();
    // serde reports a missing key at its parent object; name the key itself.
    let missing_key = message
        .strip_prefix("missing field `")
        .and_then(|rest| rest.split_once('`'))
        .map(|(key, _)| key.to_owned());
    let field = match (missing_key, parent.as_str()) {
        // Malformed JSON has no meaningful key path (serde_path_to_error says `?`).
        _ if inner.is_syntax() || inner.is_eof() => "(json syntax)".to_owned(),
        (Some(key), ".") => key,
        (Some(key), _) => format!("{parent}.{key}"),
        (None, ".") => "(document)".to_owned(),
        (None, _) => parent,
    };
    BundleError::new(path, field, message)
}

static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// A sibling path `<path>.<tag>-<pid>-<n>` unique within this process and, by
/// the pid, among live processes.
pub(crate) fn unique_sibling(path: &Path, tag: &str) -> PathBuf {
    let n = TEMP_COUNTER.fetch_add(1, Ordering::Relaxed);
    let mut name = path
        .file_name()
        .map(|s| s.to_os_string())
        .unwrap_or_default();
    name.push(format!(".{tag}-{}-{n}", std::process::id()));
    path.with_file_name(name)
}

/// Removes the entries of `dir` named `PREFIX<pid>` or `PREFIX<pid>-<n>`
/// whose process is gone: temporary outputs of killed runs (a live
/// process's are kept; where `/proc` is missing nothing is removed).
pub fn remove_abandoned_temporaries(dir: &Path, prefix: &str) -> Result<()> {
    let proc = Path::new("/proc");
    if !proc.join("self").exists() {
        return Ok(());
    }
    let Ok(entries) = fs::read_dir(dir) else {
        return Ok(());
    };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(rest) = name.strip_prefix(prefix) else {
            continue;
        };
        let pid = rest.split('-').next().unwrap_or_default();
        if pid.is_empty() || !pid.bytes().all(|b| b.is_ascii_digit()) || proc.join(pid).exists() {
            continue;
        }
        let path = entry.path();
        let removed = if entry.file_type().is_ok_and(|t| t.is_dir()) {
            fs::remove_dir_all(&path)
        } else {
            fs::remove_file(&path)
        };
        match removed {
            Ok(()) => {}
            // Another run removed it first.
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => {
                return Err(BundleError::io(
                    &path,
                    "removing a killed run's temporary output",
                    &e,
                ));
            }
        }
    }
    Ok(())
}

/// Writes `value` as pretty JSON to a temporary sibling, syncs it, then renames it
/// over `path`, so readers never observe a partially written file.
pub fn write_json_atomic<T: Serialize + ?Sized>(path: &Path, value: &T) -> Result<()> {
    let mut text = serde_json::to_vec_pretty(value)
        .map_err(|e| BundleError::new(path, "(document)", format!("serialising: {e}")))?;
    text.push(b'\n');
    write_file_atomic(path, |temp| {
        let mut file = fs::File::create(temp)?;
        file.write_all(&text)?;
        file.sync_all()
    })
}

/// Writes `path` through `write` on a unique temporary sibling, then
/// renames it into place: readers never see a half-written file, and a
/// failed write leaves the old file untouched.
pub fn write_file_atomic(
    path: &Path,
    write: impl FnOnce(&Path) -> std::io::Result<()>,
) -> Result<()> {
    let temp = unique_sibling(path, "tmp");
    if let Err(e) = write(&temp) {
        let _ = fs::remove_file(&temp);
        return Err(BundleError::io(&temp, "writing", &e));
    }
    fs::rename(&temp, path).map_err(|e| {
        let _ = fs::remove_file(&temp);
        BundleError::io(path, "renaming temporary file into place", &e)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_dead_processes_temporaries_are_removed() {
        let dir = tempfile::tempdir().expect("temp dir");
        // Above Linux's largest pid: no such process can be alive.
        let dead = dir.path().join("bundle.tmp-999999999-3");
        let live = dir
            .path()
            .join(format!("bundle.tmp-{}-0", std::process::id()));
        let other = dir.path().join("bundle.tmpfile");
        let kept_file = dir.path().join("model.json.tmp-999999999-1");
        for d in [&dead, &live, &other] {
            fs::create_dir_all(d.join("tracks")).expect("dir");
        }
        fs::write(&kept_file, b"{").expect("file");
        remove_abandoned_temporaries(dir.path(), "bundle.tmp-").expect("sweep");
        assert!(!dead.exists(), "a killed run's copy is removed");
        assert!(live.exists(), "a live process's copy is kept");
        assert!(other.exists() && kept_file.exists(), "other names are kept");
        remove_abandoned_temporaries(dir.path(), "model.json.tmp-").expect("sweep");
        assert!(!kept_file.exists(), "files too");
    }
}
