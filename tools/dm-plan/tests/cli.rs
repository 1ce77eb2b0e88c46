//! `dm-plan` from the command line: plan.json's contract keys, the video,
//! a bad goal refused with nothing written, and the plan on the GPU.

use dm_synth::{Preset, SynthConfig};
use std::path::Path;
use std::process::Command;

#[test]
fn plan_writes_its_record_actions_rollouts_and_video() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = dir.path().join("scene");
    let truth = dir.path().join("truth.json");
    dm_synth::generate(
        &SynthConfig::tiny(Preset::Rope, 2),
        &scene,
        &truth,
        &mut |_, _, _| {},
    )
    .expect("scene");
    let out = dir.path().join("plan");
    let output = Command::new(env!("CARGO_BIN_EXE_dm-plan"))
        .arg(dir.path().join("unused"))
        .args([
            "--untrained",
            "--goal",
            "move",
            "--horizon",
            "8",
            "--knots",
            "2",
            "--samples",
            "4",
        ])
        .args([
            "--iterations",
            "2",
            "--gradient-iters",
            "2",
            "--window",
            "4",
        ])
        .arg("--bundle")
        .arg(&scene)
        .arg("--plant")
        .arg(&truth)
        .arg("--out")
        .arg(&out)
        .output()
        .expect("dm-plan runs");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let record: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("plan.json")).expect("plan.json"))
            .expect("json");
    for key in ["planned", "executed", "start"] {
        assert!(
            record[key]["final_chamfer_m"]
                .as_f64()
                .is_some_and(f64::is_finite),
            "{key}: {record}"
        );
    }
    assert!(record["rollouts"].as_u64().is_some_and(|n| n > 1));
    assert!(record["seconds"].as_f64().is_some());
    assert_eq!(record["options"]["goal"], "move");
    for file in [
        "actions.json",
        "actions.npy",
        "planned.npy",
        "executed.npy",
        "goal.npy",
        "video/render.mp4",
        "video/frame_00008.png",
    ] {
        assert!(out.join(file).is_file(), "{file} missing");
    }

    let refused = Command::new(env!("CARGO_BIN_EXE_dm-plan"))
        .arg(dir.path().join("unused"))
        .args(["--untrained", "--goal", "fold"])
        .arg("--bundle")
        .arg(&scene)
        .arg("--out")
        .arg(dir.path().join("refused"))
        .output()
        .expect("dm-plan runs");
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(
        stderr.contains("--goal") && stderr.contains("straighten"),
        "{stderr}"
    );
    assert!(!dir.path().join("refused").exists());
}

/// Relative difference allowed between a plan's costs on the CPU and on
/// the GPU: both run in f32 but add up in another order, and a short plan
/// carries that round-off through a few rollouts and gradient steps
/// (about 2e-8 relative here).
const GPU_PLAN_TOLERANCE: f64 = 1e-4;

/// `dm-plan --device cuda` under the driver's emulator
/// (crates/dm-cuda/emulator): MPPI's samples side by side on their
/// streams and the gradient steps through the GPU adjoint give the CPU's
/// plan to round-off, and the truth world carries it out as on the CPU.
#[test]
fn plan_on_the_gpu_matches_the_cpu_under_the_emulator() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = dir.path().join("scene");
    dm_synth::generate(
        &SynthConfig::smallest(Preset::Rope, 3),
        &scene,
        &dir.path().join("t.json"),
        &mut |_, _, _| {},
    )
    .expect("scene");
    let emulator =
        dm_cuda::emulator::build(&dir.path().join("emulator")).unwrap_or_else(|e| panic!("{e}"));
    let plan = |out: &Path, device: &str| -> serde_json::Value {
        let mut command = Command::new(env!("CARGO_BIN_EXE_dm-plan"));
        command
            .arg(dir.path().join("unused"))
            .args(["--untrained", "--goal", "straighten", "--horizon", "6"])
            .args([
                "--samples",
                "4",
                "--iterations",
                "2",
                "--gradient-iters",
                "2",
            ])
            .args(["--settle-frames", "0", "--no-video"])
            .arg("--bundle")
            .arg(&scene)
            .arg("--plant")
            .arg(dir.path().join("t.json"))
            .arg("--out")
            .arg(out);
        dm_cuda::emulator::run_on_device(&mut command, device, &emulator)
            .unwrap_or_else(|e| panic!("{e}"));
        serde_json::from_slice(&std::fs::read(out.join("plan.json")).expect("plan.json"))
            .expect("json")
    };
    let cpu = plan(&dir.path().join("cpu"), "cpu");
    let gpu = plan(&dir.path().join("gpu"), "cuda");
    assert_eq!(gpu["options"]["device"], "cuda");
    assert_eq!(
        cpu["rollouts"], gpu["rollouts"],
        "another number of rollouts"
    );
    // The truth world is the plant, on the GPU too.
    for pointer in [
        "/planned/final_chamfer_m",
        "/planned/final_track_m",
        "/start/final_chamfer_m",
        "/executed/final_chamfer_m",
    ] {
        let value = |record: &serde_json::Value| {
            record
                .pointer(pointer)
                .and_then(serde_json::Value::as_f64)
                .unwrap_or_else(|| panic!("{pointer} is not a number: {record}"))
        };
        let (c, g) = (value(&cpu), value(&gpu));
        assert!(
            (c - g).abs() <= GPU_PLAN_TOLERANCE * c.abs(),
            "{pointer}: CPU {c}, GPU {g}"
        );
    }
}
