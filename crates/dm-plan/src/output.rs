//! A run's files: actions, rollouts, goal and plan.json.

use std::path::Path;

use dm_bundle::{write_json_atomic, write_npy_file};

use crate::PlanError;
use crate::run::RunResult;

/// Frames of points as planned.npy and executed.npy hold them, (T, N, 3).
pub fn frames_array(frames: &[Vec<[f64; 3]>]) -> ndarray::Array3<f32> {
    let n = frames.first().map_or(0, Vec::len);
    ndarray::Array3::from_shape_fn((frames.len(), n, 3), |(t, i, a)| frames[t][i][a] as f32)
}

/// Hand anchors per frame as actions.npy holds those carried out,
/// (T, H, 3) metres.
pub fn actions_array(hands: &[Vec<[f64; 3]>]) -> ndarray::Array3<f64> {
    let h = hands.first().map_or(0, Vec::len);
    ndarray::Array3::from_shape_fn((hands.len(), h, 3), |(t, i, a)| hands[t][i][a])
}

/// Writes actions.json/.npy, planned.npy, executed.npy, goal.npy and
/// plan.json into `out` (each atomically; plan.json last).
pub fn write_outputs(out: &Path, result: &RunResult) -> Result<(), PlanError> {
    std::fs::create_dir_all(out).map_err(|e| PlanError::File {
        path: out.to_path_buf(),
        problem: format!("creating the directory: {e}"),
    })?;
    let hands = &result.hands;
    write_npy_file(&out.join("actions.npy"), &actions_array(hands))?;
    write_json_atomic(
        &out.join("actions.json"),
        &serde_json::json!({
            "frame_dt_s": result.frame_dt,
            "hands_per_frame": hands,
            "plan": result.record.actions,
        }),
    )?;
    write_npy_file(&out.join("planned.npy"), &frames_array(&result.planned))?;
    write_npy_file(&out.join("executed.npy"), &frames_array(&result.executed))?;
    write_npy_file(
        &out.join("goal.npy"),
        &frames_array(std::slice::from_ref(&result.goal.points)),
    )?;
    write_json_atomic(&out.join("plan.json"), &result.record)?;
    Ok(())
}
