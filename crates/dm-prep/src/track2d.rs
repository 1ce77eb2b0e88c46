//! Dense 2D tracks without learned weights: farthest-point queries on the
//! first mask (among pixels with texture enough to track), followed frame
//! to frame by OpenCV's pyramidal Lucas–Kanade with a forward–backward
//! check. A track that fails the check or leaves its mask is lost for the
//! rest of the clip (it never jumps to another surface).
//!
//! Frame-to-frame flow accumulates its sub-pixel errors: on a deforming toy
//! the median 3D error grew from 3 mm at frame 0 to 12 mm at frame 71. Each
//! step is therefore re-anchored: the frame-to-frame position seeds a second
//! Lucas–Kanade solve from the query's frame-0 window straight to frame t,
//! whose answer (when it passes its own forward–backward check and stays
//! near the seed) replaces the seed, so errors no longer add up.
//!
//! Once the object has turned or moved under other light, its frame-0
//! windows no longer match (on a pushed toy a third of one camera's tracks
//! still anchored after the push, a sixth of another's), and frame-to-frame
//! flow took over again. So each track also keeps a keyframe — the last
//! frame where it anchored to frame 0, renewed every `keyframe_every`
//! frames — and a track that fails to anchor to frame 0 anchors to its
//! keyframe instead.
//!
//! Before falling back to its keyframe, a track that missed frame 0 tries
//! once more with its frame-0 window warped: an affine map with a gain and
//! a bias (`affine_lk`), started from the warp it last anchored with, so a
//! turning, shaded solid stays anchored to its first frame. On rendered
//! toys the warped window still leaves a residual of half to all of its
//! contrast (shading varies across it; sensor noise), yet the frame-0
//! answer within `anchor_px` of the seed beats a chain of keyframes, so
//! the residual only has to stay below the window's contrast.
//!
//! A window inside the object (`affine_interior` of it on the first mask)
//! takes the warped answer also where the translation anchor passed, once
//! the warp departs from a plain shift (`affine_departure`): on a turning
//! toy that anchor passes its checks with a bias the warp removes, while
//! on a shifting noisy texture the warp's extra parameters only add noise.
//! A window on the object's edge keeps the translation anchor: its
//! background does not move with the object, and on a thin rope the warp
//! fitted to it drifted.

use crate::affine_lk::{AffineFit, GreyView, WindowWarp, fit_window};
use image::{GrayImage, RgbImage};
use opencv::core::{Mat, Point2f, Size, TermCriteria, Vector};
use opencv::prelude::{MatTraitConst, MatTraitConstManual, MatTraitManual};

/// Settings of the fallback tracker.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrackOptions {
    /// Queries per camera and mask.
    pub queries: usize,
    /// Lucas–Kanade window (pixels, odd).
    pub window: i32,
    /// Pyramid levels above the image.
    pub pyramid_levels: i32,
    /// Forward–backward disagreement (pixels) above which a track is lost.
    pub forward_backward_px: f32,
    /// Smallest structure-tensor eigenvalue (of 8-bit grey, 3×3 blocks) of a
    /// query pixel: flat pixels cannot be tracked.
    pub min_texture: f32,
    /// Mask pixels within this distance (px) of the mask's edge are not
    /// queried (their window sees the background).
    pub edge_margin_px: u32,
    /// Re-anchor each step to the frame-0 window (see the module note); the
    /// anchored answer is kept only within this distance (px) of the
    /// frame-to-frame one. 0 disables re-anchoring.
    #[serde(default = "default_anchor_px")]
    pub anchor_px: f32,
    /// A track that cannot anchor to frame 0 anchors to its keyframe,
    /// renewed after this many frames (see the module note). 0: frame 0
    /// only.
    #[serde(default = "default_keyframe_every")]
    pub keyframe_every: usize,
    /// A track that misses frame 0 tries its frame-0 window under an
    /// affine warp with gain and bias (see the module note), kept when the
    /// residual's RMS is at most this fraction of the window's contrast.
    /// 0 disables it.
    #[serde(default = "default_affine_residual")]
    pub affine_residual: f32,
    /// A track whose frame-0 window lies at least this fraction on the
    /// first mask takes the warped window whenever it fits, also where
    /// translation anchors (see the module note). Above 1: never.
    #[serde(default = "default_affine_interior")]
    pub affine_interior: f32,
    /// There, the warp replaces a passing translation anchor once its
    /// linear part or gain departs from a plain shift by more than this.
    #[serde(default = "default_affine_departure")]
    pub affine_departure: f32,
}

fn default_affine_interior() -> f32 {
    0.9
}

fn default_affine_departure() -> f32 {
    0.1
}

fn default_affine_residual() -> f32 {
    1.0
}

fn default_anchor_px() -> f32 {
    3.0
}

fn default_keyframe_every() -> usize {
    8
}

impl Default for TrackOptions {
    fn default() -> Self {
        Self {
            queries: 600,
            window: 15,
            pyramid_levels: 3,
            forward_backward_px: 0.5,
            min_texture: 1e-4,
            edge_margin_px: 3,
            anchor_px: default_anchor_px(),
            keyframe_every: default_keyframe_every(),
            affine_residual: default_affine_residual(),
            affine_interior: default_affine_interior(),
            affine_departure: default_affine_departure(),
        }
    }
}

/// 2D tracks of one camera: `points[t][n]` (pixel coordinates, pixel
/// centres at +0.5) and `alive[t][n]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Tracks2d {
    pub points: Vec<Vec<[f32; 2]>>,
    pub alive: Vec<Vec<bool>>,
}

impl Tracks2d {
    pub fn len(&self) -> usize {
        self.points.first().map_or(0, Vec::len)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Tracks that start at `queries` in frame 0, all alive.
    pub fn starting_at(queries: &[[f32; 2]]) -> Self {
        Tracks2d {
            points: vec![queries.to_vec()],
            alive: vec![vec![true; queries.len()]],
        }
    }

    /// Appends the next frame. A live track moves to `found(k)` when that is
    /// a finite position; otherwise it is lost for the rest of the clip and
    /// holds its last position (it never jumps to another surface).
    /// `found` is asked about live tracks only.
    pub fn push_frame<E>(
        &mut self,
        mut found: impl FnMut(usize) -> Result<Option<[f32; 2]>, E>,
    ) -> Result<(), E> {
        let (Some(previous), Some(was_alive)) = (self.points.last(), self.alive.last()) else {
            return Ok(());
        };
        let mut next = Vec::with_capacity(previous.len());
        let mut next_alive = Vec::with_capacity(previous.len());
        for (k, (&last, &alive)) in previous.iter().zip(was_alive).enumerate() {
            let moved = if alive { found(k)? } else { None };
            match moved.filter(|p| p[0].is_finite() && p[1].is_finite()) {
                Some(p) => {
                    next.push(p);
                    next_alive.push(true);
                }
                None => {
                    next.push(last);
                    next_alive.push(false);
                }
            }
        }
        self.points.push(next);
        self.alive.push(next_alive);
        Ok(())
    }
}

/// Distance between two OpenCV points (px).
fn distance(a: Point2f, b: Point2f) -> f32 {
    ((a.x - b.x).powi(2) + (a.y - b.y).powi(2)).sqrt()
}

/// Grey 8-bit `Mat` of an RGB image.
pub fn grey_mat(image: &RgbImage) -> opencv::Result<Mat> {
    let (w, h) = image.dimensions();
    let mut mat = Mat::new_rows_cols_with_default(
        h as i32,
        w as i32,
        opencv::core::CV_8UC1,
        opencv::core::Scalar::all(0.0),
    )?;
    for (y, row) in image.rows().enumerate() {
        let out = mat.at_row_mut::<u8>(y as i32)?;
        for (o, p) in out.iter_mut().zip(row) {
            let v = 0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2]);
            *o = v.round().clamp(0.0, 255.0) as u8;
        }
    }
    Ok(mat)
}

/// Mask pixels at least `margin` pixels (chessboard distance) inside the mask.
fn eroded(mask: &GrayImage, margin: u32) -> Vec<(u32, u32)> {
    let (w, h) = mask.dimensions();
    let m = margin as i64;
    let inside = |x: i64, y: i64| {
        x >= 0
            && y >= 0
            && x < w as i64
            && y < h as i64
            && mask.get_pixel(x as u32, y as u32).0[0] > 0
    };
    let mut out = Vec::new();
    for y in 0..h as i64 {
        for x in 0..w as i64 {
            if inside(x, y)
                && inside(x - m, y)
                && inside(x + m, y)
                && inside(x, y - m)
                && inside(x, y + m)
                && inside(x - m, y - m)
                && inside(x + m, y + m)
                && inside(x - m, y + m)
                && inside(x + m, y - m)
            {
                out.push((x as u32, y as u32));
            }
        }
    }
    out
}

/// Farthest-point query pixels on `mask` among pixels with texture.
pub fn query_pixels(
    first: &Mat,
    mask: &GrayImage,
    options: &TrackOptions,
) -> opencv::Result<Vec<[f32; 2]>> {
    let mut eigen = Mat::default();
    opencv::imgproc::corner_min_eigen_val(first, &mut eigen, 3, 3, opencv::core::BORDER_DEFAULT)?;
    let candidates: Vec<[f64; 3]> = eroded(mask, options.edge_margin_px)
        .into_iter()
        .filter(|&(x, y)| {
            eigen
                .at_2d::<f32>(y as i32, x as i32)
                .is_ok_and(|&e| e >= options.min_texture)
        })
        .map(|(x, y)| [f64::from(x) + 0.5, f64::from(y) + 0.5, 0.0])
        .collect();
    Ok(
        dm_mpm::neighbors::farthest_point_sampling(&candidates, options.queries)
            .into_iter()
            .map(|i| [candidates[i][0] as f32, candidates[i][1] as f32])
            .collect(),
    )
}

fn lk(
    from: &Mat,
    to: &Mat,
    points: &Vector<Point2f>,
    options: &TrackOptions,
) -> opencv::Result<(Vector<Point2f>, Vector<u8>)> {
    lk_seeded(from, to, points, None, options)
}

/// Lucas–Kanade from `from` to `to`; `seed` (when given) is the starting
/// guess of each point in `to`.
fn lk_seeded(
    from: &Mat,
    to: &Mat,
    points: &Vector<Point2f>,
    seed: Option<&Vector<Point2f>>,
    options: &TrackOptions,
) -> opencv::Result<(Vector<Point2f>, Vector<u8>)> {
    let mut next = seed.cloned().unwrap_or_default();
    let mut status = Vector::<u8>::new();
    let mut error = Vector::<f32>::new();
    opencv::video::calc_optical_flow_pyr_lk(
        from,
        to,
        points,
        &mut next,
        &mut status,
        &mut error,
        Size::new(options.window, options.window),
        options.pyramid_levels,
        TermCriteria::new(
            opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
            40,
            0.003,
        )?,
        if seed.is_some() {
            opencv::video::OPTFLOW_USE_INITIAL_FLOW
        } else {
            0
        },
        1e-4,
    )?;
    Ok((next, status))
}

/// Tracks `queries` (pixel-centre coordinates) through `frames`; a track
/// must stay on `masks[t]` (when given) to stay alive.
pub fn track_points(
    frames: &[Mat],
    masks: Option<&[GrayImage]>,
    queries: &[[f32; 2]],
    options: &TrackOptions,
) -> opencv::Result<Tracks2d> {
    let n = queries.len();
    if n == 0 {
        // OpenCV refuses an empty point list; nothing to track.
        return Ok(Tracks2d {
            points: vec![Vec::new(); frames.len()],
            alive: vec![Vec::new(); frames.len()],
        });
    }
    let mut tracks = Tracks2d::starting_at(queries);
    // OpenCV's LK works in pixel-corner coordinates (pixel centre = integer).
    let to_cv = |p: [f32; 2]| Point2f::new(p[0] - 0.5, p[1] - 0.5);
    let origin: Vector<Point2f> = queries.iter().map(|&p| to_cv(p)).collect();
    // Each track's keyframe: frame and position (pixel-corner coordinates).
    let mut keyframe: Vec<(usize, Point2f)> = origin.iter().map(|p| (0, p)).collect();
    // Each track's warp of its frame-0 window when it last anchored.
    let mut warps: Vec<WindowWarp> = origin.iter().map(|p| WindowWarp::at([p.x, p.y])).collect();
    let affine = AffineFit {
        half: options.window / 2,
        iterations: 30,
        max_relative_residual: options.affine_residual,
    };
    let first = grey_view(&frames[0])?;
    let interior: Vec<bool> = origin
        .iter()
        .map(|p| {
            let window = window_on_mask(
                masks.map(|m| &m[0]),
                [p.x + 0.5, p.y + 0.5],
                options.window / 2,
            );
            window >= options.affine_interior
        })
        .collect();
    for t in 1..frames.len() {
        let current: Vector<Point2f> = tracks.points[t - 1].iter().map(|&p| to_cv(p)).collect();
        let (forward, status_f) = lk(&frames[t - 1], &frames[t], &current, options)?;
        let (backward, status_b) = lk(&frames[t], &frames[t - 1], &forward, options)?;
        let anchoring = options.anchor_px > 0.0 && t > 1;
        let to_first = if anchoring {
            anchor_to_reference(&frames[0], &frames[t], &origin, &forward, options)?
        } else {
            vec![None; n]
        };
        let mut anchored = to_first.clone();
        let mut to_first_warped = vec![false; n];
        if anchoring && options.affine_residual > 0.0 {
            let target = grey_view(&frames[t])?;
            for k in 0..n {
                if !tracks.alive[t - 1][k] || (to_first[k].is_some() && !interior[k]) {
                    continue;
                }
                let seed = forward.get(k)?;
                let start = WindowWarp {
                    centre: [seed.x, seed.y],
                    ..warps[k]
                };
                let origin_k = origin.get(k)?;
                if let Some(w) =
                    fit_window(&first, [origin_k.x, origin_k.y], &target, start, &affine)
                    && distance(Point2f::new(w.centre[0], w.centre[1]), seed) <= options.anchor_px
                {
                    warps[k] = w;
                    if to_first[k].is_none() || w.departure() > options.affine_departure {
                        anchored[k] = Some([w.centre[0] + 0.5, w.centre[1] + 0.5]);
                        to_first_warped[k] = true;
                    }
                }
            }
        }
        if anchoring && options.keyframe_every > 0 {
            // Tracks that missed frame 0, grouped by keyframe (one solve each);
            // a keyframe of the previous frame would repeat the flow above.
            let mut by_keyframe: std::collections::BTreeMap<usize, Vec<usize>> =
                std::collections::BTreeMap::new();
            for k in 0..n {
                let frame = keyframe[k].0;
                if tracks.alive[t - 1][k] && anchored[k].is_none() && frame > 0 && frame + 1 < t {
                    by_keyframe.entry(frame).or_default().push(k);
                }
            }
            for (frame, members) in by_keyframe {
                let from: Vector<Point2f> = members.iter().map(|&k| keyframe[k].1).collect();
                let seed = members
                    .iter()
                    .map(|&k| forward.get(k))
                    .collect::<opencv::Result<Vector<Point2f>>>()?;
                let found = anchor_to_reference(&frames[frame], &frames[t], &from, &seed, options)?;
                for (k, a) in members.into_iter().zip(found) {
                    anchored[k] = a;
                }
            }
        }
        tracks.push_frame(|k| {
            let f = forward.get(k)?;
            let fb = distance(backward.get(k)?, current.get(k)?);
            let p = anchored[k].unwrap_or([f.x + 0.5, f.y + 0.5]);
            let ok = status_f.get(k)? == 1
                && status_b.get(k)? == 1
                && fb <= options.forward_backward_px
                && masks.is_none_or(|masks| on_mask(&masks[t], p));
            Ok::<_, opencv::Error>(ok.then_some(p))
        })?;
        for k in 0..n {
            let renew = to_first[k].is_some()
                || to_first_warped[k]
                || t >= keyframe[k].0 + options.keyframe_every.max(1);
            if tracks.alive[t][k] && renew {
                keyframe[k] = (t, to_cv(tracks.points[t][k]));
            }
        }
    }
    Ok(tracks)
}

/// A grey 8-bit `Mat` as pixels (pixel centres at integers, as OpenCV's).
fn grey_view(mat: &Mat) -> opencv::Result<GreyView<'_>> {
    Ok(GreyView {
        pixels: mat.data_bytes()?,
        width: mat.cols() as usize,
        height: mat.rows() as usize,
    })
}

/// The fraction of the window of half-side `half` centred at `p`
/// (pixel-centre coordinates) on `mask`; without a mask, 1.
fn window_on_mask(mask: Option<&GrayImage>, p: [f32; 2], half: i32) -> f32 {
    let Some(mask) = mask else { return 1.0 };
    let side = 2 * half + 1;
    let on = (-half..=half)
        .flat_map(|j| (-half..=half).map(move |i| [p[0] + i as f32, p[1] + j as f32]))
        .filter(|&q| on_mask(mask, q))
        .count();
    on as f32 / (side * side) as f32
}

/// Whether `p` (pixel-centre coordinates) falls on a set pixel of `mask`.
pub fn on_mask(mask: &GrayImage, p: [f32; 2]) -> bool {
    let (x, y) = (p[0].floor(), p[1].floor());
    x >= 0.0
        && y >= 0.0
        && (x as u32) < mask.width()
        && (y as u32) < mask.height()
        && mask.get_pixel(x as u32, y as u32).0[0] > 0
}

/// The windows of `origin` in the reference frame `first` solved straight
/// into `to`, starting from `seed` (the frame-to-frame answer): per point,
/// the anchored position (pixel-centre coordinates) when it passes a
/// forward–backward check back to the reference and lies within
/// `anchor_px` of the seed.
fn anchor_to_reference(
    first: &Mat,
    to: &Mat,
    origin: &Vector<Point2f>,
    seed: &Vector<Point2f>,
    options: &TrackOptions,
) -> opencv::Result<Vec<Option<[f32; 2]>>> {
    let (anchored, status_f) = lk_seeded(first, to, origin, Some(seed), options)?;
    let (back, status_b) = lk_seeded(to, first, &anchored, Some(origin), options)?;
    let mut out = Vec::with_capacity(origin.len());
    for k in 0..origin.len() {
        let a = anchored.get(k)?;
        let fb = distance(back.get(k)?, origin.get(k)?);
        let shift = distance(a, seed.get(k)?);
        let ok = status_f.get(k)? == 1
            && status_b.get(k)? == 1
            && fb <= options.forward_backward_px
            && shift <= options.anchor_px
            && a.x.is_finite()
            && a.y.is_finite();
        out.push(ok.then_some([a.x + 0.5, a.y + 0.5]));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth random texture (sum of sinusoids) shifted by a known amount.
    fn textured(width: u32, height: u32, shift: [f32; 2]) -> RgbImage {
        RgbImage::from_fn(width, height, |x, y| {
            let (u, v) = (x as f32 - shift[0], y as f32 - shift[1]);
            let value = 128.0
                + 40.0 * (0.31 * u + 0.17 * v).sin()
                + 35.0 * (0.23 * u - 0.29 * v + 1.0).sin()
                + 30.0 * (0.41 * u + 0.05 * v + 2.0).cos()
                + 20.0 * (0.07 * u + 0.37 * v).sin();
            let g = value.clamp(0.0, 255.0) as u8;
            image::Rgb([g, g, g])
        })
    }

    #[test]
    fn lucas_kanade_recovers_a_known_shift() {
        let shifts = [[0.0, 0.0], [1.3, -0.7], [2.9, 0.4], [4.2, 2.1]];
        let frames: Vec<Mat> = shifts
            .iter()
            .map(|&s| grey_mat(&textured(96, 80, s)).expect("grey"))
            .collect();
        let mask = GrayImage::from_pixel(96, 80, image::Luma([255]));
        let options = TrackOptions {
            queries: 30,
            edge_margin_px: 16,
            ..TrackOptions::default()
        };
        let queries = query_pixels(&frames[0], &mask, &options).expect("queries");
        assert_eq!(queries.len(), 30);
        let tracks = track_points(&frames, None, &queries, &options).expect("tracking");
        for (t, shift) in shifts.iter().enumerate() {
            for (k, q) in queries.iter().enumerate() {
                assert!(tracks.alive[t][k], "track {k} lost at frame {t}");
                let p = tracks.points[t][k];
                let error =
                    ((p[0] - q[0] - shift[0]).powi(2) + (p[1] - q[1] - shift[1]).powi(2)).sqrt();
                assert!(error < 0.05, "frame {t} track {k}: error {error} px");
            }
        }
    }

    #[test]
    fn flat_pixels_are_not_queried_and_masks_stop_tracks() {
        let flat = grey_mat(&RgbImage::from_pixel(40, 30, image::Rgb([90, 90, 90]))).expect("grey");
        let mask = GrayImage::from_pixel(40, 30, image::Luma([255]));
        assert!(
            query_pixels(&flat, &mask, &TrackOptions::default())
                .expect("queries")
                .is_empty()
        );

        let frames: Vec<Mat> = (0..2)
            .map(|_| grey_mat(&textured(96, 80, [0.0, 0.0])).expect("grey"))
            .collect();
        let empty = GrayImage::new(96, 80);
        let masks = vec![mask_full(), empty];
        let tracks = track_points(
            &frames,
            Some(&masks),
            &[[48.5, 40.5]],
            &TrackOptions::default(),
        )
        .expect("tracking");
        assert!(tracks.alive[0][0] && !tracks.alive[1][0]);
        // No queries (a mask without texture): empty tracks, no OpenCV error.
        let none =
            track_points(&frames, Some(&masks), &[], &TrackOptions::default()).expect("empty");
        assert_eq!((none.points.len(), none.len()), (2, 0));
    }

    /// Regression (a toy capture at 5.12 mm): frame-to-frame flow on
    /// noisy frames random-walks away from the surface point; the frame-0
    /// anchor keeps the last frame as accurate as the first step, and the
    /// warped window, needless on a plain shift, does not take over.
    #[test]
    fn anchoring_to_the_first_frame_stops_drift() {
        const FRAMES: usize = 60;
        const STEP_PX: [f32; 2] = [0.37, -0.21];
        const NOISE_GREY: f32 = 20.0;
        let mut noise = noise_source(0x9e37_79b9_7f4a_7c15);
        let frames: Vec<Mat> = (0..FRAMES)
            .map(|t| {
                let shift = [STEP_PX[0] * t as f32, STEP_PX[1] * t as f32];
                let mut image = textured(128, 96, shift);
                for p in image.pixels_mut() {
                    let g = (f32::from(p[0]) + 2.0 * NOISE_GREY * noise()).clamp(0.0, 255.0) as u8;
                    *p = image::Rgb([g, g, g]);
                }
                grey_mat(&image).expect("grey")
            })
            .collect();
        let mask = GrayImage::from_pixel(128, 96, image::Luma([255]));
        let base = TrackOptions {
            queries: 40,
            edge_margin_px: 24,
            forward_backward_px: 2.0,
            ..TrackOptions::default()
        };
        let queries = query_pixels(&frames[0], &mask, &base).expect("queries");
        let last_frame_error = |options: &TrackOptions| {
            last_frame_median_error(&frames, &queries, options, |q, t| {
                [q[0] + STEP_PX[0] * t as f32, q[1] + STEP_PX[1] * t as f32]
            })
        };
        let sequential = last_frame_error(&TrackOptions {
            anchor_px: 0.0,
            ..base.clone()
        });
        let anchored = last_frame_error(&TrackOptions {
            affine_interior: 2.0,
            ..base.clone()
        });
        let warped = last_frame_error(&base);
        eprintln!(
            "last-frame median error: anchored {anchored} px, warped {warped} px, sequential {sequential} px"
        );
        assert!(
            anchored < 0.5 * sequential,
            "anchored {anchored} px vs sequential {sequential} px"
        );
        // A plain shift leaves the warp near the identity: the translation
        // anchor mostly stands (the warp everywhere gave 0.20 px).
        assert!(
            warped < 1.3 * anchored,
            "warped {warped} px vs anchored {anchored} px"
        );
    }

    /// A noisy texture turning 0.6° a frame about the image centre (30°
    /// in all) while its light dims by a quarter: translation windows stop
    /// matching frame 0 within a few frames and keyframes chain their
    /// errors; the warped frame-0 window keeps the last frame close.
    #[test]
    fn a_turning_dimming_texture_stays_anchored_to_its_first_frame() {
        const FRAMES: usize = 51;
        const TURN_DEG: f32 = 0.6;
        const NOISE_GREY: f32 = 12.0;
        let (w, h) = (128u32, 112u32);
        let centre = [w as f32 / 2.0, h as f32 / 2.0];
        let mut noise = noise_source(0x2545_f491_4f6c_dd1d);
        let turned = |p: [f32; 2], t: usize| {
            let (sin, cos) = (TURN_DEG * t as f32).to_radians().sin_cos();
            let d = [p[0] - centre[0], p[1] - centre[1]];
            [
                centre[0] + cos * d[0] - sin * d[1],
                centre[1] + sin * d[0] + cos * d[1],
            ]
        };
        let frames: Vec<Mat> = (0..FRAMES)
            .map(|t| {
                let light = 1.0 - 0.25 * t as f32 / (FRAMES - 1) as f32;
                let image = RgbImage::from_fn(w, h, |x, y| {
                    // The texture point seen at pixel centre (x, y): turned back.
                    let (sin, cos) = (TURN_DEG * t as f32).to_radians().sin_cos();
                    let d = [x as f32 + 0.5 - centre[0], y as f32 + 0.5 - centre[1]];
                    let (u, v) = (cos * d[0] + sin * d[1], -sin * d[0] + cos * d[1]);
                    let value = 128.0
                        + 40.0 * (0.31 * u + 0.17 * v).sin()
                        + 35.0 * (0.23 * u - 0.29 * v + 1.0).sin()
                        + 30.0 * (0.41 * u + 0.05 * v + 2.0).cos();
                    let g = (light * value + 2.0 * NOISE_GREY * noise()).clamp(0.0, 255.0) as u8;
                    image::Rgb([g, g, g])
                });
                grey_mat(&image).expect("grey")
            })
            .collect();
        let mask = GrayImage::from_pixel(w, h, image::Luma([255]));
        let base = TrackOptions {
            queries: 40,
            edge_margin_px: 36,
            forward_backward_px: 2.0,
            ..TrackOptions::default()
        };
        let queries = query_pixels(&frames[0], &mask, &base).expect("queries");
        let last_frame_error =
            |options: &TrackOptions| last_frame_median_error(&frames, &queries, options, turned);
        let translation_only = last_frame_error(&TrackOptions {
            affine_residual: 0.0,
            ..base.clone()
        });
        let warped_where_missed = last_frame_error(&TrackOptions {
            affine_interior: 2.0,
            ..base.clone()
        });
        let warped = last_frame_error(&base);
        eprintln!(
            "last-frame median error: warped {warped} px, warped where translation missed \
             {warped_where_missed} px, translation only {translation_only} px"
        );
        assert!(
            warped_where_missed < 0.6 * translation_only,
            "warped where missed {warped_where_missed} px vs translation only {translation_only} px"
        );
        assert!(
            warped < 0.8 * warped_where_missed,
            "warped {warped} px vs warped where missed {warped_where_missed} px"
        );
    }

    /// Seeded uniform noise in [-0.5, 0.5) (xorshift).
    fn noise_source(mut state: u64) -> impl FnMut() -> f32 {
        move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        }
    }

    /// The median distance at the last frame between the surviving tracks
    /// and where `truth(query, t)` says their points are; most must survive.
    fn last_frame_median_error(
        frames: &[Mat],
        queries: &[[f32; 2]],
        options: &TrackOptions,
        truth: impl Fn([f32; 2], usize) -> [f32; 2],
    ) -> f32 {
        let tracks = track_points(frames, None, queries, options).expect("tracking");
        let t = frames.len() - 1;
        let mut errors: Vec<f32> = queries
            .iter()
            .enumerate()
            .filter(|&(k, _)| tracks.alive[t][k])
            .map(|(k, &q)| {
                let want = truth(q, t);
                let p = tracks.points[t][k];
                ((p[0] - want[0]).powi(2) + (p[1] - want[1]).powi(2)).sqrt()
            })
            .collect();
        assert!(errors.len() >= queries.len() / 2, "most tracks survive");
        errors.sort_by(f32::total_cmp);
        errors[errors.len() / 2]
    }

    fn mask_full() -> GrayImage {
        GrayImage::from_pixel(96, 80, image::Luma([255]))
    }
}
