//! The capture → bundle stages (`segment`, `depth`, `track`, `lift`,
//! `fill`) with their cache: each stage writes its output under the work
//! directory (into a temporary sibling renamed into place) with a record
//! of the fingerprint of its inputs (file sizes and modification times,
//! upstream fingerprints, its settings). A stage whose record matches is
//! skipped, so a rerun resumes where the last one stopped.

use std::path::{Path, PathBuf};
use std::time::Instant;

use dm_bundle::{
    BundleError, BundleMeta, BundleWriter, Category, FirstFrameParticles, HandSpec, Provenance,
    Tracks, mask_box, read_json, read_npy_checked, write_json_atomic, write_npy_file,
};
use dm_view::Camera;
use image::{GrayImage, RgbImage};
use ndarray::{Array2, Array3};
use serde::{Deserialize, Serialize};

use crate::fill::{
    CarveView, ColoredPoints, carve_interior, fill_sheet, nearest_colors, voxel_thin,
};
use crate::lift::{
    LiftOptions, Tracks3d, follow_hand_centroids, fuse_cameras, hold_last, lift_camera, mask_cloud,
    smooth_in_time,
};
use crate::segment::{SegmentOptions, segment_frame};
use crate::track2d::{TrackOptions, Tracks2d, grey_mat, on_mask, query_pixels, track_points};
use dm_capture::{Capture, CaptureError};
use dm_prep_models::segment::{self as sam2, Prompt, Segmenter};
use dm_prep_models::track::{self as cotracker, PointTracker};
use dm_prep_models::{Manifest, ModelError, default_models_dir};

/// The stages in the order `all` runs them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Stage {
    Segment,
    Depth,
    Track,
    Lift,
    Fill,
}

impl Stage {
    pub const ALL: [Stage; 5] = [
        Stage::Segment,
        Stage::Depth,
        Stage::Track,
        Stage::Lift,
        Stage::Fill,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Stage::Segment => "segment",
            Stage::Depth => "depth",
            Stage::Track => "track",
            Stage::Lift => "lift",
            Stage::Fill => "fill",
        }
    }

    fn inputs(self) -> &'static [Stage] {
        match self {
            Stage::Segment | Stage::Depth => &[],
            Stage::Track => &[Stage::Segment],
            Stage::Lift => &[Stage::Segment, Stage::Depth, Stage::Track],
            Stage::Fill => &[Stage::Segment, Stage::Depth, Stage::Lift],
        }
    }
}

/// Settings of the particle fill.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FillOptions {
    /// Particle spacing (m).
    pub spacing_m: f64,
    /// Depth noise allowance of the carving (m).
    pub carve_tolerance_m: f64,
}

impl Default for FillOptions {
    fn default() -> Self {
        Self {
            spacing_m: 0.006,
            carve_tolerance_m: 0.006,
        }
    }
}

/// What the segment stage runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum SegmentModel {
    /// The depth/colour model with OpenCV GrabCut (no weights).
    #[default]
    Grabcut,
    /// The SAM 2 ONNX encoder + prompt decoder (models_manifest/), prompted
    /// on frame 0 with the box of the depth/colour model's object.
    Sam2,
}

/// What the track stage runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum TrackModel {
    /// Pyramidal Lucas–Kanade with a forward–backward check (no weights).
    #[default]
    LucasKanade,
    /// The CoTracker3 ONNX model (models_manifest/), whole clip at once.
    Cotracker3,
}

/// Which models the segment and track stages run: part of [`PrepOptions`]
/// and `dm-prep`'s command line.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct StageModels {
    /// Directory of the ONNX model files ($DM_MODELS_DIR, else ./models).
    #[arg(long = "models", value_name = "MODELS")]
    #[serde(default)]
    pub models_dir: Option<PathBuf>,
    /// Segmentation: GrabCut on the depth/colour model (no weights) or the
    /// SAM 2 ONNX models, prompted with that model's frame-0 box.
    #[arg(long, value_enum, default_value_t = SegmentModel::Grabcut)]
    #[serde(default)]
    pub segment_model: SegmentModel,
    /// 2D tracking: Lucas-Kanade (no weights) or the CoTracker3 ONNX model.
    #[arg(long, value_enum, default_value_t = TrackModel::LucasKanade)]
    #[serde(default)]
    pub track_model: TrackModel,
}

/// Every setting of the capture stages (part of each stage's fingerprint).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PrepOptions {
    pub segment: SegmentOptions,
    pub track: TrackOptions,
    pub lift: LiftOptions,
    pub fill: FillOptions,
    /// Object category; inferred from the first-frame points when `None`.
    pub category: Option<Category>,
    #[serde(flatten)]
    pub models: StageModels,
}

impl PrepOptions {
    pub fn models_dir(&self) -> PathBuf {
        self.models
            .models_dir
            .clone()
            .unwrap_or_else(default_models_dir)
    }

    /// The model files `stage` reads (their stamps join its fingerprint).
    fn model_files(&self, stage: Stage) -> Result<Vec<PathBuf>, PrepError> {
        let ids: &[&str] = match (stage, self.models.segment_model, self.models.track_model) {
            (Stage::Segment, SegmentModel::Sam2, _) => &[sam2::ENCODER_ID, sam2::DECODER_ID],
            (Stage::Track, _, TrackModel::Cotracker3) => &[cotracker::TRACKER_ID],
            _ => &[],
        };
        if ids.is_empty() {
            return Ok(Vec::new());
        }
        let manifest = Manifest::builtin()?;
        let dir = self.models_dir();
        ids.iter()
            .map(|id| Ok(dir.join(&manifest.entry(id)?.file)))
            .collect()
    }
}

/// Hand tracks farther than this from every object track at frame 0 are
/// not anchors (forearms, knuckles in the air).
const HAND_ANCHOR_REACH_M: f64 = 0.03;
/// Anchors closer than this (single linkage) belong to one hand.
const HAND_LINK_M: f64 = 0.06;
/// A hand whose tracked anchors move this far (median) from its mask
/// centroid's motion follows the centroid instead.
const HAND_TRACK_DISAGREEMENT_M: f64 = 0.02;
/// Hand-mask points within this distance of a hand's last centroid are
/// that hand's (hands are further apart than this).
const HAND_CENTROID_RADIUS_M: f64 = 0.09;
/// Spread ratio under which an axis counts as thin (as the PhysTwin import).
const THIN_AXIS_RATIO: f64 = 0.25;

#[derive(Debug, thiserror::Error)]
pub enum PrepError {
    #[error(transparent)]
    Capture(#[from] CaptureError),
    #[error(transparent)]
    Bundle(#[from] BundleError),
    /// Boxed: a model error (manifest entry, file, signature) is several
    /// times larger than the others and would bloat every stage's Result.
    #[error(transparent)]
    Model(Box<ModelError>),
    #[error("stage {stage}: OpenCV: {source}")]
    OpenCv {
        stage: &'static str,
        source: opencv::Error,
    },
    #[error("stage {stage}: {problem}")]
    Stage {
        stage: &'static str,
        problem: String,
    },
}

impl From<ModelError> for PrepError {
    fn from(error: ModelError) -> Self {
        PrepError::Model(Box::new(error))
    }
}

fn cv(stage: &'static str) -> impl Fn(opencv::Error) -> PrepError {
    move |source| PrepError::OpenCv { stage, source }
}

/// What one stage run did.
#[derive(Clone, Debug, PartialEq)]
pub struct StageOutcome {
    pub stage: Stage,
    /// False when the cached output was reused.
    pub ran: bool,
    pub seconds: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct StageRecord {
    stage: Stage,
    fingerprint: String,
    seconds: f64,
}

/// Progress report: stage, done, total.
pub type Progress<'a> = &'a mut dyn FnMut(&str, usize, usize);

/// FNV-1a, 64 bit: a stable fingerprint (the standard library's hasher
/// may change between Rust releases).
#[derive(Clone, Copy, Debug)]
struct Fnv(u64);

impl Fnv {
    fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }
    fn add(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(0x0000_0100_0000_01b3);
        }
        // Separator so ("ab", "c") and ("a", "bc") differ.
        self.0 ^= 0xff;
        self.0 = self.0.wrapping_mul(0x0000_0100_0000_01b3);
    }
    fn add_file(&mut self, path: &Path) -> Result<(), BundleError> {
        let (bytes, modified_ns) = file_stamp(path)?;
        self.add(path.to_string_lossy().as_bytes());
        self.add(&bytes.to_le_bytes());
        self.add(&modified_ns.to_le_bytes());
        Ok(())
    }
}

/// CoTracker3 tracks of `queries` as [`Tracks2d`] under the fallback's
/// rule: a track is alive while the model sees it on its mask, and once
/// lost it stays lost (it never jumps to another surface).
fn model_tracks(
    tracker: &mut PointTracker,
    frames: &[RgbImage],
    masks: &[GrayImage],
    queries: &[[f32; 2]],
) -> Result<Tracks2d, PrepError> {
    let query_f64: Vec<[f64; 2]> = queries
        .iter()
        .map(|q| [f64::from(q[0]), f64::from(q[1])])
        .collect();
    let model = tracker.track(frames, &query_f64)?;
    let mut tracks = Tracks2d::starting_at(queries);
    for t in 1..frames.len() {
        tracks.push_frame(|k| {
            let p = [model.positions[[t, k, 0]], model.positions[[t, k, 1]]];
            let seen = model.visible[[t, k]] && on_mask(&masks[t], p);
            Ok::<_, PrepError>(seen.then_some(p))
        })?;
    }
    Ok(tracks)
}

/// A file's size in bytes and modification time (ns since the epoch; 0
/// where the file system keeps none): what the caches compare.
pub fn file_stamp(path: &Path) -> Result<(u64, u128), BundleError> {
    let meta = std::fs::metadata(path).map_err(|e| BundleError::io(path, "reading", &e))?;
    let modified_ns = meta
        .modified()
        .ok()
        .and_then(|m| m.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_nanos());
    Ok((meta.len(), modified_ns))
}

/// Frame 0 lifted to the world: the object's coloured points, and per
/// camera its depth (metres, row-major), object mask and hand mask.
type FirstFrameCloud = (ColoredPoints, Vec<Vec<f32>>, Vec<GrayImage>, Vec<GrayImage>);

/// A capture being prepared, with its work directory.
#[derive(Debug)]
pub struct Prep {
    pub capture: Capture,
    pub work: PathBuf,
    pub options: PrepOptions,
    cameras: Vec<Camera>,
}

impl Prep {
    pub fn new(capture_dir: &Path, work: &Path, options: PrepOptions) -> Result<Self, PrepError> {
        let capture = Capture::open(capture_dir)?;
        let calibration_path = capture_dir.join(dm_capture::CALIBRATION_FILE);
        let cameras = capture
            .calibration
            .cameras
            .iter()
            .enumerate()
            .map(|(i, c)| {
                Camera::from_matrix_4x4(
                    c.width,
                    c.height,
                    c.fx,
                    c.fy,
                    c.cx,
                    c.cy,
                    c.world_to_camera,
                )
                .map_err(|e| {
                    BundleError::new(&calibration_path, format!("cameras[{i}]"), e.to_string())
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        std::fs::create_dir_all(work).map_err(|e| BundleError::io(work, "creating", &e))?;
        Ok(Self {
            capture,
            work: work.to_path_buf(),
            options,
            cameras,
        })
    }

    fn stage_dir(&self, stage: Stage) -> PathBuf {
        self.work.join(stage.name())
    }

    fn record_path(&self, stage: Stage) -> PathBuf {
        self.stage_dir(stage).join("stage.json")
    }

    fn read_record(&self, stage: Stage) -> Option<StageRecord> {
        read_json::<StageRecord>(&self.record_path(stage)).ok()
    }

    /// The fingerprint a fresh output of `stage` would carry now.
    fn fingerprint(&self, stage: Stage) -> Result<String, PrepError> {
        let mut hash = Fnv::new();
        hash.add(stage.name().as_bytes());
        let settings = match stage {
            Stage::Segment => {
                serde_json::to_string(&(&self.options.segment, self.options.models.segment_model))
            }
            Stage::Depth => Ok(String::new()),
            Stage::Track => {
                serde_json::to_string(&(&self.options.track, self.options.models.track_model))
            }
            Stage::Lift => serde_json::to_string(&self.options.lift),
            Stage::Fill => serde_json::to_string(&(&self.options.fill, self.options.category)),
        }
        .map_err(|e| PrepError::Stage {
            stage: stage.name(),
            problem: format!("serialising settings: {e}"),
        })?;
        hash.add(settings.as_bytes());
        // A missing model file is reported by the stage itself, by name.
        for file in self.options.model_files(stage)? {
            if file.is_file() {
                hash.add_file(&file)?;
            }
        }
        for c in 0..self.cameras.len() {
            for file in self.capture.camera_files(c) {
                hash.add_file(&file)?;
            }
        }
        for &input in stage.inputs() {
            let record = self.read_record(input).ok_or_else(|| PrepError::Stage {
                stage: stage.name(),
                problem: format!("its input stage `{}` has not run", input.name()),
            })?;
            hash.add(record.fingerprint.as_bytes());
        }
        Ok(format!("{:016x}", hash.0))
    }

    /// Seconds `stage` took when it last ran (from its record).
    pub fn recorded_seconds(&self, stage: Stage) -> Option<f64> {
        self.read_record(stage).map(|r| r.seconds)
    }

    /// Whether `stage`'s cached output is current.
    pub fn is_current(&self, stage: Stage) -> bool {
        match (self.read_record(stage), self.fingerprint(stage)) {
            (Some(record), Ok(now)) => record.fingerprint == now,
            _ => false,
        }
    }

    /// Runs `stage` after its inputs, each only when its cache is stale.
    pub fn run(
        &self,
        stage: Stage,
        progress: Progress<'_>,
    ) -> Result<Vec<StageOutcome>, PrepError> {
        let mut outcomes = Vec::new();
        for &input in stage.inputs() {
            for outcome in self.run(input, progress)? {
                if !outcomes
                    .iter()
                    .any(|o: &StageOutcome| o.stage == outcome.stage)
                {
                    outcomes.push(outcome);
                }
            }
        }
        let fingerprint = self.fingerprint(stage)?;
        if self
            .read_record(stage)
            .is_some_and(|r| r.fingerprint == fingerprint)
        {
            outcomes.push(StageOutcome {
                stage,
                ran: false,
                seconds: 0.0,
            });
            return Ok(outcomes);
        }
        let final_dir = self.stage_dir(stage);
        // Killed runs' copies of this stage's output.
        dm_bundle::remove_abandoned_temporaries(&self.work, &format!(".{}.tmp-", stage.name()))?;
        let temp = self
            .work
            .join(format!(".{}.tmp-{}", stage.name(), std::process::id()));
        if temp.exists() {
            std::fs::remove_dir_all(&temp).map_err(|e| BundleError::io(&temp, "removing", &e))?;
        }
        std::fs::create_dir_all(&temp).map_err(|e| BundleError::io(&temp, "creating", &e))?;
        let start = Instant::now();
        let result = match stage {
            Stage::Segment => self.segment(&temp, progress),
            Stage::Depth => self.depth(&temp, progress),
            Stage::Track => self.track(&temp, progress),
            Stage::Lift => self.lift(&temp, progress),
            Stage::Fill => self.fill(&temp, progress),
        };
        if let Err(e) = result {
            let _ = std::fs::remove_dir_all(&temp);
            return Err(e);
        }
        let seconds = start.elapsed().as_secs_f64();
        write_json_atomic(
            &temp.join("stage.json"),
            &StageRecord {
                stage,
                fingerprint,
                seconds,
            },
        )?;
        if final_dir.exists() {
            std::fs::remove_dir_all(&final_dir)
                .map_err(|e| BundleError::io(&final_dir, "removing", &e))?;
        }
        std::fs::rename(&temp, &final_dir)
            .map_err(|e| BundleError::io(&final_dir, "renaming into place", &e))?;
        outcomes.push(StageOutcome {
            stage,
            ran: true,
            seconds,
        });
        Ok(outcomes)
    }

    fn names(&self) -> Vec<String> {
        self.capture
            .calibration
            .cameras
            .iter()
            .map(|c| c.name.clone())
            .collect()
    }

    fn mask_path(dir: &Path, camera: &str, kind: &str, t: usize) -> PathBuf {
        dir.join(camera)
            .join(kind)
            .join(dm_bundle::frame_file_name(t))
    }

    fn read_masks(&self, c: usize, kind: &str) -> Result<Vec<GrayImage>, PrepError> {
        let dir = self.stage_dir(Stage::Segment);
        let name = &self.capture.calibration.cameras[c].name;
        (0..self.capture.frame_count())
            .map(|t| {
                let path = Self::mask_path(&dir, name, kind, t);
                image::open(&path)
                    .map(|i| i.to_luma8())
                    .map_err(|e| BundleError::new(&path, "png", e.to_string()).into())
            })
            .collect()
    }

    fn segment(&self, out: &Path, progress: Progress<'_>) -> Result<(), PrepError> {
        let calibration = &self.capture.calibration;
        let up = calibration.up_axis.unit_vector();
        let frames = self.capture.frame_count();
        let total = frames * self.cameras.len();
        // One intra-op thread: masks independent of the core count.
        let mut sam = match self.options.models.segment_model {
            SegmentModel::Grabcut => None,
            SegmentModel::Sam2 => Some(Segmenter::load(
                &Manifest::builtin()?,
                &self.options.models_dir(),
                1,
            )?),
        };
        // With SAM 2 the depth/colour model only prompts it and separates
        // the hands, so its GrabCut refinement is skipped.
        let fallback = SegmentOptions {
            grabcut_iterations: if sam.is_some() {
                0
            } else {
                self.options.segment.grabcut_iterations
            },
            ..self.options.segment.clone()
        };
        for (c, name) in self.names().iter().enumerate() {
            let colors = self.capture.read_colors(c)?;
            for kind in ["object", "hand"] {
                let dir = out.join(name).join(kind);
                std::fs::create_dir_all(&dir).map_err(|e| BundleError::io(&dir, "creating", &e))?;
            }
            let mut masks = Vec::with_capacity(frames);
            for (t, rgb) in colors.iter().enumerate() {
                let depth = self.capture.read_depth_m(c, t)?;
                masks.push(
                    segment_frame(
                        &self.cameras[c],
                        rgb,
                        &depth,
                        up,
                        calibration.floor_height_m,
                        &fallback,
                    )
                    .map_err(cv("segment"))?,
                );
                progress("segment", c * frames + t + 1, total);
            }
            if let Some(sam) = sam.as_mut() {
                let (min, max) = masks
                    .first()
                    .and_then(|m| mask_box(&m.object))
                    .ok_or_else(|| PrepError::Stage {
                        stage: "segment",
                        problem: format!(
                            "camera {name}: nothing stands above the floor in frame 0 to prompt SAM 2 with"
                        ),
                    })?;
                let objects = sam.segment_clip(&colors, &Prompt::Box { min, max })?;
                for (frame, object) in masks.iter_mut().zip(objects) {
                    // The hands: whatever stands above the floor and is not the object.
                    for ((h, o), s) in frame
                        .hand
                        .pixels_mut()
                        .zip(frame.object.pixels())
                        .zip(object.pixels())
                    {
                        let above = h.0[0] > 0 || o.0[0] > 0;
                        h.0[0] = if above && s.0[0] == 0 { 255 } else { 0 };
                    }
                    frame.object = object;
                }
            }
            for (t, frame) in masks.iter().enumerate() {
                for (kind, mask) in [("object", &frame.object), ("hand", &frame.hand)] {
                    let path = Self::mask_path(out, name, kind, t);
                    mask.save_with_format(&path, image::ImageFormat::Png)
                        .map_err(|e| BundleError::new(&path, "png", e.to_string()))?;
                }
            }
        }
        Ok(())
    }

    fn depth(&self, out: &Path, progress: Progress<'_>) -> Result<(), PrepError> {
        let frames = self.capture.frame_count();
        for (c, name) in self.names().iter().enumerate() {
            let camera = &self.cameras[c];
            let (w, h) = (camera.width as usize, camera.height as usize);
            let mut depth = Array3::<f32>::zeros((frames, h, w));
            for t in 0..frames {
                let frame = self.capture.read_depth_m(c, t)?;
                for (i, d) in frame.into_iter().enumerate() {
                    // 0 = no measurement (the .npy must stay finite).
                    depth[[t, i / w, i % w]] = if d.is_finite() { d } else { 0.0 };
                }
                progress("depth", c * frames + t + 1, frames * self.cameras.len());
            }
            write_npy_file(&out.join(format!("{name}.npy")), &depth)?;
        }
        Ok(())
    }

    fn read_depth(&self, c: usize) -> Result<Vec<Vec<f32>>, PrepError> {
        let name = &self.capture.calibration.cameras[c].name;
        let depth: Array3<f32> =
            read_npy_checked(&self.stage_dir(Stage::Depth).join(format!("{name}.npy")))?;
        Ok(depth
            .outer_iter()
            .map(|frame| {
                frame
                    .iter()
                    .map(|&d| if d > 0.0 { d } else { f32::NAN })
                    .collect()
            })
            .collect())
    }

    fn track(&self, out: &Path, progress: Progress<'_>) -> Result<(), PrepError> {
        let count = self.cameras.len();
        let mut tracker = match self.options.models.track_model {
            TrackModel::LucasKanade => None,
            TrackModel::Cotracker3 => Some(PointTracker::load(
                &Manifest::builtin()?,
                &self.options.models_dir(),
                1,
            )?),
        };
        for (c, name) in self.names().iter().enumerate() {
            let colors = self.capture.read_colors(c)?;
            let greys = colors
                .iter()
                .map(grey_mat)
                .collect::<Result<Vec<_>, _>>()
                .map_err(cv("track"))?;
            for (k, kind) in ["object", "hand"].into_iter().enumerate() {
                let masks = self.read_masks(c, kind)?;
                let queries =
                    query_pixels(&greys[0], &masks[0], &self.options.track).map_err(cv("track"))?;
                let tracks = match tracker.as_mut() {
                    Some(tracker) if !queries.is_empty() => {
                        model_tracks(tracker, &colors, &masks, &queries)?
                    }
                    _ => track_points(&greys, Some(&masks), &queries, &self.options.track)
                        .map_err(cv("track"))?,
                };
                write_tracks2d(out, name, kind, &tracks)?;
                progress("track", 2 * c + k + 1, 2 * count);
            }
        }
        Ok(())
    }

    fn read_tracks2d(&self, name: &str, kind: &str) -> Result<Tracks2d, PrepError> {
        let dir = self.stage_dir(Stage::Track);
        let points: Array3<f32> = read_npy_checked(&dir.join(format!("{name}_{kind}_points.npy")))?;
        let alive: Array2<bool> = read_npy_checked(&dir.join(format!("{name}_{kind}_alive.npy")))?;
        let (frames, n) = (points.shape()[0], points.shape()[1]);
        Ok(Tracks2d {
            points: (0..frames)
                .map(|t| {
                    (0..n)
                        .map(|k| [points[[t, k, 0]], points[[t, k, 1]]])
                        .collect()
                })
                .collect(),
            alive: (0..frames)
                .map(|t| (0..n).map(|k| alive[[t, k]]).collect())
                .collect(),
        })
    }

    fn lift(&self, out: &Path, progress: Progress<'_>) -> Result<(), PrepError> {
        let frames = self.capture.frame_count();
        let mut object = Vec::new();
        let mut hand = Vec::new();
        // Hand-mask points of every frame, all cameras (centroid fallback).
        let mut hand_clouds: Vec<Vec<[f64; 3]>> = vec![Vec::new(); frames];
        for (c, name) in self.names().iter().enumerate() {
            let depth = self.read_depth(c)?;
            for (kind, sink) in [("object", &mut object), ("hand", &mut hand)] {
                let tracks = self.read_tracks2d(name, kind)?;
                let masks = self.read_masks(c, kind)?;
                if kind == "hand" {
                    for (t, cloud) in hand_clouds.iter_mut().enumerate() {
                        cloud.extend(mask_cloud(&self.cameras[c], &depth[t], &masks[t], 2));
                    }
                }
                sink.push(lift_camera(
                    &self.cameras[c],
                    &tracks,
                    &depth,
                    &masks,
                    &self.options.lift,
                ));
            }
            progress("lift", c + 1, self.cameras.len());
        }
        let mut object = fuse_cameras(&object, &self.options.lift);
        smooth_in_time(&mut object, self.options.lift.smooth_half_frames);
        if object.is_empty() {
            return Err(PrepError::Stage {
                stage: "lift",
                problem:
                    "no object track could be lifted at frame 0 (empty object masks or no depth?)"
                        .into(),
            });
        }
        let hand = fuse_cameras(&hand, &self.options.lift);
        let (mut anchors, hands) = hand_anchors(&hand, &object.points[0]);
        // Point tracks die or stick on untextured hands: such hands follow
        // their mask centroid instead (lift::follow_hand_centroids).
        let groups: Vec<std::ops::Range<usize>> = hands
            .iter()
            .map(|h| h.anchor_range[0]..h.anchor_range[1])
            .collect();
        follow_hand_centroids(
            &mut anchors,
            &groups,
            &hand_clouds,
            HAND_CENTROID_RADIUS_M,
            HAND_TRACK_DISAGREEMENT_M,
        );
        hold_last(&mut object);
        hold_last(&mut anchors);
        let n = object.len();
        let m = anchors.len();
        let mut tracks = Tracks {
            object_points: Array3::zeros((frames, n, 3)),
            object_visibility: Array2::from_elem((frames, n), false),
            object_motion_valid: Array2::from_elem((frames, n), false),
            hand_points: Array3::zeros((frames, m, 3)),
            hand_visibility: Array2::from_elem((frames, m), false),
        };
        for t in 0..frames {
            for k in 0..n {
                for a in 0..3 {
                    tracks.object_points[[t, k, a]] = object.points[t][k][a] as f32;
                }
                tracks.object_visibility[[t, k]] = object.valid[t][k];
                // Motion is trusted where the point was seen now and in the previous frame.
                tracks.object_motion_valid[[t, k]] =
                    object.valid[t][k] && (t == 0 || object.valid[t - 1][k]);
            }
            for k in 0..m {
                for a in 0..3 {
                    tracks.hand_points[[t, k, a]] = anchors.points[t][k][a] as f32;
                }
                tracks.hand_visibility[[t, k]] = anchors.valid[t][k];
            }
        }
        write_bundle_tracks(out, &tracks)?;
        write_json_atomic(&out.join("hands.json"), &hands)?;
        Ok(())
    }

    fn read_lifted(&self) -> Result<(Tracks, Vec<HandSpec>), PrepError> {
        let dir = self.stage_dir(Stage::Lift);
        let tracks = Tracks {
            object_points: read_npy_checked(&dir.join("object_points.npy"))?,
            object_visibility: read_npy_checked(&dir.join("object_visibility.npy"))?,
            object_motion_valid: read_npy_checked(&dir.join("object_motion_valid.npy"))?,
            hand_points: read_npy_checked(&dir.join("hand_points.npy"))?,
            hand_visibility: read_npy_checked(&dir.join("hand_visibility.npy"))?,
        };
        let hands: Vec<HandSpec> = read_json(&dir.join("hands.json"))?;
        Ok((tracks, hands))
    }

    /// Every frame-0 object pixel of every camera lifted to the world, with
    /// its colour; also each camera's frame-0 depth and object and hand masks.
    fn first_frame_cloud(&self) -> Result<FirstFrameCloud, PrepError> {
        let mut cloud = ColoredPoints::default();
        let (mut depths, mut objects, mut hands) = (Vec::new(), Vec::new(), Vec::new());
        for c in 0..self.cameras.len() {
            let camera = &self.cameras[c];
            let depth = self.read_depth(c)?.swap_remove(0);
            let object = self.read_masks(c, "object")?.swap_remove(0);
            let hand = self.read_masks(c, "hand")?.swap_remove(0);
            let rgb: RgbImage = self.capture.read_colors(c)?.swap_remove(0);
            for y in 0..camera.height {
                for x in 0..camera.width {
                    if object.get_pixel(x, y).0[0] == 0 {
                        continue;
                    }
                    let (u, v) = (f64::from(x) + 0.5, f64::from(y) + 0.5);
                    let Some(d) = crate::lift::window_depth(
                        &depth,
                        camera.width,
                        camera.height,
                        Some(&object),
                        u as f32,
                        v as f32,
                        &self.options.lift,
                    ) else {
                        continue;
                    };
                    let p = camera.unproject(u, v, f64::from(d));
                    cloud.points.push([p.x, p.y, p.z]);
                    cloud
                        .colors
                        .push(rgb.get_pixel(x, y).0.map(|v| f32::from(v) / 255.0));
                }
            }
            depths.push(depth);
            objects.push(object);
            hands.push(hand);
        }
        Ok((cloud, depths, objects, hands))
    }

    fn fill(&self, out: &Path, progress: Progress<'_>) -> Result<(), PrepError> {
        let spacing = self.options.fill.spacing_m;
        let (cloud, depths, objects, hands) = self.first_frame_cloud()?;
        progress("fill", 1, 3);
        let thinned = voxel_thin(&cloud, spacing);
        if thinned.points.is_empty() {
            return Err(PrepError::Stage {
                stage: "fill",
                problem: "the frame-0 object masks hold no pixel with depth".into(),
            });
        }
        let category = self
            .options
            .category
            .unwrap_or_else(|| infer_category(&thinned.points));
        let calibration = &self.capture.calibration;
        let (surface, interior) = if category == Category::Planar {
            let sheet = fill_sheet(&thinned, spacing);
            // A sheet too sparse to triangulate keeps the thinned points.
            (
                if sheet.points.is_empty() {
                    thinned
                } else {
                    sheet
                },
                Vec::new(),
            )
        } else {
            let views: Vec<CarveView<'_>> = (0..self.cameras.len())
                .map(|c| CarveView {
                    camera: &self.cameras[c],
                    depth_m: &depths[c],
                    object: &objects[c],
                    hand: &hands[c],
                })
                .collect();
            let interior = carve_interior(
                &views,
                &thinned.points,
                calibration.up_axis.unit_vector(),
                calibration.floor_height_m,
                spacing,
                self.options.fill.carve_tolerance_m,
            );
            (thinned, interior)
        };
        progress("fill", 2, 3);
        let interior_colors = nearest_colors(&interior, &surface);
        let to_array = |points: &[[f64; 3]]| {
            Array2::from_shape_fn((points.len(), 3), |(i, a)| points[i][a] as f32)
        };
        let colors =
            |c: &[[f32; 3]]| Array2::from_shape_fn((c.len(), 3), |(i, a)| c[i][a].clamp(0.0, 1.0));
        write_npy_file(&out.join("surface_points.npy"), &to_array(&surface.points))?;
        write_npy_file(&out.join("surface_colors.npy"), &colors(&surface.colors))?;
        write_npy_file(&out.join("interior_points.npy"), &to_array(&interior))?;
        write_npy_file(&out.join("interior_colors.npy"), &colors(&interior_colors))?;
        write_json_atomic(&out.join("category.json"), &category)?;
        progress("fill", 3, 3);
        Ok(())
    }

    /// Runs every stage (resuming from the cache) and writes the bundle to
    /// `out` (atomically; an existing one only replaced with `overwrite`).
    pub fn write_bundle(
        &self,
        out: &Path,
        overwrite: bool,
        progress: Progress<'_>,
    ) -> Result<dm_bundle::Bundle, PrepError> {
        let outcomes = self.run(Stage::Fill, progress)?;
        let (tracks, hands) = self.read_lifted()?;
        let fill_dir = self.stage_dir(Stage::Fill);
        let particles = FirstFrameParticles {
            surface_points: read_npy_checked(&fill_dir.join("surface_points.npy"))?,
            surface_colors: read_npy_checked(&fill_dir.join("surface_colors.npy"))?,
            interior_points: read_npy_checked(&fill_dir.join("interior_points.npy"))?,
            interior_colors: read_npy_checked(&fill_dir.join("interior_colors.npy"))?,
        };
        let category: Category = read_json(&fill_dir.join("category.json"))?;
        let calibration = &self.capture.calibration;
        let frames = calibration.frame_count;
        let mut meta = BundleMeta::new(
            frames,
            calibration.fps,
            category,
            calibration.cameras.clone(),
        );
        meta.up_axis = calibration.up_axis;
        meta.floor_height_m = calibration.floor_height_m;
        meta.hands = hands;
        meta.provenance = Provenance {
            tool: format!("dm-prep {}", env!("CARGO_PKG_VERSION")),
            source: format!("capture {}", self.capture.dir.display()),
            created_unix_s: 0,
            notes: format!(
                "{}; {}; depth from the capture; stages {}",
                match self.options.models.segment_model {
                    SegmentModel::Grabcut => "masks: depth/colour model + GrabCut".to_owned(),
                    SegmentModel::Sam2 => format!(
                        "masks: SAM 2 (ONNX, {}) prompted by the depth/colour model",
                        self.options.models_dir().display()
                    ),
                },
                match self.options.models.track_model {
                    TrackModel::LucasKanade =>
                        "tracks: Lucas-Kanade, forward-backward check, frame-0 anchoring".to_owned(),
                    TrackModel::Cotracker3 => format!(
                        "tracks: CoTracker3 (ONNX, {})",
                        self.options.models_dir().display()
                    ),
                },
                outcomes
                    .iter()
                    .map(|o| o.stage.name())
                    .collect::<Vec<_>>()
                    .join(",")
            ),
        };
        let mut writer = if overwrite {
            BundleWriter::create_overwrite(out, meta)?
        } else {
            BundleWriter::create(out, meta)?
        };
        for (c, name) in self.names().iter().enumerate() {
            let colors = self.capture.read_colors(c)?;
            let depth = self.read_depth(c)?;
            let objects = self.read_masks(c, "object")?;
            let hand_masks = self.read_masks(c, "hand")?;
            for t in 0..frames {
                writer.write_frame_images(
                    c,
                    t,
                    &colors[t],
                    &depth[t],
                    &objects[t],
                    &hand_masks[t],
                )?;
            }
            let _ = name;
            progress("bundle", c + 1, self.cameras.len());
        }
        writer.write_tracks(&tracks)?;
        writer.write_particles(&particles)?;
        Ok(writer.finish()?)
    }
}

fn write_tracks2d(out: &Path, name: &str, kind: &str, tracks: &Tracks2d) -> Result<(), PrepError> {
    let (frames, n) = (tracks.points.len(), tracks.len());
    let points = Array3::from_shape_fn((frames, n, 2), |(t, k, a)| tracks.points[t][k][a]);
    let alive = Array2::from_shape_fn((frames, n), |(t, k)| tracks.alive[t][k]);
    write_npy_file(&out.join(format!("{name}_{kind}_points.npy")), &points)?;
    write_npy_file(&out.join(format!("{name}_{kind}_alive.npy")), &alive)?;
    Ok(())
}

fn write_bundle_tracks(out: &Path, tracks: &Tracks) -> Result<(), PrepError> {
    write_npy_file(&out.join("object_points.npy"), &tracks.object_points)?;
    write_npy_file(
        &out.join("object_visibility.npy"),
        &tracks.object_visibility,
    )?;
    write_npy_file(
        &out.join("object_motion_valid.npy"),
        &tracks.object_motion_valid,
    )?;
    write_npy_file(&out.join("hand_points.npy"), &tracks.hand_points)?;
    write_npy_file(&out.join("hand_visibility.npy"), &tracks.hand_visibility)?;
    Ok(())
}

/// Hand tracks that touch the object at frame 0, grouped into hands by
/// single linkage; columns ordered hand by hand.
fn hand_anchors(hand: &Tracks3d, object_first: &[[f64; 3]]) -> (Tracks3d, Vec<HandSpec>) {
    let index = dm_mpm::neighbors::PointIndex::new(object_first);
    let near: Vec<usize> = (0..hand.len())
        .filter(|&k| {
            hand.valid[0][k]
                && index
                    .nearest(&hand.points[0][k], 1)
                    .first()
                    .is_some_and(|n| n.1 <= HAND_ANCHOR_REACH_M)
        })
        .collect();
    // Single-linkage groups (union-find over pairs within the link distance).
    let mut parent: Vec<usize> = (0..near.len()).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    let firsts: Vec<[f64; 3]> = near.iter().map(|&k| hand.points[0][k]).collect();
    let link = dm_mpm::neighbors::PointIndex::new(&firsts);
    for i in 0..near.len() {
        for (j, _) in link.within(&firsts[i], HAND_LINK_M) {
            let (a, b) = (root(&mut parent, i), root(&mut parent, j));
            if a != b {
                parent[a.max(b)] = a.min(b);
            }
        }
    }
    let mut groups: Vec<Vec<usize>> = Vec::new();
    let mut group_of_root = std::collections::BTreeMap::new();
    for i in 0..near.len() {
        let r = root(&mut parent, i);
        let g = *group_of_root.entry(r).or_insert_with(|| {
            groups.push(Vec::new());
            groups.len() - 1
        });
        groups[g].push(near[i]);
    }
    let order: Vec<usize> = groups.iter().flatten().copied().collect();
    let mut specs = Vec::new();
    let mut start = 0;
    for (g, members) in groups.iter().enumerate() {
        specs.push(HandSpec {
            name: format!("hand{g}"),
            anchor_range: [start, start + members.len()],
        });
        start += members.len();
    }
    let frames = hand.points.len();
    let anchors = Tracks3d {
        points: (0..frames)
            .map(|t| order.iter().map(|&k| hand.points[t][k]).collect())
            .collect(),
        valid: (0..frames)
            .map(|t| order.iter().map(|&k| hand.valid[t][k]).collect())
            .collect(),
    };
    (anchors, specs)
}

/// Linear when one axis dominates, planar when one is thin, else
/// volumetric (as the PhysTwin import infers it).
pub fn infer_category(points: &[[f64; 3]]) -> Category {
    let (_, _, spread) = crate::fill::principal_axes(points);
    if spread[1] < THIN_AXIS_RATIO * spread[0] {
        Category::Linear
    } else if spread[2] < THIN_AXIS_RATIO * spread[1] {
        Category::Planar
    } else {
        Category::Volumetric
    }
}
