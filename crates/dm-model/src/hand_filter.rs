//! Smoothing of the recorded hand track before it drives the actuators.
//!
//! A hand tracker's per-frame jitter (millimetres at 30 fps) is a velocity
//! noise of several cm/s, which the actuators' spring-dampers turn into
//! forces the object never felt; a dropped frame holds the last position
//! and then jumps. Each anchor's track is replaced by a local linear fit
//! over its visible frames with Gaussian weights in time (a kernel
//! regression: unbiased on straight motion and at the clip's ends, where
//! a plain moving average would lag).

use ndarray::{Array2, Array3};

/// Frames on each side of a frame that the kernel reaches (in σ).
const KERNEL_REACH_SIGMAS: f64 = 3.0;

/// The hand track smoothed with a Gaussian kernel of `sigma_frames`
/// (σ = 0 returns the track unchanged). `visibility[t][j]` marks the
/// frames where anchor j was measured; the others are filled from the
/// fit. An anchor seen in no frame within reach keeps its values.
pub fn smooth_hand_track(
    points: &Array3<f32>,
    visibility: &Array2<bool>,
    sigma_frames: f64,
) -> Array3<f32> {
    let mut out = points.clone();
    for t in 0..points.shape()[0] {
        for (j, p) in smoothed_frame(points, visibility, t, sigma_frames)
            .iter()
            .enumerate()
        {
            for a in 0..3 {
                out[[t, j, a]] = p[a] as f32;
            }
        }
    }
    out
}

/// Frame `t` of [`smooth_hand_track`], every anchor (metres).
pub fn smoothed_frame(
    points: &Array3<f32>,
    visibility: &Array2<bool>,
    t: usize,
    sigma_frames: f64,
) -> Vec<[f64; 3]> {
    let (frames, anchors) = (points.shape()[0], points.shape()[1]);
    let raw = |s: usize, j: usize| [0, 1, 2].map(|a| f64::from(points[[s, j, a]]));
    if sigma_frames <= 0.0 {
        return (0..anchors).map(|j| raw(t, j)).collect();
    }
    let reach = (KERNEL_REACH_SIGMAS * sigma_frames).ceil() as usize;
    let lo = t.saturating_sub(reach);
    let hi = (t + reach).min(frames - 1);
    (0..anchors)
        .map(|j| {
            let (mut s0, mut s1, mut s2) = (0.0, 0.0, 0.0);
            let (mut m0, mut m1) = ([0.0f64; 3], [0.0f64; 3]);
            for s in (lo..=hi).filter(|&s| visibility[[s, j]]) {
                let d = s as f64 - t as f64;
                let w = (-0.5 * (d / sigma_frames).powi(2)).exp();
                s0 += w;
                s1 += w * d;
                s2 += w * d * d;
                let y = raw(s, j);
                for a in 0..3 {
                    m0[a] += w * y[a];
                    m1[a] += w * d * y[a];
                }
            }
            if s0 == 0.0 {
                return raw(t, j);
            }
            // The local line a + b d at d = 0; a constant where the visible
            // frames do not fix a slope (a single frame within reach).
            let det = s0 * s2 - s1 * s1;
            [0, 1, 2].map(|a| {
                if det > 1e-9 * s0 * s0 {
                    (s2 * m0[a] - s1 * m1[a]) / det
                } else {
                    m0[a] / s0
                }
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// One anchor moving along `path(t)`, seen where `seen(t)`; unseen
    /// frames hold the last seen value, as a tracker's output does.
    fn track(
        frames: usize,
        path: impl Fn(f64) -> [f64; 3],
        seen: impl Fn(usize) -> bool,
    ) -> (Array3<f32>, Array2<bool>) {
        let mut points = Array3::<f32>::zeros((frames, 1, 3));
        let mut visibility = Array2::<bool>::from_elem((frames, 1), false);
        for t in 0..frames {
            let visible = t == 0 || seen(t);
            visibility[[t, 0]] = visible;
            for a in 0..3 {
                points[[t, 0, a]] = if visible {
                    path(t as f64)[a] as f32
                } else {
                    points[[t - 1, 0, a]]
                };
            }
        }
        (points, visibility)
    }

    #[test]
    fn zero_sigma_leaves_the_track_unchanged() {
        let (points, visibility) = track(10, |t| [t, 2.0 * t, 0.5], |t| t % 3 != 0);
        assert_eq!(smooth_hand_track(&points, &visibility, 0.0), points);
    }

    /// Straight motion is reproduced at every frame, the clip's ends and the
    /// dropped frames included (a local line fits a line exactly), where a
    /// held value had frozen the anchor.
    #[test]
    fn straight_motion_is_kept_and_dropped_frames_are_filled() {
        let path = |t: f64| [0.1 + 0.01 * t, -0.02 * t, 0.3];
        let (points, visibility) = track(30, path, |t| t % 4 != 1);
        let smoothed = smooth_hand_track(&points, &visibility, 2.0);
        for t in 0..30 {
            for a in 0..3 {
                let error = (f64::from(smoothed[[t, 0, a]]) - path(t as f64)[a]).abs();
                // f32 storage of values near 0.4 m.
                assert!(error < 1e-6, "frame {t} axis {a}: off by {error}");
            }
        }
    }

    /// Seeded jitter of 3 mm on a minimum-jerk-like curve: the smoothed
    /// track is at least twice as close to the true curve as the
    /// measurements, in position and in frame-to-frame velocity.
    #[test]
    fn jitter_is_reduced() {
        let frames = 72;
        let path = |t: f64| {
            let s = (t / 71.0).clamp(0.0, 1.0);
            let m = s * s * s * (10.0 - 15.0 * s + 6.0 * s * s);
            [0.12 * m, 0.04 * m, 0.02 + 0.05 * m]
        };
        let noise = Normal::new(0.0, 0.003).expect("valid σ");
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let jitter: Vec<[f64; 3]> = (0..frames)
            .map(|_| [0, 1, 2].map(|_| noise.sample(&mut rng)))
            .collect();
        let noisy = |t: f64| {
            let p = path(t);
            let e = jitter[t as usize];
            [p[0] + e[0], p[1] + e[1], p[2] + e[2]]
        };
        let (points, visibility) = track(frames, noisy, |t| t % 10 != 5);
        let smoothed = smooth_hand_track(&points, &visibility, 2.0);
        let rms = |track: &Array3<f32>, velocity: bool| {
            let mut sum = 0.0;
            for t in 1..frames {
                for a in 0..3 {
                    let value = |tt: usize| f64::from(track[[tt, 0, a]]) - path(tt as f64)[a];
                    let e = if velocity {
                        value(t) - value(t - 1)
                    } else {
                        value(t)
                    };
                    sum += e * e;
                }
            }
            (sum / (3 * (frames - 1)) as f64).sqrt()
        };
        for velocity in [false, true] {
            let (before, after) = (rms(&points, velocity), rms(&smoothed, velocity));
            assert!(
                after < 0.5 * before,
                "velocity {velocity}: RMS error {before:.2e} → {after:.2e}"
            );
        }
    }
}
