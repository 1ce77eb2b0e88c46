//! Cheap signatures of the candidate effects in the residual
//! accelerations and the tracks: evidence printed beside each candidate's
//! held-out score, and the direction / sign a candidate's trials use.

use crate::analysis::{AccelSample, Matched, dot, norm};
use serde::Serialize;

/// What the residual accelerations and tracks say about each candidate.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Signatures {
    /// Least-squares k in r = −k v (1/s) over all samples: air drag makes it
    /// positive (residual anti-parallel to velocity).
    pub drag_rate_per_s: f64,
    /// k / its standard error.
    pub drag_t: f64,
    /// Same as `drag_rate_per_s` for the horizontal part of samples within
    /// `FLOOR_BAND_M` of the floor: floor friction makes it positive.
    pub floor_rate_per_s: f64,
    pub floor_t: f64,
    /// Mean horizontal residual acceleration (m/s², world frame): a tilted
    /// gravity makes it a constant vector.
    pub horizontal_accel: [f64; 3],
    /// |mean| / its standard error.
    pub horizontal_t: f64,
    /// Shift s (frames) that best aligns the observed centroid motion of
    /// the points near the hands with the hand track at t + s, minus the
    /// same shift for the simulated points: a lagging hand record makes it
    /// positive (the object moves before the recorded hands).
    pub hand_shift_frames: f64,
    /// Slope of the vertical residual acceleration along the main axis
    /// (m/s² per m): a density gradient makes one end sag more.
    pub sag_slope: f64,
    pub sag_t: f64,
}

/// Points closer than this to the floor count as touching it.
pub const FLOOR_BAND_M: f64 = 0.012;

/// Least squares r = −k v: (k, k / standard error).
pub fn opposing_rate(pairs: &[([f64; 3], [f64; 3])]) -> (f64, f64) {
    let vv: f64 = pairs.iter().map(|(v, _)| dot(*v, *v)).sum();
    if pairs.len() < 3 || vv <= 0.0 {
        return (0.0, 0.0);
    }
    let k = -pairs.iter().map(|(v, r)| dot(*v, *r)).sum::<f64>() / vv;
    let rss: f64 = pairs
        .iter()
        .map(|(v, r)| {
            let e = [0, 1, 2].map(|a| r[a] + k * v[a]);
            dot(e, e)
        })
        .sum();
    let dof = (3 * pairs.len()).saturating_sub(1).max(1) as f64;
    let se = (rss / dof / vv).sqrt();
    (k, if se > 0.0 { k / se } else { 0.0 })
}

/// Mean of vectors and |mean| / standard error of the mean.
pub fn mean_and_t(values: &[[f64; 3]]) -> ([f64; 3], f64) {
    let n = values.len();
    if n < 3 {
        return ([0.0; 3], 0.0);
    }
    let mut mean = [0.0; 3];
    for v in values {
        for a in 0..3 {
            mean[a] += v[a] / n as f64;
        }
    }
    let var: f64 = values
        .iter()
        .map(|v| {
            let d = [0, 1, 2].map(|a| v[a] - mean[a]);
            dot(d, d)
        })
        .sum::<f64>()
        / (n - 1) as f64;
    let se = (var / n as f64).sqrt();
    (mean, if se > 0.0 { norm(mean) / se } else { 0.0 })
}

/// Slope of y over x by least squares, and slope / standard error.
pub fn slope(xs: &[f64], ys: &[f64]) -> (f64, f64) {
    let n = xs.len();
    if n < 3 {
        return (0.0, 0.0);
    }
    let mx = xs.iter().sum::<f64>() / n as f64;
    let my = ys.iter().sum::<f64>() / n as f64;
    let sxx: f64 = xs.iter().map(|x| (x - mx).powi(2)).sum();
    if sxx <= 0.0 {
        return (0.0, 0.0);
    }
    let b = xs
        .iter()
        .zip(ys)
        .map(|(x, y)| (x - mx) * (y - my))
        .sum::<f64>()
        / sxx;
    let rss: f64 = xs
        .iter()
        .zip(ys)
        .map(|(x, y)| (y - my - b * (x - mx)).powi(2))
        .sum();
    let se = (rss / (n - 2) as f64 / sxx).sqrt();
    (b, if se > 0.0 { b / se } else { 0.0 })
}

/// The shift s ∈ [−max, max] frames (step 0.25) minimising
/// Σ_t |(c(t) − c(0)) − (h(t + s) − h(s))|², h linearly interpolated and
/// held at the ends.
pub fn best_shift(centroid: &[[f64; 3]], hand: &[[f64; 3]], max_shift: f64) -> f64 {
    let at = |time: f64| {
        let last = hand.len().saturating_sub(1);
        let time = time.clamp(0.0, last as f64);
        let i = (time.floor() as usize).min(last);
        let j = (i + 1).min(last);
        let w = time - i as f64;
        [0, 1, 2].map(|a| hand[i][a] + w * (hand[j][a] - hand[i][a]))
    };
    let steps = (max_shift / 0.25).round() as i64;
    let mut best: (f64, f64) = (f64::INFINITY, 0.0);
    for step in -steps..=steps {
        let s = step as f64 * 0.25;
        let h0 = at(s);
        let cost: f64 = centroid
            .iter()
            .enumerate()
            .map(|(t, c)| {
                let h = at(t as f64 + s);
                let d = [0, 1, 2].map(|a| (c[a] - centroid[0][a]) - (h[a] - h0[a]));
                dot(d, d)
            })
            .sum();
        if cost < best.0 - 1e-15 || (cost <= best.0 + 1e-15 && s.abs() < best.1.abs()) {
            best = (cost, s);
        }
    }
    best.1
}

/// Centroid per frame of the given tracks (observed: valid points only,
/// frames with none repeat the previous centroid).
fn centroids(frames: &[Vec<Option<[f64; 3]>>], tracks: &[usize]) -> Vec<[f64; 3]> {
    let mut out: Vec<[f64; 3]> = Vec::with_capacity(frames.len());
    for frame in frames {
        let pts: Vec<[f64; 3]> = tracks.iter().filter_map(|&k| frame[k]).collect();
        if pts.is_empty() {
            out.push(out.last().copied().unwrap_or([0.0; 3]));
            continue;
        }
        let n = pts.len() as f64;
        out.push([0, 1, 2].map(|a| pts.iter().map(|p| p[a]).sum::<f64>() / n));
    }
    out
}

/// Everything in [`Signatures`]. `near_hand` lists the tracks nearest the
/// hands, `hand_centroid` the recorded hand anchors' centroid per frame.
pub fn signatures(
    samples: &[AccelSample],
    matched: &Matched,
    near_hand: &[usize],
    hand_centroid: &[[f64; 3]],
    up: [f64; 3],
    floor_height: f64,
    axis: [f64; 3],
) -> Signatures {
    let pairs: Vec<([f64; 3], [f64; 3])> =
        samples.iter().map(|s| (s.velocity, s.residual)).collect();
    let (drag_rate_per_s, drag_t) = opposing_rate(&pairs);
    let horizontal = |v: [f64; 3]| {
        let n = dot(v, up);
        [0, 1, 2].map(|a| v[a] - n * up[a])
    };
    let floor_pairs: Vec<([f64; 3], [f64; 3])> = samples
        .iter()
        .filter(|s| dot(s.position, up) - floor_height < FLOOR_BAND_M)
        .map(|s| (horizontal(s.velocity), horizontal(s.residual)))
        .collect();
    let (floor_rate_per_s, floor_t) = opposing_rate(&floor_pairs);
    let horizontals: Vec<[f64; 3]> = samples.iter().map(|s| horizontal(s.residual)).collect();
    let (horizontal_accel, horizontal_t) = mean_and_t(&horizontals);
    let xs: Vec<f64> = samples.iter().map(|s| dot(s.position, axis)).collect();
    let ys: Vec<f64> = samples.iter().map(|s| dot(s.residual, up)).collect();
    let (sag_slope, sag_t) = slope(&xs, &ys);
    let simulated: Vec<Vec<Option<[f64; 3]>>> = matched
        .simulated
        .iter()
        .map(|f| f.iter().map(|p| Some(*p)).collect())
        .collect();
    let observed_shift = best_shift(&centroids(&matched.observed, near_hand), hand_centroid, 6.0);
    let simulated_shift = best_shift(&centroids(&simulated, near_hand), hand_centroid, 6.0);
    Signatures {
        drag_rate_per_s,
        drag_t,
        floor_rate_per_s,
        floor_t,
        horizontal_accel,
        horizontal_t,
        hand_shift_frames: observed_shift - simulated_shift,
        sag_slope,
        sag_t,
    }
}
