//! `dm-render` from the command line: frames and the MP4
//! (OpenCV) of a tiny scene's fitted splats, and clear errors for bad
//! input.

use dm_appearance::{AppearanceOptions, fit_appearance, save_appearance};
use dm_synth::{Preset, SynthConfig};
use std::path::{Path, PathBuf};
use std::process::Command;

/// A tiny scene, its untrained model and a short splat fit in the model dir.
fn tiny_scene_and_fitted_model(dir: &Path) -> (PathBuf, PathBuf) {
    let scene = dir.join("scene");
    dm_synth::generate(
        &SynthConfig::tiny(Preset::Rope, 5),
        &scene,
        &dir.join("scene.truth.json"),
        &mut |_, _, _| {},
    )
    .expect("scene generates");
    let bundle = dm_bundle::Bundle::open(&scene).expect("bundle");
    let model = dm_model::WorldModel::from_bundle(&bundle, &dm_model::ModelOptions::default())
        .expect("model");
    let model_dir = dir.join("model");
    std::fs::create_dir_all(&model_dir).expect("model dir");
    dm_bundle::write_json_atomic(&model_dir.join("model.json"), &model).expect("model.json");
    let options = AppearanceOptions {
        iterations: 5,
        ..AppearanceOptions::for_cameras(bundle.meta.cameras.len())
    };
    let (gaussians, record) = fit_appearance(&model, &bundle, &options, &mut |_| {}).expect("fit");
    save_appearance(&model_dir, &gaussians, &record).expect("save");
    (scene, model_dir)
}

fn run_render(model: &Path, args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_dm-render"))
        .arg(model)
        .args(args)
        .output()
        .expect("dm-render runs")
}

#[test]
fn render_writes_frames_video_and_rejects_bad_input() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (scene, model) = tiny_scene_and_fitted_model(dir.path());
    let scene_arg = scene.to_str().expect("utf-8 path");

    // Novel view following the rollout, frames 2..5.
    let out = dir.path().join("novel");
    let out_arg = out.to_str().expect("utf-8 path");
    let args = [
        "--bundle", scene_arg, "--view", "novel", "--frames", "2:5", "--out", out_arg,
    ];
    let result = run_render(&model, &args);
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    for t in 2..5 {
        let frame = out.join(format!("frame_{t:05}.png"));
        let image = image_size(&frame);
        assert_eq!(image, (48, 36), "{}", frame.display());
    }
    assert!(!out.join("frame_00001.png").exists());
    assert!(!out.join("frame_00005.png").exists());
    // The MP4: an ISO media file ("ftyp" box) with a video track.
    let mp4 = std::fs::read(out.join("render.mp4")).expect("render.mp4");
    assert!(
        mp4.len() > 100 && &mp4[4..8] == b"ftyp",
        "render.mp4 is not an MP4 file"
    );
    assert!(
        !std::fs::read_dir(&out)
            .expect("out dir")
            .any(|e| e.is_ok_and(|e| e.file_name().to_string_lossy().contains("tmp"))),
        "a temporary file was left behind"
    );

    // Orbit without a bundle: the object at rest, a given number of frames.
    let orbit = dir.path().join("orbit");
    let result = run_render(
        &model,
        &[
            "--view",
            "orbit",
            "--frames",
            "0:4",
            "--no-video",
            "--out",
            orbit.to_str().expect("utf-8"),
        ],
    );
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    assert!(orbit.join("frame_00003.png").is_file());
    // Different viewpoints give different images.
    let a = std::fs::read(orbit.join("frame_00000.png")).expect("frame 0");
    let b = std::fs::read(orbit.join("frame_00002.png")).expect("frame 2");
    assert_ne!(a, b, "orbit frames 0 and 2 are identical");

    let bad = dir.path().join("bad");
    let bad_arg = bad.to_str().expect("utf-8");
    // A camera that does not exist.
    let result = run_render(
        &model,
        &[
            "--bundle",
            scene_arg,
            "--view",
            "train:9",
            "--out",
            bad_arg,
            "--no-video",
        ],
    );
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(!result.status.success());
    assert!(
        stderr.contains("train:9") && stderr.contains("3 cameras"),
        "{stderr}"
    );
    // A view that does not parse; a range past the clip.
    let result = run_render(&model, &["--view", "sideways", "--out", bad_arg]);
    assert!(!result.status.success());
    assert!(String::from_utf8_lossy(&result.stderr).contains("sideways"));
    let result = run_render(
        &model,
        &[
            "--bundle",
            scene_arg,
            "--view",
            "novel",
            "--frames",
            "0:99",
            "--out",
            bad_arg,
            "--no-video",
        ],
    );
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(!result.status.success());
    assert!(
        stderr.contains("--frames") && stderr.contains("14 frames"),
        "{stderr}"
    );
    // A corrupt PLY names the file.
    std::fs::write(
        model.join("gaussians.ply"),
        b"ply\nformat ascii 1.0\nend_header\n",
    )
    .expect("write");
    let result = run_render(&model, &["--view", "novel", "--out", bad_arg, "--no-video"]);
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(!result.status.success());
    assert!(
        stderr.contains("gaussians.ply") && stderr.contains("format ascii"),
        "{stderr}"
    );
    // No splats at all: says how to make them.
    std::fs::remove_file(model.join("gaussians.ply")).expect("remove");
    let result = run_render(&model, &["--view", "novel", "--out", bad_arg]);
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(!result.status.success());
    assert!(stderr.contains("dm-appearance"), "{stderr}");
}

fn image_size(path: &Path) -> (u32, u32) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    // PNG IHDR: width and height are big-endian u32 at bytes 16..24.
    assert!(
        bytes.len() > 24 && &bytes[1..4] == b"PNG",
        "{} is not a PNG",
        path.display()
    );
    let word = |i: usize| u32::from_be_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
    (word(16), word(20))
}
