//! `dm-eval` from the command line: the metrics of a tiny
//! synthetic scene's untrained model, and clear errors for bad input.

use dm_synth::{Preset, SynthConfig};
use std::path::{Path, PathBuf};
use std::process::Command;

/// A tiny scene and its untrained model written as a model directory.
fn tiny_scene_and_model(dir: &Path) -> (PathBuf, PathBuf) {
    let config = SynthConfig::tiny(Preset::Rope, 5);
    let scene = dir.join("scene");
    dm_synth::generate(
        &config,
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
    (scene, model_dir)
}

fn run_eval(model: &Path, scene: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    eval_command(model, scene, out, extra)
        .output()
        .expect("dm-eval runs")
}

fn eval_command(model: &Path, scene: &Path, out: &Path, extra: &[&str]) -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_dm-eval"));
    command
        .arg(model)
        .arg(scene)
        .arg("--out")
        .arg(out)
        .args(extra);
    command
}

const METRICS: [&str; 6] = ["chamfer", "track", "iou", "psnr", "ssim", "lpips"];

#[test]
fn eval_writes_metrics_table_and_plots() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (scene, model) = tiny_scene_and_model(dir.path());
    let out = dir.path().join("eval");
    let result = run_eval(&model, &scene, &out, &[]);
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    let metrics: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("metrics.json")).expect("metrics.json"))
            .expect("json");
    for split in ["train", "test"] {
        for key in METRICS {
            let value = metrics[split][key]
                .as_f64()
                .unwrap_or_else(|| panic!("{split}.{key} is not a number: {}", metrics[split]));
            assert!(value.is_finite(), "{split}.{key} = {value}");
        }
        let iou = metrics[split]["iou"].as_f64().unwrap_or(f64::NAN);
        let ssim = metrics[split]["ssim"].as_f64().unwrap_or(f64::NAN);
        assert!(
            (0.0..=1.0).contains(&iou) && iou > 0.05,
            "{split} IoU {iou}"
        );
        assert!((-1.0..=1.0).contains(&ssim), "{split} SSIM {ssim}");
        let chamfer = metrics[split]["chamfer"].as_f64().unwrap_or(f64::NAN);
        assert!(chamfer < 0.2, "{split} Chamfer {chamfer} m");
    }
    let frames = metrics["frames"].as_array().expect("frames");
    assert_eq!(frames.len(), 14);
    assert_eq!(frames[0]["frame"], 0);
    assert_eq!(frames[0]["split"], "train");
    assert_eq!(frames[13]["split"], "test");
    for key in METRICS {
        assert!(frames[0].get(key).is_some(), "frames[0].{key} missing");
        assert!(
            out.join("plots").join(format!("{key}.png")).is_file(),
            "plot of {key}"
        );
    }
    let table = std::fs::read_to_string(out.join("metrics.md")).expect("metrics.md");
    assert!(
        table.contains("| test |") && table.contains("LPIPS"),
        "{table}"
    );
}

#[test]
fn eval_names_the_missing_model_file_and_writes_nothing() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (scene, _) = tiny_scene_and_model(dir.path());
    let out = dir.path().join("eval");
    let empty_model = dir.path().join("no-model");
    std::fs::create_dir_all(&empty_model).expect("dir");
    let result = run_eval(&empty_model, &scene, &out, &[]);
    assert!(!result.status.success());
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(stderr.contains("model.json"), "{stderr}");
    assert!(!out.join("metrics.json").exists());
}

#[test]
fn eval_rejects_a_missing_camera_and_skips_lpips_only_when_asked() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (scene, model) = tiny_scene_and_model(dir.path());
    let out = dir.path().join("eval");
    let result = run_eval(&model, &scene, &out, &["--camera", "9"]);
    assert!(!result.status.success());
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(stderr.contains("--camera"), "{stderr}");

    // A missing LPIPS cache: an error naming the file and `make lpips` ...
    let no_cache = dir.path().join("no-cache");
    let args = ["--lpips-dir", no_cache.to_str().expect("utf-8 path")];
    let result = run_eval(&model, &scene, &out, &args);
    assert!(!result.status.success());
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(
        stderr.contains("lpips_alex_v01.onnx") && stderr.contains("make lpips"),
        "{stderr}"
    );
    assert!(!out.join("metrics.json").exists());
    // ... or, with --skip-lpips, null LPIPS and a warning.
    let result = run_eval(
        &model,
        &scene,
        &out,
        &[args[0], args[1], "--skip-lpips", "--frames", "4"],
    );
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    assert!(String::from_utf8_lossy(&result.stderr).contains("warning"));
    let metrics: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("metrics.json")).expect("metrics.json"))
            .expect("json");
    assert!(metrics["train"]["lpips"].is_null());
    assert!(metrics["train"]["psnr"].is_f64());
}

/// With splats in the model directory dm-eval renders them,
/// says so in `run.renderer`, and its frame-0 PSNR on camera 0 is the one
/// the fit recorded; without, it draws particle spheres.
#[test]
fn eval_uses_the_fitted_splats_when_present() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (scene, model_dir) = tiny_scene_and_model(dir.path());
    let no_cache = dir.path().join("no-cache");
    let args = [
        "--lpips-dir",
        no_cache.to_str().expect("utf-8 path"),
        "--skip-lpips",
        "--frames",
        "3",
    ];
    let read_metrics = |out: &Path| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(out.join("metrics.json")).expect("metrics.json"))
            .expect("json")
    };
    let out = dir.path().join("eval-particles");
    let result = run_eval(&model_dir, &scene, &out, &args);
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    assert_eq!(read_metrics(&out)["run"]["renderer"], "particle_spheres");

    let bundle = dm_bundle::Bundle::open(&scene).expect("bundle");
    let model: dm_model::WorldModel =
        dm_bundle::read_json(&model_dir.join("model.json")).expect("model");
    let options = dm_appearance::AppearanceOptions {
        iterations: 10,
        ..dm_appearance::AppearanceOptions::for_cameras(bundle.meta.cameras.len())
    };
    let (gaussians, record) =
        dm_appearance::fit_appearance(&model, &bundle, &options, &mut |_| {}).expect("fit");
    dm_appearance::save_appearance(&model_dir, &gaussians, &record).expect("save");
    let out = dir.path().join("eval-splats");
    let result = run_eval(&model_dir, &scene, &out, &args);
    assert!(
        result.status.success(),
        "{}",
        String::from_utf8_lossy(&result.stderr)
    );
    let metrics = read_metrics(&out);
    assert_eq!(metrics["run"]["renderer"], "gaussian_splats");
    let psnr0 = metrics["frames"][0]["psnr"].as_f64().expect("frame-0 PSNR");
    let recorded = record.psnr[0].psnr_db;
    assert!(
        (psnr0 - recorded).abs() < 1e-9,
        "dm-eval {psnr0} dB, fit record {recorded} dB"
    );
    let iou0 = metrics["frames"][0]["iou"].as_f64().expect("frame-0 IoU");
    assert!(iou0 > 0.5, "frame-0 IoU {iou0}");
}

/// Largest difference in Chamfer or Track, metres: f32 positions after a
/// GPU rollout agree with the CPU's to round-off (~1e-7 m here), far below.
const GEOMETRY_TOLERANCE_M: f64 = 1e-5;
/// Largest difference in IoU, SSIM and LPIPS: a particle on a pixel's edge
/// may cover it or not after round-off, moving these by about a pixel's share.
const IMAGE_TOLERANCE: f64 = 0.02;
/// Largest PSNR difference, dB, for the same reason.
const PSNR_TOLERANCE_DB: f64 = 0.5;

/// `--device cuda` rolls the model out on the GPU: under the driver's
/// emulator (crates/dm-cuda/emulator) the metrics are the CPU run's to
/// round-off and metrics.json records where the rollout ran.
#[test]
fn eval_on_the_gpu_matches_the_cpu_under_the_emulator() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (scene, model) = tiny_scene_and_model(dir.path());
    let emulator =
        dm_cuda::emulator::build(&dir.path().join("emulator")).unwrap_or_else(|e| panic!("{e}"));
    let eval = |device: &str| -> serde_json::Value {
        let out = dir.path().join(device);
        let mut command = eval_command(
            &model,
            &scene,
            &out,
            &["--skip-lpips", "--lpips-dir", "none"],
        );
        dm_cuda::emulator::run_on_device(&mut command, device, &emulator)
            .unwrap_or_else(|e| panic!("{e}"));
        serde_json::from_slice(&std::fs::read(out.join("metrics.json")).expect("metrics.json"))
            .expect("json")
    };
    let (cpu, gpu) = (eval("cpu"), eval("cuda"));
    assert_eq!(cpu["run"]["device"], "cpu");
    assert_eq!(gpu["run"]["device"], "cuda");
    for split in ["train", "test"] {
        for key in ["chamfer", "track", "iou", "psnr", "ssim"] {
            let value = |m: &serde_json::Value| {
                m[split][key]
                    .as_f64()
                    .unwrap_or_else(|| panic!("{split}.{key} is not a number: {}", m[split]))
            };
            let tolerance = match key {
                "chamfer" | "track" => GEOMETRY_TOLERANCE_M,
                "psnr" => PSNR_TOLERANCE_DB,
                _ => IMAGE_TOLERANCE,
            };
            let (a, b) = (value(&cpu), value(&gpu));
            assert!(
                (a - b).abs() <= tolerance,
                "{split}.{key}: CPU {a}, emulated GPU {b} (tolerance {tolerance})"
            );
        }
    }
}
