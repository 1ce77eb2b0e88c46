//! A recorded session as a new scene bundle (docs/bundle.md): the three
//! playground views rendered at half the page resolution (particles
//! over the floor, dm-model's preview renderer, so RGB, depth and masks come
//! from one render), the hands as two one-anchor hands, tracks on
//! farthest-point samples of the surface particles (visible where a view
//! sees them unoccluded) and the first recorded frame's particles. A
//! novel-action rollout users can fit (`dm-fit`) or evaluate on (`dm-eval`).

use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use dm_bundle::{
    BundleMeta, BundleWriter, Category, FirstFrameParticles, HandSpec, Provenance, Tracks, UpAxis,
};
use dm_model::WorldModel;
use dm_model::preview::{HAND_LABEL, OBJECT_LABEL, particle_frame, spec_from_camera};
use dm_mpm::MaterialBounds;
use dm_mpm::neighbors::farthest_point_sampling;
use dm_view::Camera;
use nalgebra::Point3;
use ndarray::{Array2, Array3};

use crate::PlayError;
use crate::scene::SceneView;
use crate::session::{Body, HAND_COUNT, Recording};

/// Tracked surface points written per recording.
pub const RECORD_TRACKS: usize = 400;
/// Recorded images are this fraction of the page's main-view size.
const RECORD_IMAGE_SCALE: f64 = 0.5;

/// Writes `recording` as a bundle `play_<unix seconds>` under `dir`
/// (atomically: a temporary directory renamed into place) and returns its path.
pub fn write_recording(
    dir: &Path,
    model: &WorldModel,
    body: &Body,
    view: &SceneView,
    recording: &Recording,
    frame_dt: f64,
) -> Result<PathBuf, PlayError> {
    let frames = recording.positions.len();
    if frames < 2 {
        return Err(PlayError::Recording(format!(
            "only {frames} frame recorded; record at least 2"
        )));
    }
    std::fs::create_dir_all(dir).map_err(|source| PlayError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let stamp = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let mut out = dir.join(format!("play_{stamp}"));
    let mut k = 1;
    while out.exists() {
        out = dir.join(format!("play_{stamp}_{k}"));
        k += 1;
    }

    let cameras: Vec<Camera> = view
        .cameras
        .iter()
        .map(|c| {
            let s = RECORD_IMAGE_SCALE * f64::from(view.cameras[0].width) / f64::from(c.width);
            Camera {
                width: (f64::from(c.width) * s).round() as u32,
                height: (f64::from(c.height) * s).round() as u32,
                fx: c.fx * s,
                fy: c.fy * s,
                cx: c.cx * s,
                cy: c.cy * s,
                world_to_camera: c.world_to_camera,
            }
        })
        .collect();
    let specs = cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let name = ["main", "novel1", "novel2"]
                .get(i)
                .map_or(format!("cam{i}"), |n| n.to_string());
            spec_from_camera(name, c)
        })
        .collect();
    let mut meta = BundleMeta::new(frames, 1.0 / frame_dt, category_of(model, body), specs);
    meta.up_axis = up_axis(view.up)?;
    meta.floor_height_m = view.floor_height;
    meta.hands = (0..HAND_COUNT)
        .map(|k| HandSpec {
            name: format!("hand{}", k + 1),
            anchor_range: [k, k + 1],
        })
        .collect();
    meta.provenance = Provenance {
        tool: format!("dm-play {}", env!("CARGO_PKG_VERSION")),
        source: "interactive playground session (simulated by the fitted model)".into(),
        created_unix_s: stamp,
        notes: "rendered particles, noise-free; hands are the playground's anchors".into(),
    };

    let surface: Vec<[f64; 3]> = recording.positions[0][..body.surface_count]
        .iter()
        .map(|p| p.map(f64::from))
        .collect();
    let tracked = farthest_point_sampling(&surface, RECORD_TRACKS.min(surface.len()));
    let radius = body.splat_radius;
    let tolerance = 1.5 * view.particle_spacing + 0.004;
    let mut writer = BundleWriter::create(&out, meta)?;
    let n = tracked.len();
    let mut tracks = Tracks {
        object_points: Array3::zeros((frames, n, 3)),
        object_visibility: Array2::from_elem((frames, n), false),
        object_motion_valid: Array2::from_elem((frames, n), false),
        hand_points: Array3::zeros((frames, HAND_COUNT, 3)),
        hand_visibility: Array2::from_elem((frames, HAND_COUNT), true),
    };
    for t in 0..frames {
        let positions = &recording.positions[t];
        let anchors: Vec<[f32; 3]> = recording.hands[t]
            .iter()
            .map(|h| h.map(|c| c as f32))
            .collect();
        for (c, camera) in cameras.iter().enumerate() {
            let frame = particle_frame(
                camera,
                positions,
                &body.colors,
                radius,
                &anchors,
                view.up,
                view.floor_height,
            );
            for (k, &i) in tracked.iter().enumerate() {
                let p = positions[i].map(f64::from);
                if frame.is_unoccluded(camera, &Point3::from(p), tolerance) {
                    tracks.object_visibility[[t, k]] = true;
                }
            }
            writer.write_frame_images(
                c,
                t,
                &frame.to_rgb8(),
                &frame.depth,
                &frame.mask(OBJECT_LABEL),
                &frame.mask(HAND_LABEL),
            )?;
        }
        for (k, &i) in tracked.iter().enumerate() {
            for a in 0..3 {
                tracks.object_points[[t, k, a]] = positions[i][a];
            }
            tracks.object_motion_valid[[t, k]] = tracks.object_visibility[[t, k]]
                && (t == 0 || tracks.object_visibility[[t - 1, k]]);
        }
        for (j, a) in anchors.iter().enumerate() {
            for d in 0..3 {
                tracks.hand_points[[t, j, d]] = a[d];
            }
        }
    }
    writer.write_tracks(&tracks)?;
    let first = &recording.positions[0];
    let arrays = |range: std::ops::Range<usize>| {
        let mut points = Array2::<f32>::zeros((range.len(), 3));
        let mut colors = Array2::<f32>::zeros((range.len(), 3));
        for (r, i) in range.enumerate() {
            for a in 0..3 {
                points[[r, a]] = first[i][a];
                colors[[r, a]] = body.colors[i][a];
            }
        }
        (points, colors)
    };
    let (surface_points, surface_colors) = arrays(0..body.surface_count);
    let (interior_points, interior_colors) = arrays(body.surface_count..first.len());
    writer.write_particles(&FirstFrameParticles {
        surface_points,
        surface_colors,
        interior_points,
        interior_colors,
    })?;
    writer.finish()?;
    Ok(out)
}

/// The bundle category of a model: volumetric bounds mean a volumetric
/// object; thin objects are linear when their second-longest extent is
/// under a third of the longest, else planar.
fn category_of(model: &WorldModel, body: &Body) -> Category {
    if model.bounds == MaterialBounds::VOLUMETRIC {
        return Category::Volumetric;
    }
    let (lo, hi) = crate::session::bounds(&body.particles);
    let mut extents: Vec<f64> = (0..3).map(|a| hi[a] - lo[a]).collect();
    extents.sort_by(|a, b| b.total_cmp(a));
    if extents[1] < extents[0] / 3.0 {
        Category::Linear
    } else {
        Category::Planar
    }
}

fn up_axis(up: [f64; 3]) -> Result<UpAxis, PlayError> {
    let axes = [
        ([1.0, 0.0, 0.0], UpAxis::PosX),
        ([-1.0, 0.0, 0.0], UpAxis::NegX),
        ([0.0, 1.0, 0.0], UpAxis::PosY),
        ([0.0, -1.0, 0.0], UpAxis::NegY),
        ([0.0, 0.0, 1.0], UpAxis::PosZ),
        ([0.0, 0.0, -1.0], UpAxis::NegZ),
    ];
    axes.iter()
        .find(|(v, _)| (0..3).all(|a| (v[a] - up[a]).abs() < 1e-6))
        .map(|(_, axis)| *axis)
        .ok_or_else(|| {
            PlayError::Recording(format!(
                "the model's up direction {up:?} is not a world axis; bundles need one"
            ))
        })
}
