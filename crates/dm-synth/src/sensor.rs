//! The sensor model: a calibrated 3-camera RGB-D rig, object and hand
//! masks, point trackers and a hand tracker, each with realistic errors.

use crate::truth::{FPS, GroundTruth};
use crate::{Progress, SynthConfig, SynthError, splitmix};
use dm_bundle::{
    BundleMeta, BundleWriter, CameraSpec, FirstFrameParticles, HandSpec, Provenance, Tracks,
};
use dm_mpm::neighbors::farthest_point_sampling;
use dm_view::{Camera, RenderOptions, Splat, add_sensor_noise, render};
use nalgebra::{Point3, Vector3};
use ndarray::{Array2, Array3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

pub const OBJECT_LABEL: u8 = 1;
pub const HAND_LABEL: u8 = 2;
const SKIN: [f32; 3] = [0.86, 0.66, 0.55];

/// Sensor error magnitudes (documented in docs/bundle.md's synthetic notes).
#[derive(Clone, Copy, Debug)]
pub struct SensorNoise {
    /// Depth noise σ = a + b z², metres (structured-light-like growth with range).
    pub depth_sigma_a: f64,
    pub depth_sigma_b: f64,
    /// Fraction of depth pixels lost at random.
    pub depth_dropout: f64,
    /// Depth pixels across a jump larger than this (m) are lost half the time.
    pub depth_edge_jump: f32,
    /// RGB noise amplitude in [0, 1].
    pub rgb_noise: f32,
    /// Object track noise σ (m) per frame, and a per-track constant bias σ.
    pub track_sigma: f64,
    pub track_bias_sigma: f64,
    /// Probability that a visible track is dropped in a frame.
    pub track_dropout: f64,
    /// Hand anchor noise σ (m) and dropout probability.
    pub hand_sigma: f64,
    pub hand_dropout: f64,
    /// First-frame particle noise σ (m).
    pub particle_sigma: f64,
}

impl Default for SensorNoise {
    fn default() -> Self {
        Self {
            depth_sigma_a: 0.001,
            depth_sigma_b: 0.0025,
            depth_dropout: 0.015,
            depth_edge_jump: 0.03,
            rgb_noise: 0.02,
            track_sigma: 0.0015,
            track_bias_sigma: 0.001,
            track_dropout: 0.03,
            hand_sigma: 0.003,
            hand_dropout: 0.1,
            particle_sigma: 0.001,
        }
    }
}

/// Three cameras around the object at varied azimuths, 40° above it.
pub fn rig(truth: &GroundTruth, width: u32, height: u32, seed: u64) -> Vec<Camera> {
    let (lo, hi) = truth.preset.bounds();
    let target = Point3::new(
        0.5 * (lo[0] + hi[0]),
        0.5 * (lo[1] + hi[1]),
        0.35 * hi[2] + 0.03,
    );
    let mut rng = ChaCha8Rng::seed_from_u64(splitmix(seed ^ 0xca3e));
    let radius = 0.85;
    [25.0, 145.0, 265.0]
        .iter()
        .map(|&azimuth: &f64| {
            let az = (azimuth + 16.0 * (rng.random::<f64>() - 0.5)).to_radians();
            let el = (38.0 + 8.0 * (rng.random::<f64>() - 0.5)).to_radians();
            let eye = Point3::new(
                target.x + radius * el.cos() * az.cos(),
                target.y + radius * el.cos() * az.sin(),
                target.z + radius * el.sin(),
            );
            Camera::look_at(eye, target, Vector3::z(), width, height, 50.0)
        })
        .collect()
}

fn camera_spec(name: String, c: &Camera) -> CameraSpec {
    CameraSpec {
        name,
        width: c.width,
        height: c.height,
        fx: c.fx,
        fy: c.fy,
        cx: c.cx,
        cy: c.cy,
        world_to_camera: c.to_matrix_4x4(),
        axes: dm_bundle::CAMERA_AXES_OPENCV.to_string(),
    }
}

/// Splats of the hands: a fingertip ball per anchor, a palm above them and
/// a forearm reaching up and outwards.
fn hand_splats(anchors: &[[f64; 3]], hands: &[crate::actions::HandScript]) -> Vec<Splat> {
    let mut splats = Vec::new();
    let mut start = 0;
    for hand in hands {
        let own = &anchors[start..start + hand.anchors.len()];
        start += hand.anchors.len();
        let n = own.len() as f64;
        let c = [0, 1, 2].map(|a| own.iter().map(|p| p[a]).sum::<f64>() / n);
        for p in own {
            splats.push(Splat {
                position: p.map(|v| v as f32),
                radius: 0.009,
                color: SKIN,
                label: HAND_LABEL,
            });
        }
        let outward = {
            let r = (c[0] * c[0] + c[1] * c[1]).sqrt().max(1e-6);
            [c[0] / r, c[1] / r]
        };
        for (k, radius) in [(0.0, 0.028), (1.0, 0.024), (2.0, 0.022), (3.0, 0.022)] {
            let step: f64 = 0.035;
            splats.push(Splat {
                position: [
                    (c[0] + outward[0] * step * k) as f32,
                    (c[1] + outward[1] * step * k) as f32,
                    (c[2] + 0.035 + step * 1.2 * k) as f32,
                ],
                radius,
                color: SKIN,
                label: HAND_LABEL,
            });
        }
    }
    splats
}

/// Depth as a sensor measures it: noise growing with range, random
/// dropouts, lost pixels across depth edges.
fn measured_depth(
    depth: &[f32],
    width: usize,
    noise: &SensorNoise,
    rng: &mut ChaCha8Rng,
) -> Vec<f32> {
    let unit = Normal::new(0.0, 1.0).expect("unit normal is valid");
    let height = depth.len() / width;
    let mut out = depth.to_vec();
    for y in 0..height {
        for x in 0..width {
            let i = y * width + x;
            let z = depth[i];
            if !z.is_finite() {
                out[i] = f32::NAN;
                continue;
            }
            let jump = [(1i64, 0i64), (0, 1)].iter().any(|&(dx, dy)| {
                let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                nx < width as i64
                    && ny < height as i64
                    && (depth[ny as usize * width + nx as usize] - z).abs() > noise.depth_edge_jump
            });
            let lost =
                rng.random::<f64>() < noise.depth_dropout || (jump && rng.random::<f64>() < 0.5);
            let sigma = noise.depth_sigma_a + noise.depth_sigma_b * (z as f64) * (z as f64);
            out[i] = if lost {
                f32::NAN
            } else {
                z + (sigma * unit.sample(rng)) as f32
            };
        }
    }
    out
}

/// Receives the raw capture while the bundle is rendered: what the rig's
/// cameras record (noisy colour, measured depth), nothing else. dm-synth's
/// tool writes it as a capture directory with `dm-synth-capture`.
pub trait CaptureSink {
    /// Called once before any frame, with the bundle's metadata (cameras,
    /// frame rate, frame count, up axis, floor).
    fn start(&mut self, meta: &BundleMeta) -> Result<(), SynthError>;
    /// Colour and depth (metres, NaN = no measurement) of one camera and frame.
    fn frame(
        &mut self,
        camera: usize,
        frame: usize,
        rgb: &image::RgbImage,
        depth_m: &[f32],
    ) -> Result<(), SynthError>;
}

/// Renders every camera and frame and writes the bundle (and the raw
/// capture to `capture`, when given).
pub fn write_bundle(
    config: &SynthConfig,
    truth: &GroundTruth,
    out: &std::path::Path,
    mut capture: Option<&mut dyn CaptureSink>,
    progress: Progress<'_>,
) -> Result<(), SynthError> {
    let mut noise = SensorNoise::default();
    if config.exact_tracks {
        noise.track_sigma = 0.0;
        noise.track_bias_sigma = 0.0;
        noise.track_dropout = 0.0;
    }
    let frames = truth.frames.len();
    let cameras = rig(truth, config.width, config.height, config.seed);
    let specs: Vec<CameraSpec> = cameras
        .iter()
        .enumerate()
        .map(|(i, c)| camera_spec(format!("cam{i}"), c))
        .collect();
    let mut meta = BundleMeta::new(frames, FPS, config.preset.category(), specs);
    meta.provenance = Provenance {
        tool: format!("dm-synth {}", env!("CARGO_PKG_VERSION")),
        source: format!("synthetic preset {}", config.preset.name()),
        created_unix_s: 0,
        notes: "synthetic 3-camera RGB-D capture; ground truth is kept outside the bundle".into(),
    };
    let mut start = 0;
    meta.hands = truth
        .hands
        .iter()
        .map(|h| {
            let range = [start, start + h.anchors.len()];
            start += h.anchors.len();
            HandSpec {
                name: h.name.clone(),
                anchor_range: range,
            }
        })
        .collect();
    if let Some(sink) = capture.as_deref_mut() {
        sink.start(&meta)?;
    }
    let mut writer = BundleWriter::create(out, meta)?;

    // Object splats: surface particles coloured by the texture at rest.
    let surface: Vec<usize> = (0..truth.cloud.len())
        .filter(|&i| truth.cloud.on_surface[i])
        .collect();
    let albedo: Vec<[f32; 3]> = surface
        .iter()
        .map(|&i| config.preset.albedo(truth.cloud.positions[i]))
        .collect();
    let radius = (0.85 * truth.cloud.spacing) as f32;
    let options = RenderOptions::studio([0.0, 0.0, 1.0], 0.0);

    // Tracked points: farthest-point samples of the surface at frame 0.
    // Exact tracks follow points on the rendered skin instead (see
    // `skin_tracks`), sampled among particles whose skin point is visible
    // from outside.
    let (candidates, skin) = if config.exact_tracks {
        let (ids, offsets) = outer_skin(truth, radius);
        (ids, Some(offsets))
    } else {
        (surface.clone(), None)
    };
    let candidate_rest: Vec<[f64; 3]> = candidates
        .iter()
        .map(|&i| truth.frames[0][i].map(f64::from))
        .collect();
    let chosen = farthest_point_sampling(&candidate_rest, config.tracks);
    let tracked: Vec<usize> = chosen.iter().map(|&s| candidates[s]).collect();
    let track_positions: Vec<Vec<[f64; 3]>> = match &skin {
        Some(offsets) => {
            let offsets: Vec<[f64; 3]> = chosen.iter().map(|&s| offsets[s]).collect();
            skin_tracks(truth, &tracked, &offsets)
        }
        None => truth
            .frames
            .iter()
            .map(|frame| tracked.iter().map(|&i| frame[i].map(f64::from)).collect())
            .collect(),
    };
    let n_tracks = tracked.len();
    let mut visible_any = Array2::<bool>::from_elem((frames, n_tracks), false);

    let mut rng = ChaCha8Rng::seed_from_u64(splitmix(config.seed ^ 0x5e45));
    let visibility_tolerance = 1.5 * truth.cloud.spacing + 0.004;
    for t in 0..frames {
        let mut splats: Vec<Splat> = surface
            .iter()
            .zip(&albedo)
            .map(|(&i, &color)| Splat {
                position: truth.frames[t][i],
                radius,
                color,
                label: crate::sensor::OBJECT_LABEL,
            })
            .collect();
        splats.extend(hand_splats(&truth.anchors[t], &truth.hands));
        for (c, camera) in cameras.iter().enumerate() {
            let mut frame = render(camera, &splats, &options);
            for (k, p) in track_positions[t].iter().enumerate() {
                if frame.is_unoccluded(camera, &Point3::new(p[0], p[1], p[2]), visibility_tolerance)
                {
                    visible_any[[t, k]] = true;
                }
            }
            let depth = measured_depth(&frame.depth, frame.width as usize, &noise, &mut rng);
            let object_mask = frame.mask(OBJECT_LABEL);
            let hand_mask = frame.mask(HAND_LABEL);
            add_sensor_noise(
                &mut frame,
                noise.rgb_noise,
                splitmix(config.seed ^ ((t * 8 + c) as u64)),
            );
            let rgb = frame.to_rgb8();
            if let Some(sink) = capture.as_deref_mut() {
                sink.frame(c, t, &rgb, &depth)?;
            }
            writer.write_frame_images(c, t, &rgb, &depth, &object_mask, &hand_mask)?;
        }
        progress("rendering", t + 1, frames);
    }

    writer.write_tracks(&observed_tracks(
        truth,
        &track_positions,
        &visible_any,
        &noise,
        config.exact_hands,
        &mut rng,
    ))?;
    writer.write_particles(&first_frame_particles(config, truth, &noise, &mut rng))?;
    writer.finish()?;
    Ok(())
}

/// Noisy object tracks with visibility (seen by a camera and not dropped)
/// and motion validity (visible now and in the previous frame). Where a
/// point is not visible the last observation is held. With `exact_hands`
/// the hand tracks are the recorded anchors themselves, every frame seen;
/// the noise is still drawn so the rest of the scene stays the same.
fn observed_tracks(
    truth: &GroundTruth,
    track_positions: &[Vec<[f64; 3]>],
    visible_any: &Array2<bool>,
    noise: &SensorNoise,
    exact_hands: bool,
    rng: &mut ChaCha8Rng,
) -> Tracks {
    let frames = truth.frames.len();
    let n = track_positions[0].len();
    let unit = Normal::new(0.0, 1.0).expect("unit normal is valid");
    let bias: Vec<[f64; 3]> = (0..n)
        .map(|_| [0, 1, 2].map(|_| noise.track_bias_sigma * unit.sample(rng)))
        .collect();
    let mut points = Array3::<f32>::zeros((frames, n, 3));
    let mut visibility = Array2::<bool>::from_elem((frames, n), false);
    let mut motion_valid = Array2::<bool>::from_elem((frames, n), false);
    for t in 0..frames {
        for k in 0..n {
            let truth_p = track_positions[t][k];
            let seen = visible_any[[t, k]] && rng.random::<f64>() >= noise.track_dropout;
            let measured: [f64; 3] =
                [0, 1, 2].map(|a| truth_p[a] + bias[k][a] + noise.track_sigma * unit.sample(rng));
            let value = if seen || t == 0 {
                measured
            } else {
                [0, 1, 2].map(|a| f64::from(points[[t - 1, k, a]]))
            };
            for a in 0..3 {
                points[[t, k, a]] = value[a] as f32;
            }
            visibility[[t, k]] = seen;
            motion_valid[[t, k]] = seen && (t == 0 || visibility[[t - 1, k]]);
        }
    }
    let m = truth.recorded_anchors[0].len();
    let mut hand_points = Array3::<f32>::zeros((frames, m, 3));
    let mut hand_visibility = Array2::<bool>::from_elem((frames, m), false);
    for t in 0..frames {
        for j in 0..m {
            let seen = t == 0 || rng.random::<f64>() >= noise.hand_dropout;
            for a in 0..3 {
                let exact = truth.recorded_anchors[t][j][a];
                let observed = if seen {
                    (exact + noise.hand_sigma * unit.sample(rng)) as f32
                } else {
                    hand_points[[t - 1, j, a]]
                };
                hand_points[[t, j, a]] = if exact_hands { exact as f32 } else { observed };
            }
            hand_visibility[[t, j]] = seen || exact_hands;
        }
    }
    Tracks {
        object_points: points,
        object_visibility: visibility,
        object_motion_valid: motion_valid,
        hand_points,
        hand_visibility,
    }
}

/// What a reconstruction would give at frame 0: a random subset of the
/// truth particles with noise, split into surface and interior, coloured
/// by the texture.
fn first_frame_particles(
    config: &SynthConfig,
    truth: &GroundTruth,
    noise: &SensorNoise,
    rng: &mut ChaCha8Rng,
) -> FirstFrameParticles {
    let unit = Normal::new(0.0, 1.0).expect("unit normal is valid");
    let n = truth.cloud.len();
    let keep = config.bundle_particles.min(n);
    // Partial Fisher-Yates: a seeded uniform subset.
    let mut ids: Vec<usize> = (0..n).collect();
    for i in 0..keep {
        let j = rng.random_range(i..n);
        ids.swap(i, j);
    }
    let mut chosen = ids[..keep].to_vec();
    chosen.sort_unstable();
    let (surface, interior): (Vec<usize>, Vec<usize>) =
        chosen.into_iter().partition(|&i| truth.cloud.on_surface[i]);
    let mut to_arrays = |ids: &[usize]| {
        let mut points = Array2::<f32>::zeros((ids.len(), 3));
        let mut colors = Array2::<f32>::zeros((ids.len(), 3));
        for (r, &i) in ids.iter().enumerate() {
            let c = config.preset.albedo(truth.cloud.positions[i]);
            for a in 0..3 {
                points[[r, a]] = (f64::from(truth.frames[0][i][a])
                    + noise.particle_sigma * unit.sample(rng))
                    as f32;
                colors[[r, a]] = c[a];
            }
        }
        (points, colors)
    };
    let (surface_points, surface_colors) = to_arrays(&surface);
    let (interior_points, interior_colors) = to_arrays(&interior);
    FirstFrameParticles {
        surface_points,
        surface_colors,
        interior_points,
        interior_colors,
    }
}

/// Surface particles whose skin point (centre + splat radius along the
/// rest shape's outward normal) lies on the rendered surface — outside
/// every other splat — with that offset.
fn outer_skin(truth: &GroundTruth, radius: f32) -> (Vec<usize>, Vec<[f64; 3]>) {
    let rest = &truth.cloud.positions;
    let index = dm_mpm::neighbors::PointIndex::new(rest);
    let r = f64::from(radius);
    let h = 1e-4;
    let mut ids = Vec::new();
    let mut offsets = Vec::new();
    for i in (0..rest.len()).filter(|&i| truth.cloud.on_surface[i]) {
        let p = rest[i];
        let gradient: [f64; 3] = std::array::from_fn(|a| {
            let (mut plus, mut minus) = (p, p);
            plus[a] += h;
            minus[a] -= h;
            (truth.preset.sdf(plus) - truth.preset.sdf(minus)) / (2.0 * h)
        });
        let norm = (gradient[0].powi(2) + gradient[1].powi(2) + gradient[2].powi(2)).sqrt();
        if norm < 1e-9 {
            continue;
        }
        let offset = gradient.map(|g| r * g / norm);
        let skin = [0, 1, 2].map(|a| p[a] + offset[a]);
        let covered = index.within(&skin, 0.98 * r).iter().any(|&(j, _)| j != i);
        if !covered {
            ids.push(i);
            offsets.push(offset);
        }
    }
    (ids, offsets)
}

/// Neighbours whose rigid fit carries a skin offset along.
const SKIN_NEIGHBOURS: usize = 12;

/// Positions over the clip of skin points `x_i + R_i(t) o_i`, with
/// `R_i(t)` the rotation of the best rigid fit (Kabsch) of the particle's
/// rest neighbourhood to frame t: the offset turns with the material
/// around it, so the point stays on its splat's surface.
fn skin_tracks(truth: &GroundTruth, tracked: &[usize], offsets: &[[f64; 3]]) -> Vec<Vec<[f64; 3]>> {
    use nalgebra::Matrix3;
    let rest = &truth.cloud.positions;
    let index = dm_mpm::neighbors::PointIndex::new(rest);
    let neighbours: Vec<Vec<usize>> = tracked
        .iter()
        .map(|&i| {
            index
                .nearest(&rest[i], SKIN_NEIGHBOURS)
                .into_iter()
                .map(|(j, _)| j)
                .collect()
        })
        .collect();
    truth
        .frames
        .iter()
        .map(|frame| {
            tracked
                .iter()
                .zip(&neighbours)
                .zip(offsets)
                .map(|((&i, ns), o)| {
                    let n = ns.len() as f64;
                    let centre = |pts: &dyn Fn(usize) -> Vector3<f64>| {
                        ns.iter().map(|&j| pts(j)).sum::<Vector3<f64>>() / n
                    };
                    let at_rest = |j: usize| Vector3::from(rest[j]);
                    let now = |j: usize| Vector3::from(frame[j].map(f64::from));
                    let (c0, c1) = (centre(&at_rest), centre(&now));
                    let h: Matrix3<f64> = ns
                        .iter()
                        .map(|&j| (at_rest(j) - c0) * (now(j) - c1).transpose())
                        .sum();
                    let svd = h.svd(true, true);
                    let rotation = match (svd.u, svd.v_t) {
                        (Some(u), Some(v_t)) => {
                            let mut r = v_t.transpose() * u.transpose();
                            if r.determinant() < 0.0 {
                                let mut v = v_t.transpose();
                                v.column_mut(2).neg_mut();
                                r = v * u.transpose();
                            }
                            r
                        }
                        _ => Matrix3::identity(),
                    };
                    let skin = now(i) + rotation * Vector3::from(*o);
                    [skin.x, skin.y, skin.z]
                })
                .collect()
        })
        .collect()
}
