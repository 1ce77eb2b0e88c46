//! Per-frame errors of a rollout against the observed tracks (the track
//! and shape terms of the PhysTwin protocol, method.md §9). `dm-eval`
//! builds on these.

use dm_bundle::Tracks;
use dm_mpm::neighbors::PointIndex;

/// Per-frame errors, metres; NaN where no point was visible.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameErrors {
    /// Mean distance from each visible tracked point to the particle it was
    /// matched to at frame 0.
    pub track: Vec<f64>,
    /// Mean distance from each visible observed point to the nearest
    /// predicted surface particle (observed → predicted).
    pub chamfer: Vec<f64>,
}

fn to_f64(p: &[f32; 3]) -> [f64; 3] {
    p.map(f64::from)
}

fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

pub fn frame_errors(
    rollout: &[Vec<[f32; 3]>],
    surface_count: usize,
    tracks: &Tracks,
) -> FrameErrors {
    let observed = |t: usize, k: usize| {
        let p = &tracks.object_points;
        [
            p[[t, k, 0]] as f64,
            p[[t, k, 1]] as f64,
            p[[t, k, 2]] as f64,
        ]
    };
    let n_tracks = tracks.object_points.shape()[1];
    let first: Vec<[f64; 3]> = rollout[0].iter().map(to_f64).collect();
    let index = PointIndex::new(&first);
    let matched: Vec<usize> = (0..n_tracks)
        .map(|k| index.nearest(&observed(0, k), 1).first().map_or(0, |n| n.0))
        .collect();
    let mut track = Vec::with_capacity(rollout.len());
    let mut chamfer = Vec::with_capacity(rollout.len());
    for (t, frame) in rollout.iter().enumerate() {
        let visible: Vec<usize> = (0..n_tracks)
            .filter(|&k| tracks.object_visibility[[t, k]])
            .collect();
        if visible.is_empty() {
            track.push(f64::NAN);
            chamfer.push(f64::NAN);
            continue;
        }
        let n = visible.len() as f64;
        track.push(
            visible
                .iter()
                .map(|&k| distance(to_f64(&frame[matched[k]]), observed(t, k)))
                .sum::<f64>()
                / n,
        );
        let surface: Vec<[f64; 3]> = frame[..surface_count.min(frame.len())]
            .iter()
            .map(to_f64)
            .collect();
        let surface_index = PointIndex::new(&surface);
        chamfer.push(
            visible
                .iter()
                .map(|&k| {
                    surface_index
                        .nearest(&observed(t, k), 1)
                        .first()
                        .map_or(f64::NAN, |n| n.1)
                })
                .sum::<f64>()
                / n,
        );
    }
    FrameErrors { track, chamfer }
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
