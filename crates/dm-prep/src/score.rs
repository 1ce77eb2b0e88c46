//! Scores a bundle's 3D object tracks against a reference bundle's (for
//! synthetic scenes: dm-synth's exact truth tracks, `--exact-tracks`).
//!
//! Correspondence as in the benchmark's track metric (method.md §9): each
//! prepared track is matched once, at frame 0, to the nearest reference
//! track; its error at frame t is the distance between the two at t. Only
//! entries the prepared bundle marks visible and motion-valid count (what
//! a fit would use). The median over those entries is the score; the
//! frame-0 match distance is reported too (it bounds what sampling of the
//! reference alone contributes).

use std::path::Path;

use dm_bundle::Bundle;
use dm_mpm::neighbors::PointIndex;

/// The result of [`score_tracks`].
#[derive(Clone, Debug, PartialEq)]
pub struct TrackScore {
    pub median_m: f64,
    pub mean_m: f64,
    pub p90_m: f64,
    /// Median frame-0 distance to the matched reference track.
    pub match_median_m: f64,
    /// Scored (track, frame) entries and tracks.
    pub entries: usize,
    pub tracks: usize,
}

#[derive(Debug, thiserror::Error)]
pub enum ScoreError {
    #[error(transparent)]
    Bundle(#[from] dm_bundle::BundleError),
    #[error("{0}")]
    Mismatch(String),
}

/// Rewrites the object tracks of `bundle` in its camera 0's frame.
fn to_camera0(bundle: &mut Bundle, path: &Path) -> Result<(), ScoreError> {
    let camera = bundle
        .meta
        .cameras
        .first()
        .cloned()
        .ok_or_else(|| ScoreError::Mismatch(format!("{} has no camera 0", path.display())))?;
    let points = &mut bundle.tracks.object_points;
    let (frames, tracks, _) = points.dim();
    for t in 0..frames {
        for n in 0..tracks {
            let world = [0, 1, 2].map(|k| f64::from(points[[t, n, k]]));
            let camera_point = camera.world_to_camera_point(world);
            for (k, value) in camera_point.into_iter().enumerate() {
                points[[t, n, k]] = value as f32;
            }
        }
    }
    Ok(())
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// Where the two bundles' tracks are compared.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScoreFrame {
    /// Their world coordinates (the same calibration).
    World,
    /// Each bundle's camera 0 frame: for bundles of one physical camera
    /// whose worlds differ (a monocular clip's world comes from its floor).
    Camera0,
}

pub fn score_tracks(bundle: &Path, reference: &Path) -> Result<TrackScore, ScoreError> {
    score_tracks_in(bundle, reference, ScoreFrame::World)
}

/// [`score_tracks`] with the tracks compared in `frame`.
pub fn score_tracks_in(
    bundle: &Path,
    reference: &Path,
    frame: ScoreFrame,
) -> Result<TrackScore, ScoreError> {
    let mut prepared = Bundle::open(bundle)?;
    let mut truth = Bundle::open(reference)?;
    if frame == ScoreFrame::Camera0 {
        to_camera0(&mut prepared, bundle)?;
        to_camera0(&mut truth, reference)?;
    }
    let (p, r) = (&prepared.tracks, &truth.tracks);
    let frames = p.frame_count();
    if r.frame_count() != frames {
        return Err(ScoreError::Mismatch(format!(
            "{} has {frames} frames, the reference {} has {}",
            bundle.display(),
            reference.display(),
            r.frame_count()
        )));
    }
    let at =
        |a: &ndarray::Array3<f32>, t: usize, n: usize| [0, 1, 2].map(|k| f64::from(a[[t, n, k]]));
    let reference_first: Vec<[f64; 3]> = (0..r.object_point_count())
        .map(|n| at(&r.object_points, 0, n))
        .collect();
    let index = PointIndex::new(&reference_first);
    let mut errors = Vec::new();
    let mut matches = Vec::new();
    for n in 0..p.object_point_count() {
        let Some(&(j, d0)) = index.nearest(&at(&p.object_points, 0, n), 1).first() else {
            return Err(ScoreError::Mismatch(format!(
                "the reference {} has no object tracks",
                reference.display()
            )));
        };
        matches.push(d0);
        for t in 0..frames {
            if p.object_visibility[[t, n]] && p.object_motion_valid[[t, n]] {
                let (a, b) = (at(&p.object_points, t, n), at(&r.object_points, t, j));
                errors.push(
                    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt(),
                );
            }
        }
    }
    if errors.is_empty() {
        return Err(ScoreError::Mismatch(format!(
            "{} has no visible, motion-valid track entries to score",
            bundle.display()
        )));
    }
    errors.sort_by(f64::total_cmp);
    matches.sort_by(f64::total_cmp);
    Ok(TrackScore {
        median_m: quantile(&errors, 0.5),
        mean_m: errors.iter().sum::<f64>() / errors.len() as f64,
        p90_m: quantile(&errors, 0.9),
        match_median_m: quantile(&matches, 0.5),
        entries: errors.len(),
        tracks: p.object_point_count(),
    })
}
