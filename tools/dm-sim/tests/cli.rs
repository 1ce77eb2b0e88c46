//! `dm-sim` from the command line: a rollout of a small scene,
//! and clear errors naming the file and field for a corrupted bundle.

use dm_synth::{Preset, SynthConfig};
use std::path::Path;
use std::process::Command;

fn tiny_scene(dir: &Path) -> std::path::PathBuf {
    let config = SynthConfig::tiny(Preset::Rope, 5);
    let out = dir.join("scene");
    dm_synth::generate(
        &config,
        &out,
        &dir.join("scene.truth.json"),
        &mut |_, _, _| {},
    )
    .expect("scene generates");
    out
}

fn run_sim(scene: &Path, out: &Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_dm-sim"))
        .arg(scene)
        .arg("--out")
        .arg(out)
        .output()
        .expect("dm-sim runs")
}

#[test]
fn sim_rolls_out_and_summarises() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = tiny_scene(dir.path());
    let out = dir.path().join("sim");
    let result = run_sim(&scene, &out);
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).expect("summary"))
            .expect("json");
    for split in ["train", "test"] {
        let track = summary["track_error_m"][split]
            .as_f64()
            .expect("track error");
        assert!(
            track.is_finite() && track < 0.2,
            "{split} track error {track}"
        );
    }
    assert_eq!(summary["frames"], 14);
    assert!(out.join("preview.png").is_file());
    let rollout: ndarray::Array3<f32> =
        ndarray_npy::read_npy(out.join("rollout.npy")).expect("rollout npy");
    assert_eq!(rollout.shape()[0], 14);
    assert!(rollout.iter().all(|v| v.is_finite()));
}

#[test]
fn sim_names_file_and_field_of_a_corrupted_bundle() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = tiny_scene(dir.path());
    let points = scene.join("tracks/object_points.npy");
    let bytes = std::fs::read(&points).expect("read");
    std::fs::write(&points, &bytes[..bytes.len() - 7]).expect("truncate");
    let out = dir.path().join("sim");
    let result = run_sim(&scene, &out);
    assert!(!result.status.success());
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(stderr.contains("object_points.npy"), "{stderr}");
    assert!(!out.join("summary.json").exists());
}
