//! "Show": where and how a rollout departs from the observed tracks —
//! per-frame and per-region errors, residual accelerations (observed minus
//! simulated, from finite differences of the tracks and of the matched
//! particles) and the learned residual's Δv.

use crate::DiagnoseError;
use dm_bundle::Bundle;
use dm_model::WorldModel;
use dm_model::corrected::CorrectedWorld;
use dm_model::device::{Device, DeviceWorld};
use dm_model::metrics::{FrameErrors, frame_errors};
use dm_mpm::neighbors::PointIndex;
use std::sync::Arc;

/// An open-loop rollout with the learned residual's per-frame mean |Δv|.
#[derive(Clone, Debug)]
pub struct Rollout {
    pub positions: Vec<Vec<[f32; 3]>>,
    /// Mean |Δv| (m/s) of the residual per simulated frame; empty without one.
    pub residual_dv: Vec<f64>,
    /// Mean residual Δv vector per frame (world frame, m/s).
    pub residual_dv_mean: Vec<[f64; 3]>,
}

/// Rolls `model` out over the whole clip on `device` (the CPU where the
/// world needs it), recording the residual's Δv.
pub fn rollout(
    model: &WorldModel,
    bundle: &Bundle,
    device: Device,
) -> Result<Rollout, DiagnoseError> {
    let world = model.world()?;
    let device = device.for_world(&world);
    let mut world = CorrectedWorld::new(
        DeviceWorld::new(world, device)?,
        model.residual_network_on(device)?.map(Arc::new),
    );
    let as_f32 = |ps: Vec<[f64; 3]>| ps.iter().map(|p| p.map(|c| c as f32)).collect::<Vec<_>>();
    let mut positions = vec![as_f32(world.positions()?)];
    let mut residual_dv = Vec::new();
    let mut residual_dv_mean = Vec::new();
    for t in 0..bundle.frame_count().saturating_sub(1) {
        let (from, to, grasp) = model.hand_step(bundle, t);
        if let Some(dv) = world.step_frame(&from, &to, &grasp)? {
            let n = dv.len().max(1) as f64;
            residual_dv.push(dv.iter().map(|d| norm(*d)).sum::<f64>() / n);
            let mut mean = [0.0; 3];
            for d in &dv {
                for a in 0..3 {
                    mean[a] += d[a] / n;
                }
            }
            residual_dv_mean.push(mean);
        }
        positions.push(as_f32(world.positions()?));
    }
    Ok(Rollout {
        positions,
        residual_dv,
        residual_dv_mean,
    })
}

pub(crate) fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Observed tracks and the simulated particles matched to them at frame 0
/// (nearest particle, as `dm_model::metrics`).
#[derive(Clone, Debug)]
pub struct Matched {
    /// observed[t][k]; `None` where the point is not valid at t.
    pub observed: Vec<Vec<Option<[f64; 3]>>>,
    /// simulated[t][k]: the matched particle's position.
    pub simulated: Vec<Vec<[f64; 3]>>,
}

pub fn match_tracks(bundle: &Bundle, positions: &[Vec<[f32; 3]>]) -> Matched {
    let tracks = &bundle.tracks;
    let frames = positions.len().min(tracks.frame_count());
    let n_tracks = tracks.object_points.shape()[1];
    let point = |t: usize, k: usize| {
        let p = &tracks.object_points;
        [0, 1, 2].map(|a| p[[t, k, a]] as f64)
    };
    let first: Vec<[f64; 3]> = positions[0].iter().map(|p| p.map(f64::from)).collect();
    let index = PointIndex::new(&first);
    let matched: Vec<usize> = (0..n_tracks)
        .map(|k| index.nearest(&point(0, k), 1).first().map_or(0, |n| n.0))
        .collect();
    let observed = (0..frames)
        .map(|t| {
            (0..n_tracks)
                .map(|k| {
                    (tracks.object_visibility[[t, k]] && tracks.object_motion_valid[[t, k]])
                        .then(|| point(t, k))
                })
                .collect()
        })
        .collect();
    let simulated = (0..frames)
        .map(|t| {
            matched
                .iter()
                .map(|&i| positions[t][i].map(f64::from))
                .collect()
        })
        .collect();
    Matched {
        observed,
        simulated,
    }
}

/// Half-width (frames) of the second difference: (x[t+h] − 2x[t] + x[t−h]) / (h Δt)².
/// h = 2 divides the acceleration noise of millimetre track noise by 4
/// compared with h = 1, at the cost of smoothing over 4 frames.
pub const ACCEL_STRIDE: usize = 2;

/// One residual-acceleration sample: a tracked point at a frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AccelSample {
    pub frame: usize,
    pub track: usize,
    /// Observed velocity (central difference), m/s.
    pub velocity: [f64; 3],
    /// Observed minus simulated acceleration, m/s².
    pub residual: [f64; 3],
    /// Observed position.
    pub position: [f64; 3],
}

/// Residual accelerations of every point valid at t − h, t and t + h.
pub fn residual_accelerations(matched: &Matched, fps: f64) -> Vec<AccelSample> {
    let h = ACCEL_STRIDE;
    let frames = matched.observed.len();
    let mut out = Vec::new();
    if frames < 2 * h + 1 {
        return out;
    }
    let scale = (fps / h as f64).powi(2);
    for t in h..frames - h {
        for k in 0..matched.observed[t].len() {
            let (Some(a), Some(b), Some(c)) = (
                matched.observed[t - h][k],
                matched.observed[t][k],
                matched.observed[t + h][k],
            ) else {
                continue;
            };
            let (sa, sb, sc) = (
                matched.simulated[t - h][k],
                matched.simulated[t][k],
                matched.simulated[t + h][k],
            );
            let obs = [0, 1, 2].map(|i| (a[i] - 2.0 * b[i] + c[i]) * scale);
            let sim = [0, 1, 2].map(|i| (sa[i] - 2.0 * sb[i] + sc[i]) * scale);
            let velocity = [0, 1, 2].map(|i| (c[i] - a[i]) * fps / (2 * h) as f64);
            out.push(AccelSample {
                frame: t,
                track: k,
                velocity,
                residual: sub(obs, sim),
                position: b,
            });
        }
    }
    out
}

/// Mean track error per region, over the frames of `range`.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct RegionError {
    /// e.g. "height: low third".
    pub region: String,
    pub mean_error_m: f64,
    pub points: usize,
}

/// The object's main axis: the principal direction of the first-frame
/// particles (power iteration on the covariance).
pub fn main_axis(points: &[[f64; 3]]) -> [f64; 3] {
    let n = points.len().max(1) as f64;
    let mut mean = [0.0; 3];
    for p in points {
        for a in 0..3 {
            mean[a] += p[a] / n;
        }
    }
    let mut cov = [[0.0; 3]; 3];
    for p in points {
        let d = sub(*p, mean);
        for i in 0..3 {
            for j in 0..3 {
                cov[i][j] += d[i] * d[j] / n;
            }
        }
    }
    let mut v = [1.0, 0.7, 0.3];
    for _ in 0..100 {
        let w = [0, 1, 2].map(|i| dot(cov[i], v));
        let len = norm(w);
        if len <= 0.0 {
            return [1.0, 0.0, 0.0];
        }
        v = w.map(|c| c / len);
    }
    v
}

/// Per-track mean error over `range` (NaN where never valid).
pub fn per_track_error(matched: &Matched, range: [usize; 2]) -> Vec<f64> {
    let n = matched.observed.first().map_or(0, Vec::len);
    (0..n)
        .map(|k| {
            let errs: Vec<f64> = (range[0]..range[1].min(matched.observed.len()))
                .filter_map(|t| {
                    matched.observed[t][k].map(|o| norm(sub(o, matched.simulated[t][k])))
                })
                .collect();
            if errs.is_empty() {
                f64::NAN
            } else {
                errs.iter().sum::<f64>() / errs.len() as f64
            }
        })
        .collect()
}

/// Errors per third of the object by height, along its main axis and by
/// distance from the hands (at frame 0).
pub fn region_errors(
    bundle: &Bundle,
    per_track: &[f64],
    up: [f64; 3],
    axis: [f64; 3],
) -> Vec<RegionError> {
    let first: Vec<[f64; 3]> = (0..per_track.len())
        .map(|k| {
            let p = &bundle.tracks.object_points;
            [0, 1, 2].map(|a| p[[0, k, a]] as f64)
        })
        .collect();
    let hands = dm_model::hand_anchors(bundle, 0);
    let hand_distance = |p: [f64; 3]| {
        hands
            .iter()
            .map(|h| norm(sub(*h, p)))
            .fold(f64::INFINITY, f64::min)
    };
    let mut out = Vec::new();
    type Key<'a> = Box<dyn Fn([f64; 3]) -> f64 + 'a>;
    let groupings: [(&str, [&str; 3], Key); 3] = [
        (
            "height",
            ["low", "middle", "high"],
            Box::new(|p| dot(p, up)),
        ),
        (
            "main axis",
            ["first third", "middle third", "last third"],
            Box::new(|p| dot(p, axis)),
        ),
        (
            "distance from hands",
            ["near", "middle", "far"],
            Box::new(hand_distance),
        ),
    ];
    for (what, names, key) in &groupings {
        let keys: Vec<f64> = first.iter().map(|p| key(*p)).collect();
        let mut sorted = keys.clone();
        sorted.sort_by(f64::total_cmp);
        if sorted.is_empty() {
            continue;
        }
        let cut1 = sorted[sorted.len() / 3];
        let cut2 = sorted[2 * sorted.len() / 3];
        for (bin, name) in names.iter().enumerate() {
            let errs: Vec<f64> = keys
                .iter()
                .zip(per_track)
                .filter(|(k, e)| {
                    e.is_finite()
                        && match bin {
                            0 => **k < cut1,
                            1 => **k >= cut1 && **k < cut2,
                            _ => **k >= cut2,
                        }
                })
                .map(|(_, e)| *e)
                .collect();
            out.push(RegionError {
                region: format!("{what}: {name}"),
                mean_error_m: if errs.is_empty() {
                    f64::NAN
                } else {
                    errs.iter().sum::<f64>() / errs.len() as f64
                },
                points: errs.len(),
            });
        }
    }
    out
}

/// Track and Chamfer errors of a rollout, per frame.
pub fn errors(model: &WorldModel, bundle: &Bundle, positions: &[Vec<[f32; 3]>]) -> FrameErrors {
    frame_errors(positions, model.surface_count, &bundle.tracks)
}
