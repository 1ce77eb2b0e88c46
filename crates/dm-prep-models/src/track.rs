//! CoTracker3-style point tracking (manifest entry `cotracker3`): query
//! points on frame 0 → 2D tracks and visibility over the clip.

use std::path::Path;

use image::RgbImage;
use ndarray::{Array2, Array3, Array5, Axis, s};

use crate::{InputGeometry, Manifest, ModelError, OnnxModel, image_planes};

pub const TRACKER_ID: &str = "cotracker3";
/// A track point counts as visible above this visibility probability.
pub const VISIBILITY_THRESHOLD: f32 = 0.5;

/// Tracks in original-frame pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct Tracks2d {
    /// (T, N, 2) x, y.
    pub positions: Array3<f32>,
    /// (T, N).
    pub visible: Array2<bool>,
}

#[derive(Debug)]
pub struct PointTracker {
    model: OnnxModel,
}

impl PointTracker {
    pub fn load(
        manifest: &Manifest,
        models_dir: &Path,
        threads: usize,
    ) -> Result<Self, ModelError> {
        Ok(Self {
            model: OnnxModel::load(manifest, TRACKER_ID, models_dir, threads)?,
        })
    }

    /// Tracks `queries` (frame-0 pixels) through `frames` (same size).
    pub fn track(
        &mut self,
        frames: &[RgbImage],
        queries: &[[f64; 2]],
    ) -> Result<Tracks2d, ModelError> {
        let label = format!("{} ({})", self.model.entry.model, self.model.path.display());
        let bad = |problem: String| ModelError::BadInput {
            model: label.clone(),
            problem,
        };
        let Some(first) = frames.first() else {
            return Err(bad("no frames to track".into()));
        };
        if queries.is_empty() {
            return Err(bad("no query points".into()));
        }
        if let Some(t) = frames
            .iter()
            .position(|frame| frame.dimensions() != first.dimensions())
        {
            return Err(bad(format!(
                "frame {t} is {:?}, frame 0 {:?}",
                frames[t].dimensions(),
                first.dimensions()
            )));
        }
        let preprocess = self.model.entry.preprocess.clone();
        let geometry = InputGeometry::new(first.dimensions(), &preprocess);
        let (w, h) = (geometry.input.0 as usize, geometry.input.1 as usize);
        let mut video = Array5::<f32>::zeros((1, frames.len(), 3, h, w));
        for (t, frame) in frames.iter().enumerate() {
            let (planes, _) = image_planes(frame, &preprocess);
            video.slice_mut(s![0, t, .., .., ..]).assign(&planes);
        }
        let mut query_array = Array3::<f32>::zeros((1, queries.len(), 3));
        for (n, query) in queries.iter().enumerate() {
            let input = geometry.to_input(*query);
            query_array[[0, n, 1]] = input[0] as f32;
            query_array[[0, n, 2]] = input[1] as f32;
        }
        let outputs = self.model.run(vec![
            ("video", video.into_dyn()),
            ("queries", query_array.into_dyn()),
        ])?;
        let tracks = outputs[0]
            .view()
            .into_dimensionality::<ndarray::Ix4>()
            .map_err(|e| bad(format!("output `tracks`: {e}")))?;
        let visibility = outputs[1]
            .view()
            .into_dimensionality::<ndarray::Ix3>()
            .map_err(|e| bad(format!("output `visibility`: {e}")))?;
        let expected = (1, frames.len(), queries.len());
        if (tracks.dim().0, tracks.dim().1, tracks.dim().2) != expected
            || visibility.dim() != expected
        {
            return Err(bad(format!(
                "outputs tracks {:?} / visibility {:?} do not match {} frames × {} queries",
                tracks.dim(),
                visibility.dim(),
                frames.len(),
                queries.len()
            )));
        }
        let mut positions = tracks.index_axis(Axis(0), 0).to_owned();
        for mut point in positions.lanes_mut(Axis(2)) {
            let original = geometry.to_original([f64::from(point[0]), f64::from(point[1])]);
            point[0] = original[0] as f32;
            point[1] = original[1] as f32;
        }
        let visible = visibility
            .index_axis(Axis(0), 0)
            .mapv(|p| p > VISIBILITY_THRESHOLD);
        Ok(Tracks2d { positions, visible })
    }
}
