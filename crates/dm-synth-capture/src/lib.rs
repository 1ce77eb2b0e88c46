//! A synthetic scene's raw capture: dm-synth's [`CaptureSink`] hook writing
//! what the rig's cameras record (noisy colour, measured depth) as a capture
//! directory (docs/capture.md) with `dm-capture`, frames as they are
//! rendered. Kept apart so dm-synth stays free of OpenCV and dm-prep, which
//! reads captures, free of dm-synth.

use std::path::{Path, PathBuf};

use dm_bundle::{BundleError, BundleMeta};
use dm_capture::{CAPTURE_FORMAT, CAPTURE_VERSION, Calibration, CaptureError, CaptureWriter};
use dm_synth::SynthError;
use dm_synth::sensor::CaptureSink;
use image::RgbImage;

/// dm-synth's capture hook writing a capture directory: the calibration
/// comes from the synthetic bundle's metadata, frames as they are rendered.
#[derive(Debug)]
pub struct SynthCaptureSink {
    dir: PathBuf,
    writer: Option<CaptureWriter>,
}

impl SynthCaptureSink {
    pub fn new(dir: &Path) -> Self {
        Self {
            dir: dir.to_path_buf(),
            writer: None,
        }
    }

    /// Closes the videos and renames the capture into place.
    pub fn finish(self) -> Result<(), CaptureError> {
        match self.writer {
            Some(writer) => writer.finish(),
            None => Err(CaptureError::Field(BundleError::new(
                &self.dir,
                "file",
                "no frame was rendered",
            ))),
        }
    }
}

impl CaptureSink for SynthCaptureSink {
    fn start(&mut self, meta: &BundleMeta) -> Result<(), SynthError> {
        let calibration = Calibration {
            format: CAPTURE_FORMAT.into(),
            version: CAPTURE_VERSION,
            fps: meta.fps,
            frame_count: meta.frame_count,
            depth_unit: "millimetres".into(),
            up_axis: meta.up_axis,
            floor_height_m: meta.floor_height_m,
            cameras: meta.cameras.clone(),
        };
        self.writer = Some(
            CaptureWriter::create(&self.dir, calibration)
                .map_err(|e| SynthError::Capture(e.to_string()))?,
        );
        Ok(())
    }

    fn frame(
        &mut self,
        camera: usize,
        frame: usize,
        rgb: &RgbImage,
        depth_m: &[f32],
    ) -> Result<(), SynthError> {
        let writer = self
            .writer
            .as_mut()
            .ok_or_else(|| SynthError::Capture("frame before start".into()))?;
        writer
            .write_frame(camera, frame, rgb, depth_m)
            .map_err(|e| SynthError::Capture(e.to_string()))
    }
}
