//! `dm-appearance` killed with SIGKILL at 20 seeded moments and run again:
//! every rerun writes the uninterrupted run's splats and record, and
//! neither is ever seen half-written (dm_fuzz::kill).

use dm_bundle::{Bundle, write_json_atomic};
use dm_fuzz::kill::{KillCheck, assert_kill_and_resume};
use dm_model::{ModelOptions, ResidualKind, WorldModel};
use dm_synth::{Preset, SynthConfig};
use std::path::Path;
use std::process::Command;

/// Kill moments (the floor).
const KILL_POINTS: usize = 20;

#[test]
fn a_killed_splat_fit_reruns_to_the_uninterrupted_files() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = dir.path().join("scene");
    dm_synth::generate(
        &SynthConfig::tiny(Preset::Toy, 8),
        &scene,
        &dir.path().join("truth.json"),
        &mut |_, _, _| {},
    )
    .expect("scene");
    let bundle = Bundle::open(&scene).expect("bundle");
    let options = ModelOptions {
        residual: ResidualKind::None,
        ..ModelOptions::default()
    };
    let model = WorldModel::from_bundle(&bundle, &options).expect("model");
    // Each run's model directory starts with the model alone.
    let prepare = |out: &Path| -> Result<(), String> {
        std::fs::create_dir_all(out).map_err(|e| e.to_string())?;
        write_json_atomic(&out.join("model.json"), &model).map_err(|e| e.to_string())
    };
    let command = |out: &Path, _rerun: bool| {
        let mut c = Command::new(env!("CARGO_BIN_EXE_dm-appearance"));
        c.arg(out).arg(&scene).args(["--iters", "150"]);
        c
    };
    let scratch = dir.path().join("runs");
    assert_kill_and_resume(
        "dm-appearance",
        &KillCheck {
            command: &command,
            points: KILL_POINTS,
            seed: 43,
            scratch: &scratch,
            prepare: Some(&prepare),
            run_record_keys: &[],
            run_record_lines: &[],
        },
    );
}
