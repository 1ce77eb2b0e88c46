//! The plan's pictures: each frame the planned rollout (left) beside what
//! the plant did (right), both with the goal points in red and the hands,
//! seen by a bundle camera over the floor; PNG frames for an MP4.

use std::path::{Path, PathBuf};

use dm_bundle::write_file_atomic;
use dm_view::{RenderOptions, Splat, render, side_by_side};

use crate::PlanError;
use crate::run::RunResult;

const GOAL_COLOR: [f32; 3] = [0.9, 0.1, 0.1];
const PLANNED_COLOR: [f32; 3] = [0.25, 0.45, 0.85];
const EXECUTED_COLOR: [f32; 3] = [0.95, 0.6, 0.2];
const HAND_COLOR: [f32; 3] = [0.86, 0.66, 0.55];

fn splats(
    points: &[[f64; 3]],
    radius: f32,
    color: [f32; 3],
    label: u8,
) -> impl Iterator<Item = Splat> + '_ {
    points.iter().map(move |p| Splat {
        position: p.map(|c| c as f32),
        radius,
        color,
        label,
    })
}

/// Frame `t` of `frames`, or its last frame when shorter (no copy).
fn at_frame(frames: &[Vec<[f64; 3]>], t: usize) -> &[[f64; 3]] {
    frames.get(t).or(frames.last()).map_or(&[], Vec::as_slice)
}

/// Writes `video/frame_NNNNN.png` for every frame and returns the frame
/// directory.
pub fn write_frames(out: &Path, camera: usize, result: &RunResult) -> Result<PathBuf, PlanError> {
    let (bundle, radius) = (&result.bundle, result.splat_radius);
    let dir = out.join("video");
    std::fs::create_dir_all(&dir).map_err(|e| PlanError::File {
        path: dir.clone(),
        problem: format!("creating the directory: {e}"),
    })?;
    if camera >= bundle.meta.cameras.len() {
        return Err(PlanError::InvalidOption {
            option: "--camera".into(),
            problem: format!(
                "camera {camera} does not exist; the bundle has {}",
                bundle.meta.cameras.len()
            ),
        });
    }
    let view = dm_model::preview::bundle_camera(bundle, camera)?;
    let options = RenderOptions::studio(
        bundle.meta.up_axis.unit_vector(),
        bundle.meta.floor_height_m,
    );
    for t in 0..result.executed.len().max(result.planned.len()) {
        let hands = at_frame(&result.hands, t);
        let panel = |points: &[[f64; 3]], color| {
            let scene: Vec<Splat> = splats(points, radius, color, 1)
                .chain(splats(&result.goal.points, 0.5 * radius, GOAL_COLOR, 2))
                .chain(splats(hands, 0.009, HAND_COLOR, 3))
                .collect();
            render(&view, &scene, &options).to_rgb8()
        };
        let planned = at_frame(&result.planned, t);
        let executed = at_frame(&result.executed, t);
        let image = side_by_side(
            &[
                panel(planned, PLANNED_COLOR),
                panel(executed, EXECUTED_COLOR),
            ],
            &[],
        );
        let path = dir.join(dm_appearance::clip::frame_file_name(t));
        write_file_atomic(&path, |tmp| {
            image
                .save_with_format(tmp, image::ImageFormat::Png)
                .map_err(std::io::Error::other)
        })?;
    }
    Ok(dir)
}
