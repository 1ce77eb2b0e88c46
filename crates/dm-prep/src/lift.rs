//! 2D tracks + depth + calibration → 3D tracks. Each camera's tracks are
//! lifted with a robust depth (the median of the valid depths of a small
//! window on the track's own mask, so a window across an edge takes no
//! floor or hand depth); tracks of different cameras that follow the same
//! material point are fused (averaged where both see it) and duplicates
//! dropped.

use dm_mpm::neighbors::PointIndex;
use dm_view::Camera;
use image::GrayImage;

use crate::track2d::Tracks2d;

/// Settings of the lift and fusion.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LiftOptions {
    /// Half size of the depth window (pixels): (2r+1)² samples.
    pub depth_window_radius: u32,
    /// Fewest valid depth samples in the window.
    pub min_depth_samples: usize,
    /// Largest spread (m) between the window's median and its samples
    /// that still counts (outliers beyond it are dropped before the median).
    pub depth_spread_m: f32,
    /// Tracks of two cameras closer than this at frame 0 (m) are candidates
    /// for fusion.
    pub fuse_radius_m: f64,
    /// ...and are fused when their median distance over the frames both
    /// see stays below this (m).
    pub fuse_agreement_m: f64,
    /// Object tracks are smoothed in time over this many frames either
    /// side (`smooth_in_time`); 0: not at all.
    #[serde(default = "default_smooth_half_frames")]
    pub smooth_half_frames: usize,
}

fn default_smooth_half_frames() -> usize {
    5
}

impl Default for LiftOptions {
    fn default() -> Self {
        Self {
            depth_window_radius: 2,
            min_depth_samples: 5,
            depth_spread_m: 0.01,
            fuse_radius_m: 0.003,
            fuse_agreement_m: 0.004,
            smooth_half_frames: default_smooth_half_frames(),
        }
    }
}

/// 3D tracks: `points[t][n]` world metres, `valid[t][n]`.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Tracks3d {
    pub points: Vec<Vec<[f64; 3]>>,
    pub valid: Vec<Vec<bool>>,
}

impl Tracks3d {
    pub fn len(&self) -> usize {
        self.points.first().map_or(0, Vec::len)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn column(&self, n: usize) -> (Vec<[f64; 3]>, Vec<bool>) {
        (
            self.points.iter().map(|row| row[n]).collect(),
            self.valid.iter().map(|row| row[n]).collect(),
        )
    }
}

/// Robust depth (m) at pixel `(u, v)` of `depth_m` over `mask`.
pub fn window_depth(
    depth_m: &[f32],
    width: u32,
    height: u32,
    mask: Option<&GrayImage>,
    u: f32,
    v: f32,
    options: &LiftOptions,
) -> Option<f32> {
    let (cx, cy) = (u.floor() as i64, v.floor() as i64);
    let r = i64::from(options.depth_window_radius);
    let mut samples = Vec::with_capacity(((2 * r + 1) * (2 * r + 1)) as usize);
    for y in cy - r..=cy + r {
        for x in cx - r..=cx + r {
            if x < 0 || y < 0 || x >= i64::from(width) || y >= i64::from(height) {
                continue;
            }
            if let Some(mask) = mask
                && mask.get_pixel(x as u32, y as u32).0[0] == 0
            {
                continue;
            }
            let d = depth_m[(y as usize) * width as usize + x as usize];
            if d.is_finite() && d > 0.0 {
                samples.push(d);
            }
        }
    }
    if samples.len() < options.min_depth_samples {
        return None;
    }
    samples.sort_by(f32::total_cmp);
    let median = samples[samples.len() / 2];
    let kept: Vec<f32> = samples
        .into_iter()
        .filter(|d| (d - median).abs() <= options.depth_spread_m)
        .collect();
    if kept.len() < options.min_depth_samples {
        return None;
    }
    Some(kept[kept.len() / 2])
}

/// Lifts one camera's 2D tracks: `depth[t]` (m, row-major, NaN = none) and
/// `masks[t]` the mask the tracks live on.
pub fn lift_camera(
    camera: &Camera,
    tracks: &Tracks2d,
    depth: &[Vec<f32>],
    masks: &[GrayImage],
    options: &LiftOptions,
) -> Tracks3d {
    let frames = tracks.points.len();
    let n = tracks.len();
    let mut out = Tracks3d {
        points: vec![vec![[0.0; 3]; n]; frames],
        valid: vec![vec![false; n]; frames],
    };
    for t in 0..frames {
        for k in 0..n {
            if !tracks.alive[t][k] {
                continue;
            }
            let [u, v] = tracks.points[t][k];
            if let Some(d) = window_depth(
                &depth[t],
                camera.width,
                camera.height,
                Some(&masks[t]),
                u,
                v,
                options,
            ) {
                let p = camera.unproject(f64::from(u), f64::from(v), f64::from(d));
                out.points[t][k] = [p.x, p.y, p.z];
                out.valid[t][k] = true;
            }
        }
    }
    out
}

fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Smooths each track in time: over each run of consecutive valid frames,
/// a point becomes the value at its frame of the least-squares quadratic
/// through the run's points within `half` frames of it (Savitzky–Golay
/// where the whole window lies in the run). Sensor depth noise is
/// independent from frame to frame; a material point moves smoothly.
/// Runs shorter than 3 frames are left alone.
pub fn smooth_in_time(tracks: &mut Tracks3d, half: usize) {
    if half == 0 {
        return;
    }
    let frames = tracks.points.len();
    for k in 0..tracks.len() {
        let (points, valid) = tracks.column(k);
        let mut t = 0;
        while t < frames {
            if !valid[t] {
                t += 1;
                continue;
            }
            let start = t;
            while t < frames && valid[t] {
                t += 1;
            }
            let run = start..t;
            if run.len() < 3 {
                continue;
            }
            for centre in run.clone() {
                let lo = centre.saturating_sub(half).max(run.start);
                let hi = (centre + half + 1).min(run.end);
                tracks.points[centre][k] =
                    quadratic_at_zero((lo..hi).map(|s| (s as f64 - centre as f64, points[s])));
            }
        }
    }
}

/// The value at 0 of the least-squares quadratic through at least 3
/// `(offset, point)` samples.
fn quadratic_at_zero(samples: impl Iterator<Item = (f64, [f64; 3])>) -> [f64; 3] {
    // Normal equations of p(s) = c0 + c1 s + c2 s².
    let mut m = [[0.0f64; 3]; 3];
    let mut b = [[0.0f64; 3]; 3];
    for (s, p) in samples {
        let basis = [1.0, s, s * s];
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] += basis[i] * basis[j];
            }
            for a in 0..3 {
                b[a][i] += basis[i] * p[a];
            }
        }
    }
    let det3 = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let det = det3(&m);
    // Cramer's rule for c0: replace the first column by b.
    std::array::from_fn(|a| {
        let mut m0 = m;
        for i in 0..3 {
            m0[i][0] = b[a][i];
        }
        det3(&m0) / det
    })
}

/// Fuses the tracks of several cameras: only tracks valid at frame 0 are
/// kept; a track of a later camera that follows an earlier kept track
/// (close at frame 0, median distance over common frames small) is
/// averaged into it instead of being added.
pub fn fuse_cameras(per_camera: &[Tracks3d], options: &LiftOptions) -> Tracks3d {
    let frames = per_camera.iter().map(|t| t.points.len()).max().unwrap_or(0);
    // Fused tracks: sum of positions and count per frame.
    let mut sums: Vec<Vec<[f64; 3]>> = Vec::new();
    let mut counts: Vec<Vec<u32>> = Vec::new();
    let mut first_points: Vec<[f64; 3]> = Vec::new();
    for tracks in per_camera {
        // Tracks of one camera never fuse with each other: the index holds
        // the earlier cameras' tracks only.
        let index = PointIndex::new(&first_points);
        let mut additions = Vec::new();
        for k in 0..tracks.len() {
            let (points, valid) = tracks.column(k);
            if !valid[0] {
                continue;
            }
            let mut best: Option<(usize, f64)> = None;
            for (j, _) in index.within(&points[0], options.fuse_radius_m) {
                let mut ds: Vec<f64> = (0..frames)
                    .filter(|&t| valid[t] && counts[j][t] > 0)
                    .map(|t| {
                        let mean = sums[j][t].map(|s| s / f64::from(counts[j][t]));
                        distance(mean, points[t])
                    })
                    .collect();
                ds.sort_by(f64::total_cmp);
                let agreement = ds[ds.len() / 2];
                if agreement <= options.fuse_agreement_m && best.is_none_or(|b| agreement < b.1) {
                    best = Some((j, agreement));
                }
            }
            match best {
                Some((j, _)) => {
                    for t in 0..frames {
                        if valid[t] {
                            for a in 0..3 {
                                sums[j][t][a] += points[t][a];
                            }
                            counts[j][t] += 1;
                        }
                    }
                }
                None => additions.push((points, valid)),
            }
        }
        for (points, valid) in additions {
            first_points.push(points[0]);
            sums.push(
                (0..frames)
                    .map(|t| if valid[t] { points[t] } else { [0.0; 3] })
                    .collect(),
            );
            counts.push(valid.iter().map(|&v| u32::from(v)).collect());
        }
    }
    let n = sums.len();
    let mut out = Tracks3d {
        points: vec![vec![[0.0; 3]; n]; frames],
        valid: vec![vec![false; n]; frames],
    };
    for j in 0..n {
        for t in 0..frames {
            if counts[j][t] > 0 {
                out.points[t][j] = sums[j][t].map(|s| s / f64::from(counts[j][t]));
                out.valid[t][j] = true;
            }
        }
    }
    out
}

/// Fills frames where a track is not valid with its last valid position
/// (the bundle needs finite values everywhere; validity says which count).
pub fn hold_last(tracks: &mut Tracks3d) {
    for t in 1..tracks.points.len() {
        for k in 0..tracks.len() {
            if !tracks.valid[t][k] {
                tracks.points[t][k] = tracks.points[t - 1][k];
            }
        }
    }
}

/// The 3D points of a mask's pixels (every `stride`-th pixel in both
/// directions) with a valid depth (m, row-major; NaN or ≤ 0 = none).
pub fn mask_cloud(camera: &Camera, depth: &[f32], mask: &GrayImage, stride: u32) -> Vec<[f64; 3]> {
    let stride = stride.max(1);
    let mut out = Vec::new();
    for v in (0..mask.height().min(camera.height)).step_by(stride as usize) {
        for u in (0..mask.width().min(camera.width)).step_by(stride as usize) {
            if mask.get_pixel(u, v)[0] == 0 {
                continue;
            }
            let d = depth[(v * camera.width + u) as usize];
            if d.is_finite() && d > 0.0 {
                let p = camera.unproject(f64::from(u) + 0.5, f64::from(v) + 0.5, f64::from(d));
                out.push([p.x, p.y, p.z]);
            }
        }
    }
    out
}

/// Fewest hand-mask points that make a hand's centroid at a frame.
pub const MIN_CENTROID_POINTS: usize = 8;

/// The path of a hand's mask centroid: at frame 0 the mean of the points
/// of `clouds[0]` within `radius` of `start`, then at each frame the mean
/// of those within `radius` of the last centroid (`None` where fewer than
/// [`MIN_CENTROID_POINTS`]). `None` when there is no centroid at frame 0.
pub fn hand_centroid_path(
    start: [f64; 3],
    clouds: &[Vec<[f64; 3]>],
    radius: f64,
) -> Option<Vec<Option<[f64; 3]>>> {
    let centroid_near = |cloud: &[[f64; 3]], centre: [f64; 3]| {
        let near: Vec<&[f64; 3]> = cloud
            .iter()
            .filter(|p| distance(**p, centre) <= radius)
            .collect();
        (near.len() >= MIN_CENTROID_POINTS).then(|| {
            let n = near.len() as f64;
            [0, 1, 2].map(|a| near.iter().map(|p| p[a]).sum::<f64>() / n)
        })
    };
    let first = centroid_near(clouds.first()?, start)?;
    let mut path = vec![Some(first)];
    let mut last = first;
    for cloud in &clouds[1..] {
        let now = centroid_near(cloud, last);
        if let Some(c) = now {
            last = c;
        }
        path.push(now);
    }
    Some(path)
}

/// Replaces the point tracks of each hand that lost them with its hand-mask
/// centroid's motion: the fallback for untextured hands, on which point
/// tracks die or stick in place (a track on a uniform patch passes the
/// forward–backward check standing still). `groups[g]` are hand g's anchor
/// columns, `clouds[t]` the hand-mask points of frame t (all cameras). A
/// hand is switched when its anchors are valid in fewer than half the
/// later frames, or when their mean displacement departs from the
/// centroid's by more than `max_disagreement` (median over frames); its
/// anchors then become `anchor(0) + centroid(t) − centroid(0)`, valid where
/// the centroid is (held otherwise). Returns the hands switched.
pub fn follow_hand_centroids(
    anchors: &mut Tracks3d,
    groups: &[std::ops::Range<usize>],
    clouds: &[Vec<[f64; 3]>],
    radius: f64,
    max_disagreement: f64,
) -> Vec<usize> {
    let frames = anchors.points.len().min(clouds.len());
    let mut switched = Vec::new();
    for (g, group) in groups.iter().enumerate() {
        if group.is_empty() || frames < 2 {
            continue;
        }
        let mean_at = |t: usize| {
            let n = group.len() as f64;
            [0, 1, 2].map(|a| group.clone().map(|k| anchors.points[t][k][a]).sum::<f64>() / n)
        };
        let Some(path) = hand_centroid_path(mean_at(0), &clouds[..frames], radius) else {
            continue;
        };
        let c0 = path[0].unwrap_or_default();
        let a0 = mean_at(0);
        let later_valid = (1..frames)
            .flat_map(|t| group.clone().map(move |k| (t, k)))
            .filter(|&(t, k)| anchors.valid[t][k])
            .count();
        let mostly_lost = 2 * later_valid < (frames - 1) * group.len();
        let mut departures: Vec<f64> = (1..frames)
            .filter(|&t| group.clone().all(|k| anchors.valid[t][k]))
            .filter_map(|t| {
                let c = path[t]?;
                let a = mean_at(t);
                Some(distance(
                    [0, 1, 2].map(|i| a[i] - a0[i]),
                    [0, 1, 2].map(|i| c[i] - c0[i]),
                ))
            })
            .collect();
        departures.sort_by(f64::total_cmp);
        let departs = departures
            .get(departures.len() / 2)
            .is_some_and(|&d| d > max_disagreement);
        if !(mostly_lost || departs) {
            continue;
        }
        switched.push(g);
        let mut last = c0;
        for (t, centroid) in path.iter().enumerate().take(frames).skip(1) {
            if let Some(c) = centroid {
                last = *c;
            }
            for k in group.clone() {
                anchors.points[t][k] = [0, 1, 2].map(|a| anchors.points[0][k][a] + last[a] - c0[a]);
                anchors.valid[t][k] = centroid.is_some();
            }
        }
    }
    switched
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, Vector3};

    #[test]
    fn anchors_follow_their_hand_mask_centroid_when_their_tracks_stick() {
        // Two hands 0.3 m apart, two anchors each; the clouds (a blob per
        // hand, offset from the anchors as a palm is from the fingertips)
        // move by known steps; hand 1 is out of sight at frame 2. Hand 0's
        // tracks stay valid but stuck at frame 0's place (an untextured
        // hand); hand 1's were lost.
        let blob = |centre: [f64; 3]| -> Vec<[f64; 3]> {
            (0..27)
                .map(|i| {
                    let o = [i % 3, (i / 3) % 3, i / 9].map(|c| (c as f64 - 1.0) * 0.01);
                    [0, 1, 2].map(|a| centre[a] + o[a])
                })
                .collect()
        };
        let a0 = [
            [0.0, 0.0, 0.0],
            [0.02, 0.0, 0.0],
            [0.3, 0.0, 0.0],
            [0.32, 0.0, 0.0],
        ];
        let mut anchors = Tracks3d {
            points: vec![a0.to_vec(); 3],
            valid: vec![
                vec![true; 4],
                vec![true, true, false, false],
                vec![true, true, false, false],
            ],
        };
        let palm = [0.01, 0.0, 0.03];
        let shift = |p: [f64; 3], d: [f64; 3]| [0, 1, 2].map(|a| p[a] + d[a]);
        let (h0, h1) = (shift(a0[0], palm), shift(a0[2], palm));
        let step = [0.0, 0.01, 0.02];
        let clouds = vec![
            [blob(h0), blob(h1)].concat(),
            [blob(shift(h0, step)), blob(shift(h1, [-0.01, 0.0, 0.0]))].concat(),
            blob(shift(shift(h0, step), step)),
        ];
        let groups = [0..2, 2..4];
        let stuck = anchors.clone();
        assert_eq!(
            follow_hand_centroids(&mut anchors, &groups, &clouds, 0.09, 0.02),
            [0, 1]
        );
        let close = |p: [f64; 3], q: [f64; 3]| distance(p, q) < 1e-12;
        assert!(close(anchors.points[1][1], shift(a0[1], step)));
        assert!(close(anchors.points[2][0], shift(a0[0], [0.0, 0.02, 0.04])));
        assert!(close(anchors.points[1][3], shift(a0[3], [-0.01, 0.0, 0.0])));
        assert_eq!(anchors.valid[2], [true, true, false, false]);
        // Hand 1 lost at frame 2 keeps its last position.
        assert!(close(anchors.points[2][2], anchors.points[1][2]));
        // Tracks that move with the centroid are kept as they are.
        let mut moving = anchors.clone();
        moving.valid = vec![vec![true; 4]; 3];
        let kept = moving.clone();
        let none: Vec<usize> = Vec::new();
        assert_eq!(
            follow_hand_centroids(&mut moving, &groups[..1], &clouds, 0.09, 0.02),
            none
        );
        assert_eq!(moving, kept);
        assert_ne!(stuck, anchors);
    }

    fn camera() -> Camera {
        Camera::look_at(
            Point3::new(0.3, -0.4, 0.5),
            Point3::new(0.0, 0.0, 0.05),
            Vector3::z(),
            80,
            60,
            50.0,
        )
    }

    #[test]
    fn lift_of_a_known_pixel_and_depth_gives_the_known_point() {
        let camera = camera();
        let point = Point3::new(0.02, -0.01, 0.04);
        let (u, v, z) = camera.project(&point).expect("in front");
        let depth = vec![vec![z as f32; 80 * 60]];
        let masks = vec![GrayImage::from_pixel(80, 60, image::Luma([255]))];
        let tracks = Tracks2d {
            points: vec![vec![[u as f32, v as f32]]],
            alive: vec![vec![true]],
        };
        let lifted = lift_camera(&camera, &tracks, &depth, &masks, &LiftOptions::default());
        assert!(lifted.valid[0][0]);
        let p = lifted.points[0][0];
        // f32 pixel coordinates and depth: ~1e-7 relative of 0.7 m.
        assert!(distance(p, [point.x, point.y, point.z]) < 1e-5, "{p:?}");
    }

    #[test]
    fn window_depth_ignores_other_masks_and_outliers() {
        let (w, h) = (9u32, 9u32);
        let mut depth = vec![0.5f32; 81];
        let mut mask = GrayImage::from_pixel(w, h, image::Luma([255]));
        for y in 0..9 {
            for x in 5..9 {
                depth[y * 9 + x] = 0.9; // the floor, beside the object
                mask.put_pixel(x as u32, y as u32, image::Luma([0]));
            }
        }
        depth[4 * 9 + 3] = f32::NAN;
        let options = LiftOptions::default();
        let d = window_depth(&depth, w, h, Some(&mask), 4.5, 4.5, &options).expect("depth");
        assert_eq!(d, 0.5);
        assert!(
            window_depth(
                &depth,
                w,
                h,
                Some(&GrayImage::new(w, h)),
                4.5,
                4.5,
                &options
            )
            .is_none()
        );
    }

    /// A point on a quadratic path comes through unchanged; seeded noise
    /// on it shrinks; a frame without the point splits the runs and stays
    /// as it was.
    #[test]
    fn smoothing_in_time_keeps_quadratic_motion_and_shrinks_noise() {
        const FRAMES: usize = 40;
        let path = |t: usize| {
            let s = t as f64 / 30.0;
            [0.1 + 0.2 * s, -0.05 * s + 0.3 * s * s, 0.02]
        };
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut noise = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.006
        };
        let gap = 17;
        let mut tracks = Tracks3d {
            points: (0..FRAMES)
                .map(|t| {
                    let p = path(t);
                    vec![p, [p[0] + noise(), p[1] + noise(), p[2] + noise()]]
                })
                .collect(),
            valid: (0..FRAMES).map(|t| vec![t != gap, t != gap]).collect(),
        };
        tracks.points[gap] = vec![[9.0; 3], [9.0; 3]];
        let noisy = tracks.clone();
        smooth_in_time(&mut tracks, 2);
        let error = |tracks: &Tracks3d| {
            let squares: f64 = (0..FRAMES)
                .filter(|&t| t != gap)
                .map(|t| {
                    let p = path(t);
                    (0..3)
                        .map(|a| (tracks.points[t][1][a] - p[a]).powi(2))
                        .sum::<f64>()
                })
                .sum();
            (squares / (FRAMES - 1) as f64).sqrt()
        };
        for t in (0..FRAMES).filter(|&t| t != gap) {
            for a in 0..3 {
                assert!(
                    (tracks.points[t][0][a] - path(t)[a]).abs() < 1e-12,
                    "frame {t}"
                );
            }
        }
        assert_eq!(tracks.points[gap], vec![[9.0; 3], [9.0; 3]]);
        let (before, after) = (error(&noisy), error(&tracks));
        assert!(
            after < 0.8 * before,
            "RMS error {after} m against {before} m before"
        );
    }

    #[test]
    fn fusion_averages_the_same_point_seen_twice_and_keeps_others() {
        let a = Tracks3d {
            points: vec![
                vec![[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]],
                vec![[0.0, 0.0, 0.01], [0.1, 0.0, 0.01]],
            ],
            valid: vec![vec![true, true], vec![true, true]],
        };
        let b = Tracks3d {
            points: vec![
                vec![[0.001, 0.0, 0.0], [0.5, 0.0, 0.0]],
                vec![[0.001, 0.0, 0.01], [0.5, 0.0, 0.0]],
            ],
            valid: vec![vec![true, true], vec![true, false]],
        };
        let fused = fuse_cameras(&[a, b], &LiftOptions::default());
        assert_eq!(fused.len(), 3);
        assert!(distance(fused.points[1][0], [0.0005, 0.0, 0.01]) < 1e-12);
        assert!(fused.valid[0][2] && !fused.valid[1][2]);
    }
}
