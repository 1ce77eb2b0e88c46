//! `dm-diagnose --device cuda` under the driver's emulator
//! (crates/dm-cuda/emulator) against the CPU.

// The diagnosis library's tests fit their models the same way.
#[path = "../../../crates/dm-diagnose/tests/common/mod.rs"]
mod common;

use dm_synth::{Preset, SynthConfig};
use std::path::Path;
use std::process::Command;

/// Largest difference allowed between a candidate's score on the CPU and
/// on the GPU. Scores are differences of Track-error ratios, of order
/// 0.01–3; both devices run f32 but add up in another order, and each
/// score carries that round-off through its candidate's effect fit (seen:
/// at most 5e-7).
const GPU_SCORE_TOLERANCE: f64 = 1e-5;

/// Relative difference allowed between the extended model's Track error
/// on the two devices, for the same reason (seen: 5e-7).
const GPU_TRACK_TOLERANCE: f64 = 1e-4;

/// The smallest rope, its ground tilted by 8°, a physics-only model fitted
/// in two material steps, diagnosed on both devices with the effect fits
/// only (no discovery, detection limits or refit, which would take the
/// emulator many minutes): the same cause, the hidden tilt, and every
/// candidate's score as on the CPU.
#[test]
fn diagnosis_on_the_gpu_matches_the_cpu_under_the_emulator() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = dir.path().join("scene");
    let config = SynthConfig {
        effect: Some("ground_tilt:8".parse().expect("effect")),
        ..SynthConfig::smallest(Preset::Rope, 3)
    };
    dm_synth::generate(
        &config,
        &scene,
        &dir.path().join("t.json"),
        &mut |_, _, _| {},
    )
    .expect("scene");
    let bundle = dm_bundle::Bundle::open(&scene).expect("bundle");
    let model_dir = common::fit_physics_only(&bundle, 2, &dir.path().join("model"));
    let emulator =
        dm_cuda::emulator::build(&dir.path().join("emulator")).unwrap_or_else(|e| panic!("{e}"));
    let diagnose = |out: &Path, device: &str| -> serde_json::Value {
        let mut command = Command::new(env!("CARGO_BIN_EXE_dm-diagnose"));
        command
            .arg(&model_dir)
            .arg(&scene)
            .args([
                "--discover-iters",
                "0",
                "--detect-steps",
                "0",
                "--refit-iters",
                "0",
            ])
            // The two-step fit leaves the tilt's score at 0.08.
            .args(["--threshold", "0.05"])
            .arg("--out")
            .arg(out);
        dm_cuda::emulator::run_on_device(&mut command, device, &emulator)
            .unwrap_or_else(|e| panic!("{e}"));
        serde_json::from_slice(&std::fs::read(out.join("diagnosis.json")).expect("diagnosis"))
            .expect("json")
    };
    let cpu = diagnose(&dir.path().join("cpu"), "cpu");
    let gpu = diagnose(&dir.path().join("gpu"), "cuda");
    assert_eq!(cpu["cause"], "ground_tilt", "the CPU's diagnosis: {cpu}");
    assert_eq!(gpu["cause"], cpu["cause"]);
    let scores = |record: &serde_json::Value| -> Vec<(String, f64)> {
        record["candidates"]
            .as_array()
            .expect("candidates")
            .iter()
            .map(|c| {
                let name = c["name"].as_str().expect("name").to_owned();
                (name, c["score"].as_f64().expect("score"))
            })
            .collect()
    };
    let (cpu_scores, gpu_scores) = (scores(&cpu), scores(&gpu));
    assert_eq!(cpu_scores.len(), gpu_scores.len(), "another candidate list");
    for ((name, c), (gpu_name, g)) in cpu_scores.iter().zip(&gpu_scores) {
        assert_eq!(name, gpu_name, "candidates in another order");
        assert!(
            (c - g).abs() <= GPU_SCORE_TOLERANCE,
            "{name}: score {c} on the CPU, {g} on the GPU"
        );
    }
    let track = |record: &serde_json::Value| record["gain"]["track_after"].as_f64().expect("track");
    let (c, g) = (track(&cpu), track(&gpu));
    assert!(
        (c - g).abs() <= GPU_TRACK_TOLERANCE * c,
        "extended model's Track error: CPU {c}, GPU {g}"
    );
}
