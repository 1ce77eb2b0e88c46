//! Colour video through OpenCV: an MP4 sink written frame by frame under a
//! temporary name (renamed into place when finished), and a decoder.

use std::path::{Path, PathBuf};

use image::RgbImage;
use opencv::core::{Mat, Size, Vec3b};
use opencv::prelude::{
    MatTraitConst, MatTraitConstManual, MatTraitManual, VideoCaptureTrait, VideoCaptureTraitConst,
};
use opencv::prelude::{VideoWriterTrait, VideoWriterTraitConst};
use opencv::videoio;

use crate::CaptureError;

fn video_error(path: &Path, problem: impl Into<String>) -> CaptureError {
    CaptureError::Video {
        path: path.to_path_buf(),
        problem: problem.into(),
    }
}

fn utf8(path: &Path) -> Result<&str, CaptureError> {
    path.to_str()
        .ok_or_else(|| video_error(path, "path is not UTF-8"))
}

/// RGB image → OpenCV BGR `Mat`.
pub fn rgb_to_bgr_mat(image: &RgbImage) -> opencv::Result<Mat> {
    let (w, h) = image.dimensions();
    let mut mat = Mat::new_rows_cols_with_default(
        h as i32,
        w as i32,
        opencv::core::CV_8UC3,
        opencv::core::Scalar::all(0.0),
    )?;
    for (y, row) in image.rows().enumerate() {
        let out = mat.at_row_mut::<Vec3b>(y as i32)?;
        for (o, p) in out.iter_mut().zip(row) {
            *o = Vec3b::from([p[2], p[1], p[0]]);
        }
    }
    Ok(mat)
}

/// OpenCV BGR `Mat` → RGB image.
pub fn bgr_mat_to_rgb(mat: &Mat) -> opencv::Result<RgbImage> {
    let (w, h) = (mat.cols() as u32, mat.rows() as u32);
    let mut image = RgbImage::new(w, h);
    for y in 0..h {
        let row = mat.at_row::<Vec3b>(y as i32)?;
        for (x, p) in row.iter().enumerate() {
            image.put_pixel(x as u32, y, image::Rgb([p[2], p[1], p[0]]));
        }
    }
    Ok(image)
}

/// An MP4 being written: H.264 (`avc1`) where OpenCV's FFmpeg has an
/// encoder, else MPEG-4 Part 2 (`mp4v`).
#[derive(Debug)]
pub struct VideoSink {
    path: PathBuf,
    tmp: PathBuf,
    writer: videoio::VideoWriter,
}

impl VideoSink {
    pub fn create(path: &Path, fps: f64, width: u32, height: u32) -> Result<Self, CaptureError> {
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .ok_or_else(|| video_error(path, "path has no UTF-8 file name"))?;
        // OpenCV picks the container from the extension: keep `.mp4` last.
        let tmp = path.with_file_name(format!(".{}.tmp.{name}", std::process::id()));
        let cv = |e: opencv::Error| video_error(path, format!("OpenCV VideoWriter: {e}"));
        for code in [['a', 'v', 'c', '1'], ['m', 'p', '4', 'v']] {
            let fourcc =
                videoio::VideoWriter::fourcc(code[0], code[1], code[2], code[3]).map_err(cv)?;
            let mut writer = videoio::VideoWriter::new(
                utf8(&tmp)?,
                fourcc,
                fps,
                Size::new(width as i32, height as i32),
                true,
            )
            .map_err(cv)?;
            if writer.is_opened().map_err(cv)? {
                // Highest quality the encoder offers: trackers need the texture.
                let _ = writer.set(videoio::VIDEOWRITER_PROP_QUALITY, 100.0);
                return Ok(Self {
                    path: path.to_path_buf(),
                    tmp,
                    writer,
                });
            }
        }
        let _ = std::fs::remove_file(&tmp);
        Err(video_error(
            path,
            "OpenCV could open no MP4 encoder (avc1, mp4v); is libopencv-dev built with FFmpeg? (`make setup`)",
        ))
    }

    pub fn write(&mut self, frame: &RgbImage) -> Result<(), CaptureError> {
        let cv = |e: opencv::Error| video_error(&self.path, format!("OpenCV write: {e}"));
        let mat = rgb_to_bgr_mat(frame).map_err(cv)?;
        self.writer.write(&mat).map_err(cv)
    }

    pub fn finish(mut self) -> Result<(), CaptureError> {
        self.writer
            .release()
            .map_err(|e| video_error(&self.path, format!("OpenCV release: {e}")))?;
        std::fs::rename(&self.tmp, &self.path).map_err(|e| {
            let _ = std::fs::remove_file(&self.tmp);
            video_error(&self.path, format!("renaming the video into place: {e}"))
        })
    }
}

/// Every frame of a video, as RGB images.
pub fn decode_video(path: &Path) -> Result<Vec<RgbImage>, CaptureError> {
    decode_video_with_fps(path).map(|(frames, _)| frames)
}

/// Every frame of a video and its frame rate (`None` when the container
/// does not say).
pub fn decode_video_with_fps(path: &Path) -> Result<(Vec<RgbImage>, Option<f64>), CaptureError> {
    let cv = |e: opencv::Error| video_error(path, format!("OpenCV VideoCapture: {e}"));
    let mut capture =
        videoio::VideoCapture::from_file(utf8(path)?, videoio::CAP_ANY).map_err(cv)?;
    if !capture.is_opened().map_err(cv)? {
        return Err(video_error(path, "OpenCV could not open the video"));
    }
    let mut frames = Vec::new();
    let mut mat = Mat::default();
    while capture.read(&mut mat).map_err(cv)? {
        if mat.empty() {
            break;
        }
        frames.push(bgr_mat_to_rgb(&mat).map_err(cv)?);
    }
    let fps = capture.get(videoio::CAP_PROP_FPS).map_err(cv)?;
    Ok((frames, (fps.is_finite() && fps > 0.0).then_some(fps)))
}
