//! Per-frame errors of a rollout against the observed tracks (the track
//! and Chamfer terms of the PhysTwin protocol, method.md §9). The one
//! implementation behind `dm-sim`'s summary and `dm-eval`'s metrics.

use dm_bundle::Tracks;
use dm_mpm::neighbors::PointIndex;

/// Per-frame errors, metres; NaN where no point was visible.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameErrors {
    /// Mean Euclidean distance from each valid tracked point (visible and
    /// `object_motion_valid` at that frame) to the particle it was matched
    /// to (nearest, Euclidean) at frame 0; NaN where no point is valid.
    pub track: Vec<f64>,
    /// Mean L1 distance (|dx| + |dy| + |dz|) from each visible observed
    /// point to the nearest predicted surface particle under that same L1
    /// norm (observed → predicted; interior particles excluded), as
    /// PhysTwin's one-directional Chamfer with `norm=1`.
    pub chamfer: Vec<f64>,
}

fn to_f64(p: &[f32; 3]) -> [f64; 3] {
    p.map(f64::from)
}

fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn l1_distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    (a[0] - b[0]).abs() + (a[1] - b[1]).abs() + (a[2] - b[2]).abs()
}

/// L1 distance from `query` to its L1-nearest point of `points`, found
/// through the Euclidean index: with `d` the Euclidean nearest distance,
/// the L1-nearest point lies within Euclidean `√3 d` (L2 ≤ L1 ≤ √3 L2),
/// so only those candidates are compared. NaN for an empty cloud.
fn l1_nearest_distance(index: &PointIndex, points: &[[f64; 3]], query: [f64; 3]) -> f64 {
    let Some(&(_, euclidean)) = index.nearest(&query, 1).first() else {
        return f64::NAN;
    };
    // A relative margin so rounding never drops the true L1-nearest point.
    let radius = euclidean * 3f64.sqrt() * (1.0 + 1e-9) + 1e-12;
    index
        .within(&query, radius)
        .iter()
        .map(|&(i, _)| l1_distance(points[i], query))
        .fold(f64::INFINITY, f64::min)
}

/// Errors of each rollout frame (frames beyond the tracks are ignored).
pub fn frame_errors(
    rollout: &[Vec<[f32; 3]>],
    surface_count: usize,
    tracks: &Tracks,
) -> FrameErrors {
    let first: Vec<[f64; 3]> = rollout
        .first()
        .map(|frame| frame.iter().map(to_f64).collect())
        .unwrap_or_default();
    let matched = match_tracks(&first, tracks);
    let track = track_errors(rollout, tracks, &matched);
    let n_tracks = tracks.object_points.shape()[1];
    let chamfer = rollout
        .iter()
        .take(tracks.frame_count())
        .enumerate()
        .map(|(t, frame)| {
            let targets: Vec<[f64; 3]> = (0..n_tracks)
                .filter(|&k| tracks.object_visibility[[t, k]])
                .map(|k| observed(tracks, t, k))
                .collect();
            if targets.is_empty() {
                return f64::NAN;
            }
            let surface: Vec<[f64; 3]> = frame[..surface_count.min(frame.len())]
                .iter()
                .map(to_f64)
                .collect();
            chamfer_to(&surface, &targets)
        })
        .collect();
    FrameErrors { track, chamfer }
}

fn observed(tracks: &Tracks, t: usize, k: usize) -> [f64; 3] {
    let p = &tracks.object_points;
    [p[[t, k, 0]], p[[t, k, 1]], p[[t, k, 2]]].map(f64::from)
}

/// The track term of [`frame_errors`] with the particles each tracked
/// point is matched to given ([`match_tracks`]): per frame, the mean
/// distance from each valid point to its particle (NaN where none is
/// valid).
pub fn track_errors(
    rollout: &[Vec<[f32; 3]>],
    tracks: &Tracks,
    matched: &[Option<usize>],
) -> Vec<f64> {
    let n_tracks = tracks.object_points.shape()[1];
    rollout
        .iter()
        .take(tracks.frame_count())
        .enumerate()
        .map(|(t, frame)| {
            let valid: Vec<(usize, usize)> = (0..n_tracks)
                .filter(|&k| tracks.object_visibility[[t, k]])
                .filter(|&k| tracks.object_motion_valid[[t, k]])
                .filter_map(|k| Some((k, matched.get(k).copied().flatten()?)))
                .filter(|&(_, i)| i < frame.len())
                .collect();
            if valid.is_empty() {
                f64::NAN
            } else {
                valid
                    .iter()
                    .map(|&(k, i)| distance(to_f64(&frame[i]), observed(tracks, t, k)))
                    .sum::<f64>()
                    / valid.len() as f64
            }
        })
        .collect()
}

/// The particle each tracked point is matched to: its Euclidean nearest
/// among the first-frame `particles` (`None` only when there are none).
pub fn match_tracks(particles: &[[f64; 3]], tracks: &Tracks) -> Vec<Option<usize>> {
    let index = PointIndex::new(particles);
    let p = &tracks.object_points;
    (0..p.shape()[1])
        .map(|k| {
            let q = [p[[0, k, 0]], p[[0, k, 1]], p[[0, k, 2]]].map(f64::from);
            index.nearest(&q, 1).first().map(|n| n.0)
        })
        .collect()
}

/// One-directional L1 Chamfer distance: the mean over `targets` of the L1
/// distance to the L1-nearest point of `surface` (the metric's Chamfer
/// term; NaN when either cloud is empty).
pub fn chamfer_to(surface: &[[f64; 3]], targets: &[[f64; 3]]) -> f64 {
    if targets.is_empty() {
        return f64::NAN;
    }
    let index = PointIndex::new(surface);
    targets
        .iter()
        .map(|&q| l1_nearest_distance(&index, surface, q))
        .sum::<f64>()
        / targets.len() as f64
}

/// Mean of the finite values in `values[range[0]..range[1]]` (NaN if none).
pub fn split_mean(values: &[f64], range: [usize; 2]) -> f64 {
    let end = range[1].min(values.len());
    let finite: Vec<f64> = values[range[0].min(end)..end]
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    if finite.is_empty() {
        f64::NAN
    } else {
        finite.iter().sum::<f64>() / finite.len() as f64
    }
}
