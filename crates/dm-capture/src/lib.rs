//! The raw multi-view RGB-D capture a camera rig gives (docs/capture.md):
//! per-camera colour video (or PNG frames), 16-bit depth PNG frames in
//! millimetres and `calibration.json`. No tracks, no masks.
//!
//! [`Capture`] reads one (dm-prep's stages), [`CaptureWriter`] writes one
//! frame by frame (dm-synth's `--capture-out` through `dm-synth-capture`,
//! dm-prep's monocular clips); colour video goes through OpenCV ([`video`]).

pub mod video;

use std::path::{Path, PathBuf};

use dm_bundle::{BundleError, CameraSpec, UpAxis, read_json, write_json_atomic};
use image::{ImageBuffer, Luma, RgbImage};
use serde::{Deserialize, Serialize};

/// `calibration.json` `format` value.
pub const CAPTURE_FORMAT: &str = "deformmaster-capture";
pub const CAPTURE_VERSION: u32 = 1;
pub const CALIBRATION_FILE: &str = "calibration.json";
/// Per-camera colour video.
pub const COLOR_VIDEO_FILE: &str = "color.mp4";
/// Per-camera colour frames, used when there is no video.
pub const COLOR_DIR: &str = "color";
pub const DEPTH_DIR: &str = "depth";

/// The rig's calibration: intrinsics and extrinsics per camera (bundle
/// conventions: OpenCV axes, row-major world-to-camera), frame rate, and the
/// world's up axis and floor (the calibration board lies on the table).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    pub format: String,
    pub version: u32,
    pub fps: f64,
    pub frame_count: usize,
    pub depth_unit: String,
    pub up_axis: UpAxis,
    pub floor_height_m: f64,
    pub cameras: Vec<CameraSpec>,
}

/// Why a capture could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    #[error(transparent)]
    Field(#[from] BundleError),
    #[error("{}: {problem}", path.display())]
    Video { path: PathBuf, problem: String },
}

fn field_error(path: &Path, field: &str, problem: impl Into<String>) -> CaptureError {
    CaptureError::Field(BundleError::new(path, field, problem))
}

impl Calibration {
    /// Reads and validates `DIR/calibration.json`.
    pub fn read(dir: &Path) -> Result<Self, CaptureError> {
        let path = dir.join(CALIBRATION_FILE);
        let calibration: Calibration = read_json(&path)?;
        calibration.validate(&path)?;
        Ok(calibration)
    }

    fn validate(&self, path: &Path) -> Result<(), CaptureError> {
        if self.format != CAPTURE_FORMAT {
            return Err(field_error(
                path,
                "format",
                format!("must be \"{CAPTURE_FORMAT}\""),
            ));
        }
        if self.version != CAPTURE_VERSION {
            return Err(field_error(
                path,
                "version",
                format!("must be {CAPTURE_VERSION}"),
            ));
        }
        if self.depth_unit != "millimetres" {
            return Err(field_error(path, "depth_unit", "must be \"millimetres\""));
        }
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return Err(field_error(path, "fps", "must be finite and positive"));
        }
        if self.frame_count < 2 {
            return Err(field_error(path, "frame_count", "need at least 2 frames"));
        }
        if !self.floor_height_m.is_finite() {
            return Err(field_error(path, "floor_height_m", "must be finite"));
        }
        if self.cameras.is_empty() {
            return Err(field_error(path, "cameras", "need at least one camera"));
        }
        // The bundle's checks of cameras (names, intrinsics, rigid extrinsics).
        let mut meta = dm_bundle::BundleMeta::new(
            self.frame_count,
            self.fps,
            dm_bundle::Category::Volumetric,
            self.cameras.clone(),
        );
        meta.up_axis = self.up_axis;
        meta.floor_height_m = self.floor_height_m;
        meta.validate(path)?;
        Ok(())
    }

    pub fn write(&self, dir: &Path) -> Result<(), CaptureError> {
        write_json_atomic(&dir.join(CALIBRATION_FILE), self)?;
        Ok(())
    }
}

/// Path of camera `camera`'s depth frame `frame`.
pub fn depth_path(dir: &Path, camera: &str, frame: usize) -> PathBuf {
    dir.join(camera)
        .join(DEPTH_DIR)
        .join(dm_bundle::frame_file_name(frame))
}

/// Path of camera `camera`'s colour frame `frame` (PNG layout).
pub fn color_frame_path(dir: &Path, camera: &str, frame: usize) -> PathBuf {
    dir.join(camera)
        .join(COLOR_DIR)
        .join(dm_bundle::frame_file_name(frame))
}

/// A capture directory opened for reading.
#[derive(Clone, Debug)]
pub struct Capture {
    pub dir: PathBuf,
    pub calibration: Calibration,
}

impl Capture {
    pub fn open(dir: &Path) -> Result<Self, CaptureError> {
        Ok(Self {
            dir: dir.to_path_buf(),
            calibration: Calibration::read(dir)?,
        })
    }

    pub fn frame_count(&self) -> usize {
        self.calibration.frame_count
    }

    /// Every input file of camera `c` (for cache fingerprints).
    pub fn camera_files(&self, c: usize) -> Vec<PathBuf> {
        let name = &self.calibration.cameras[c].name;
        let video = self.dir.join(name).join(COLOR_VIDEO_FILE);
        let mut files = vec![self.dir.join(CALIBRATION_FILE)];
        if video.exists() {
            files.push(video);
        } else {
            files.extend((0..self.frame_count()).map(|t| color_frame_path(&self.dir, name, t)));
        }
        files.extend((0..self.frame_count()).map(|t| depth_path(&self.dir, name, t)));
        files
    }

    /// All colour frames of camera `c`: decoded from `color.mp4` when it
    /// exists, else read from `color/<frame>.png`.
    pub fn read_colors(&self, c: usize) -> Result<Vec<RgbImage>, CaptureError> {
        let camera = &self.calibration.cameras[c];
        let video = self.dir.join(&camera.name).join(COLOR_VIDEO_FILE);
        let frames = if video.exists() {
            crate::video::decode_video(&video)?
        } else {
            (0..self.frame_count())
                .map(|t| {
                    let path = color_frame_path(&self.dir, &camera.name, t);
                    image::open(&path)
                        .map(|i| i.to_rgb8())
                        .map_err(|e| field_error(&path, "png", e.to_string()))
                })
                .collect::<Result<Vec<_>, _>>()?
        };
        if frames.len() < self.frame_count() {
            return Err(field_error(
                &video,
                "frame_count",
                format!(
                    "has {} frames, calibration.json says {}",
                    frames.len(),
                    self.frame_count()
                ),
            ));
        }
        for (t, frame) in frames.iter().enumerate().take(self.frame_count()) {
            if frame.dimensions() != (camera.width, camera.height) {
                return Err(field_error(
                    &video,
                    "size",
                    format!(
                        "frame {t} is {}x{}, camera \"{}\" is {}x{}",
                        frame.width(),
                        frame.height(),
                        camera.name,
                        camera.width,
                        camera.height
                    ),
                ));
            }
        }
        Ok(frames.into_iter().take(self.frame_count()).collect())
    }

    /// Depth frame `t` of camera `c` in metres, row-major, NaN where the
    /// sensor measured nothing (PNG value 0).
    pub fn read_depth_m(&self, c: usize, t: usize) -> Result<Vec<f32>, CaptureError> {
        let camera = &self.calibration.cameras[c];
        read_depth_png_m(
            &depth_path(&self.dir, &camera.name, t),
            camera.width,
            camera.height,
        )
    }
}

/// A 16-bit millimetre depth PNG of `width` x `height` in metres, row-major,
/// NaN where nothing was measured (value 0).
pub fn read_depth_png_m(path: &Path, width: u32, height: u32) -> Result<Vec<f32>, CaptureError> {
    let image = image::open(path).map_err(|e| field_error(path, "png", e.to_string()))?;
    let image::DynamicImage::ImageLuma16(depth) = image else {
        return Err(field_error(
            path,
            "colour_type",
            "depth must be 16-bit grey (millimetres)",
        ));
    };
    if depth.dimensions() != (width, height) {
        return Err(field_error(
            path,
            "size",
            format!(
                "is {}x{}, the colour frames are {width}x{height}",
                depth.width(),
                depth.height(),
            ),
        ));
    }
    Ok(depth
        .into_raw()
        .into_iter()
        .map(|mm| {
            if mm == 0 {
                f32::NAN
            } else {
                f32::from(mm) / 1000.0
            }
        })
        .collect())
}

/// Writes a capture: `calibration.json`, then per camera its colour video
/// and depth frames. Frames are written as they come so a long capture
/// needs no memory for its video; everything goes to a temporary sibling
/// directory renamed into place by [`CaptureWriter::finish`].
#[derive(Debug)]
pub struct CaptureWriter {
    final_dir: PathBuf,
    dir: PathBuf,
    calibration: Calibration,
    videos: Vec<crate::video::VideoSink>,
}

impl CaptureWriter {
    /// Starts writing `final_dir` (which must not exist) and opens one
    /// video per camera.
    pub fn create(final_dir: &Path, calibration: Calibration) -> Result<Self, CaptureError> {
        if final_dir.exists() {
            return Err(field_error(
                final_dir,
                "file",
                "already exists; remove it first",
            ));
        }
        calibration.validate(&final_dir.join(CALIBRATION_FILE))?;
        let mut name = final_dir.file_name().unwrap_or_default().to_os_string();
        name.push(format!(".tmp-{}", std::process::id()));
        let dir = final_dir.with_file_name(name);
        if dir.exists() {
            std::fs::remove_dir_all(&dir).map_err(|e| BundleError::io(&dir, "removing", &e))?;
        }
        let mut videos = Vec::new();
        for camera in &calibration.cameras {
            let cam_dir = dir.join(&camera.name);
            std::fs::create_dir_all(cam_dir.join(DEPTH_DIR))
                .map_err(|e| BundleError::io(&cam_dir, "creating", &e))?;
            videos.push(crate::video::VideoSink::create(
                &cam_dir.join(COLOR_VIDEO_FILE),
                calibration.fps,
                camera.width,
                camera.height,
            )?);
        }
        calibration.write(&dir)?;
        Ok(Self {
            final_dir: final_dir.to_path_buf(),
            dir,
            calibration,
            videos,
        })
    }

    /// Appends frame `t` of camera `c`: colour to its video, depth (metres,
    /// NaN = none) as a millimetre PNG.
    pub fn write_frame(
        &mut self,
        c: usize,
        t: usize,
        rgb: &RgbImage,
        depth_m: &[f32],
    ) -> Result<(), CaptureError> {
        let camera = &self.calibration.cameras[c];
        let path = depth_path(&self.dir, &camera.name, t);
        let mm: Vec<u16> = depth_m
            .iter()
            .map(|&d| dm_bundle::depth_m_to_png_mm(d))
            .collect();
        let image = ImageBuffer::<Luma<u16>, Vec<u16>>::from_raw(camera.width, camera.height, mm)
            .ok_or_else(|| {
            field_error(&path, "size", "depth buffer does not match the camera")
        })?;
        dm_bundle::write_file_atomic(&path, |tmp| {
            image
                .save_with_format(tmp, image::ImageFormat::Png)
                .map_err(std::io::Error::other)
        })?;
        self.videos[c].write(rgb)?;
        Ok(())
    }

    /// Closes the videos and renames the capture into place.
    pub fn finish(self) -> Result<(), CaptureError> {
        for video in self.videos {
            video.finish()?;
        }
        std::fs::rename(&self.dir, &self.final_dir)
            .map_err(|e| BundleError::io(&self.final_dir, "renaming the capture into place", &e))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn calibration_json() -> serde_json::Value {
        serde_json::json!({
            "format": CAPTURE_FORMAT, "version": 1, "fps": 30.0, "frame_count": 3,
            "depth_unit": "millimetres", "up_axis": "+z", "floor_height_m": 0.0,
            "cameras": [{"name": "cam0", "width": 8, "height": 6, "fx": 10.0, "fy": 10.0,
                "cx": 4.0, "cy": 3.0, "axes": "opencv",
                "world_to_camera": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0],
                                    [0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 0.0, 1.0]]}]
        })
    }

    fn open_with(json: &serde_json::Value) -> (tempfile::TempDir, Result<Capture, CaptureError>) {
        let dir = tempfile::tempdir().expect("temp dir");
        std::fs::write(dir.path().join(CALIBRATION_FILE), json.to_string()).expect("write");
        let result = Capture::open(dir.path());
        (dir, result)
    }

    #[test]
    fn a_valid_calibration_opens() {
        let (_dir, result) = open_with(&calibration_json());
        assert_eq!(result.expect("opens").frame_count(), 3);
    }

    #[test]
    fn bad_calibrations_name_the_file_and_field() {
        type Corruption = Box<dyn Fn(&mut serde_json::Value)>;
        let cases: [(&str, Corruption); 4] = [
            (
                "cameras[0].fx",
                Box::new(|v| {
                    v["cameras"][0]
                        .as_object_mut()
                        .expect("object")
                        .remove("fx");
                }),
            ),
            ("fps", Box::new(|v| v["fps"] = serde_json::json!(-1.0))),
            (
                "depth_unit",
                Box::new(|v| v["depth_unit"] = serde_json::json!("metres")),
            ),
            (
                "frame_count",
                Box::new(|v| {
                    v.as_object_mut().expect("object").remove("frame_count");
                }),
            ),
        ];
        for (field, break_it) in cases {
            let mut json = calibration_json();
            break_it(&mut json);
            let (_dir, result) = open_with(&json);
            let message = result.expect_err("must fail").to_string();
            assert!(message.contains(CALIBRATION_FILE), "{message}");
            assert!(message.contains(&format!("field `{field}`")), "{message}");
        }
    }

    #[test]
    fn a_missing_depth_frame_names_its_file() {
        let (dir, result) = open_with(&calibration_json());
        let capture = result.expect("opens");
        let message = capture
            .read_depth_m(0, 1)
            .expect_err("no depth")
            .to_string();
        assert!(
            message.contains(&depth_path(dir.path(), "cam0", 1).display().to_string()),
            "{message}"
        );
    }
}
