//! `dm-fit` from the command line: the report's contract keys,
//! and a fit paused and resumed gives the same model as an uninterrupted one.

use dm_synth::{Preset, SynthConfig};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Stages 1–2 in a few steps.
const FAST_PHYSICS: &[&str] = &[
    "--iters",
    "2",
    "--stage2-iters",
    "1",
    "--gain-evals",
    "4",
    "--patches",
    "8",
];

/// `dm-fit SCENE --out OUT` with FAST_PHYSICS, no residual-only stage, two
/// stage-3 steps and `extra`.
fn fit(scene: &Path, out: &Path, extra: &[&str]) -> Output {
    let stages = ["--residual-iters", "0", "--rgb-iters", "2"];
    fit_with(scene, out, &[FAST_PHYSICS, &stages, extra].concat())
}

/// `dm-fit SCENE --out OUT ARGS..`, which must succeed.
fn fit_with(scene: &Path, out: &Path, args: &[&str]) -> Output {
    fit_with_env(scene, out, args, &[])
}

/// [`fit_with`] with extra environment variables.
fn fit_with_env(scene: &Path, out: &Path, args: &[&str], env: &[(&str, &str)]) -> Output {
    let output = Command::new(env!("CARGO_BIN_EXE_dm-fit"))
        .arg(scene)
        .arg("--out")
        .arg(out)
        .args(args)
        .envs(env.iter().copied())
        .output()
        .expect("dm-fit runs");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    output
}

/// A tiny dm-synth scene at DIR/scene.
fn tiny_scene(dir: &Path, preset: Preset, seed: u64) -> PathBuf {
    let scene = dir.join("scene");
    dm_synth::generate(
        &SynthConfig::tiny(preset, seed),
        &scene,
        &dir.join("t.json"),
        &mut |_, _, _| {},
    )
    .expect("scene");
    scene
}

#[test]
fn fit_reports_contract_keys_and_resumes_exactly() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = tiny_scene(dir.path(), Preset::Cloth, 4);

    let whole = dir.path().join("whole");
    let output = fit(&scene, &whole, &[]);
    // The default network went through the residual check, and the
    // summary says what it decided.
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        stdout.contains("residual network: train Track"),
        "no residual check line in {stdout}"
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(whole.join("fit_report.json")).expect("report"))
            .expect("json");
    for key in ["E_median_pa", "nu_median"] {
        assert!(
            report["material"][key].as_f64().is_some_and(f64::is_finite),
            "material.{key}"
        );
    }
    for key in ["kp", "kd"] {
        assert!(
            report["dca"][key].as_f64().is_some_and(|v| v > 0.0),
            "dca.{key}"
        );
    }
    assert!(report["loss"]["final"].as_f64().is_some_and(f64::is_finite));
    assert!(report["seconds"].as_f64().is_some());
    assert_eq!(report["options"]["iters"], 2);
    // Stage 3 ran its two steps after the three material steps.
    let history = report["loss"]["history"].as_array().expect("history");
    assert_eq!(history.len(), 5);
    assert!(history[..3].iter().all(|h| h.get("rgb_l1").is_none()));
    assert!(
        history[3..]
            .iter()
            .all(|h| h["rgb_l1"].as_f64().is_some_and(|l| l > 0.0 && l < 1.0))
    );
    for file in [
        "model.json",
        "youngs_pa.npy",
        "poisson.npy",
        "expert_weights.npy",
        "loss_curve.png",
        "gaussians.ply",
        "appearance.json",
    ] {
        assert!(whole.join(file).is_file(), "{file}");
    }

    let split = dir.path().join("split");
    let paused = fit(&scene, &split, &["--stop-after", "2"]);
    assert!(String::from_utf8_lossy(&paused.stdout).contains("paused"));
    assert!(!split.join("model.json").exists());
    // Pause again inside stage 3 (loop step 7: its first step, which fits
    // and saves the Gaussians), so the second stage-3 step loads them.
    fit(&scene, &split, &["--resume", "--stop-after", "5"]);
    let checkpoint: serde_json::Value =
        serde_json::from_slice(&std::fs::read(split.join("checkpoint.json")).expect("checkpoint"))
            .expect("json");
    assert_eq!(checkpoint["stage"], "rgb");
    assert_eq!(checkpoint["iteration"], 1);
    fit(&scene, &split, &["--resume"]);
    let model_whole = std::fs::read(whole.join("model.json")).expect("model");
    let model_split = std::fs::read(split.join("model.json")).expect("model");
    assert!(
        model_whole == model_split,
        "a resumed fit must equal an uninterrupted one"
    );
}

#[test]
fn resume_refuses_a_checkpoint_made_with_other_options() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = tiny_scene(dir.path(), Preset::Rope, 4);
    let out = dir.path().join("model");
    fit(&scene, &out, &["--stop-after", "1"]);
    let result = Command::new(env!("CARGO_BIN_EXE_dm-fit"))
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .args(["--iters", "5", "--resume"])
        .output()
        .expect("dm-fit runs");
    assert!(!result.status.success());
    assert!(String::from_utf8_lossy(&result.stderr).contains("different options"));
}

/// `--residual-iters N`: N steps on the residual network after
/// stage 2 with the physics frozen: the material fields equal those of the
/// same fit without the stage, the network's weights do not.
#[test]
fn residual_stage_trains_the_network_and_leaves_the_physics() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = tiny_scene(dir.path(), Preset::Rope, 5);
    let without = dir.path().join("without");
    let with = dir.path().join("with");
    // No stage 3: it would move the material again.
    let physics_then_residual = |out: &Path, residual_iters: &str| {
        // `last`: the stage's best late-frames network may be its start.
        let stages = [
            "--rgb-iters",
            "0",
            "--residual",
            "pgnd",
            "--residual-keep",
            "last",
            // Both networks are compared, whatever they gain.
            "--residual-min-gain",
            "0",
            "--residual-iters",
        ];
        fit_with(
            &scene,
            out,
            &[FAST_PHYSICS, &stages, &[residual_iters]].concat(),
        );
    };
    physics_then_residual(&without, "0");
    physics_then_residual(&with, "2");
    let history_len = |model: &Path| {
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(model.join("fit_report.json")).expect("report"))
                .expect("json");
        report["loss"]["history"].as_array().expect("history").len()
    };
    assert_eq!((history_len(&without), history_len(&with)), (3, 5));
    for frozen in ["youngs_pa.npy", "poisson.npy", "expert_weights.npy"] {
        assert!(
            std::fs::read(without.join(frozen)).expect(frozen)
                == std::fs::read(with.join(frozen)).expect(frozen),
            "{frozen} changed in the residual stage"
        );
    }
    assert!(
        std::fs::read(without.join("residual.safetensors")).expect("weights")
            != std::fs::read(with.join("residual.safetensors")).expect("weights"),
        "the residual stage did not change the network"
    );
}

/// `--identifiability`: the Cramér–Rao bound is printed, one
/// entry per parameter, and a bad noise value is refused naming the flag.
#[test]
fn identifiability_is_printed_and_bad_noise_refused() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = tiny_scene(dir.path(), Preset::Rope, 4);
    let stages = [
        "--residual",
        "none",
        "--rgb-iters",
        "0",
        "--gain-evals",
        "0",
        "--identifiability",
    ];
    let output = fit_with(
        &scene,
        &dir.path().join("model"),
        &[&FAST_PHYSICS[..4], &FAST_PHYSICS[6..], &stages].concat(),
    );
    let stdout = String::from_utf8_lossy(&output.stdout);
    let line = stdout
        .lines()
        .find(|l| l.contains("Cramér–Rao bound"))
        .unwrap_or_else(|| panic!("no bound line in {stdout}"));
    for name in ["E ±", "nu ±", "kp ±", "kd ±"] {
        assert!(line.contains(name), "{name} missing: {line}");
    }

    let refused = Command::new(env!("CARGO_BIN_EXE_dm-fit"))
        .arg(&scene)
        .arg("--out")
        .arg(dir.path().join("refused"))
        .args(["--identifiability", "--track-noise-mm", "0"])
        .output()
        .expect("dm-fit runs");
    assert!(!refused.status.success());
    assert!(
        String::from_utf8_lossy(&refused.stderr).contains("--track-noise-mm"),
        "{}",
        String::from_utf8_lossy(&refused.stderr)
    );
}

/// A bad `--hand-smoothing` stops dm-fit before any work, naming the flag,
/// and leaves no model directory behind.
#[test]
fn bad_hand_smoothing_is_refused() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = tiny_scene(dir.path(), Preset::Rope, 4);
    let out = dir.path().join("refused");
    let refused = Command::new(env!("CARGO_BIN_EXE_dm-fit"))
        .arg(&scene)
        .arg("--out")
        .arg(&out)
        .arg("--hand-smoothing=-2")
        .output()
        .expect("dm-fit runs");
    assert!(!refused.status.success());
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(stderr.contains("--hand-smoothing"), "{stderr}");
    // Nothing is written, not even an empty output directory.
    assert!(!out.exists(), "a refused run created {}", out.display());
}

/// The whole fit — gain search, material stages, the residual network and
/// its check, stage 3 — writes bitwise the same files on one thread as on
/// two: every parallel sum runs over fixed ranges in a fixed order.
#[test]
fn fit_writes_the_same_files_on_one_and_two_threads() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = tiny_scene(dir.path(), Preset::Toy, 6);
    let run = |threads: &str| {
        let out = dir.path().join(format!("threads{threads}"));
        let stages = [
            "--residual",
            "pgnd",
            "--residual-iters",
            "2",
            "--rgb-iters",
            "1",
        ];
        fit_with_env(
            &scene,
            &out,
            &[FAST_PHYSICS, &stages].concat(),
            &[("RAYON_NUM_THREADS", threads)],
        );
        out
    };
    let (one, two) = (run("1"), run("2"));
    let files = [
        "model.json",
        "youngs_pa.npy",
        "poisson.npy",
        "expert_weights.npy",
        "gaussians.ply",
    ];
    for file in files {
        let read = |dir: &Path| std::fs::read(dir.join(file)).expect(file);
        assert!(
            read(&one) == read(&two),
            "{file} differs between 1 and 2 threads"
        );
    }
    // The reports' numbers too, all but the wall-clock times.
    for report in ["fit_report.json", "appearance.json"] {
        let numbers = |dir: &Path| {
            let text = std::fs::read_to_string(dir.join(report)).expect(report);
            let mut value: serde_json::Value = serde_json::from_str(&text).expect(report);
            strip_seconds(&mut value);
            value
        };
        assert_eq!(numbers(&one), numbers(&two), "{report}");
    }
}

fn strip_seconds(value: &mut serde_json::Value) {
    match value {
        serde_json::Value::Object(map) => {
            map.retain(|key, _| !key.contains("seconds"));
            map.values_mut().for_each(strip_seconds);
        }
        serde_json::Value::Array(items) => items.iter_mut().for_each(strip_seconds),
        _ => {}
    }
}

/// Relative difference allowed between a CPU fit's numbers and the same
/// fit on the GPU: both run in f32 but add up particles and nodes in
/// another order, and a short fit carries that round-off through a few
/// steps (about 1e-7 relative on this scene).
const GPU_FIT_TOLERANCE: f64 = 1e-4;

/// `dm-fit --device cuda` under the driver's emulator
/// (crates/dm-cuda/emulator): the residual check's physics-only fit runs
/// beside the main fit, its progress lines passed on, and the fit — its
/// material, losses and the check's decision — is the CPU fit's to
/// round-off.
#[test]
fn fit_on_the_gpu_with_the_check_beside_it_matches_the_cpu_under_the_emulator() {
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
    // One step of each dynamics stage with the default network and check.
    let args = [
        "--iters",
        "1",
        "--stage2-iters",
        "0",
        "--gain-evals",
        "0",
        "--residual-iters",
        "1",
        "--rgb-iters",
        "0",
    ];
    let cpu = dir.path().join("cpu");
    fit_with(&scene, &cpu, &args);
    let gpu = dir.path().join("gpu");
    let emulated = [("LD_PRELOAD", emulator.to_str().expect("utf-8 path"))];
    let output = fit_with_env(
        &scene,
        &gpu,
        &[&args[..], &["--device", "cuda"]].concat(),
        &emulated,
    );
    let lines = String::from_utf8_lossy(&output.stdout) + String::from_utf8_lossy(&output.stderr);
    assert!(
        lines.contains("beside this fit") && lines.contains("[no network] Material1 1/1"),
        "the check's fit did not run beside the main one:\n{lines}"
    );
    assert!(
        gpu.join("residual_check/model.json").is_file(),
        "no physics-only model"
    );
    let report = |dir: &Path| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(dir.join("fit_report.json")).expect("report"))
            .expect("json")
    };
    let (cpu, gpu) = (report(&cpu), report(&gpu));
    assert_eq!(cpu["options"]["device"], "cpu");
    assert_eq!(gpu["options"]["device"], "cuda");
    assert_eq!(
        cpu["residual"]["check"]["kept"], gpu["residual"]["check"]["kept"],
        "the check decided otherwise"
    );
    let numbers = [
        "/material/E_median_pa",
        "/material/nu_median",
        "/loss/initial",
        "/loss/final",
        "/residual/check/track_with",
        "/residual/check/track_without",
    ];
    for pointer in numbers {
        let value = |report: &serde_json::Value| {
            report
                .pointer(pointer)
                .and_then(serde_json::Value::as_f64)
                .unwrap_or_else(|| panic!("{pointer} is not a number"))
        };
        let (c, g) = (value(&cpu), value(&gpu));
        assert!(
            (c - g).abs() <= GPU_FIT_TOLERANCE * c.abs(),
            "{pointer}: CPU {c}, GPU {g}"
        );
    }
}
