//! `dm-plan` from the command line: plan.json's contract keys, the video,
//! and a bad goal refused with nothing written.

use dm_synth::{Preset, SynthConfig};
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
