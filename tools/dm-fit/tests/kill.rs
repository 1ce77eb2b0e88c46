//! `dm-fit` killed with SIGKILL at 20 seeded moments and resumed with
//! `--resume`: every resumed fit writes the uninterrupted fit's files, and
//! no output file is ever seen half-written (dm_fuzz::kill).

use dm_fuzz::kill::{KillCheck, assert_kill_and_resume};
use dm_synth::{Preset, SynthConfig};
use std::path::Path;
use std::process::Command;

/// Kill moments (the floor).
const KILL_POINTS: usize = 20;

#[test]
fn a_killed_fit_resumes_to_the_uninterrupted_files() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = dir.path().join("scene");
    dm_synth::generate(
        &SynthConfig::tiny(Preset::Rope, 5),
        &scene,
        &dir.path().join("truth.json"),
        &mut |_, _, _| {},
    )
    .expect("scene");
    // Every stage, each in a step or two: material, residual, splats.
    let command = |out: &Path, resume: bool| {
        let mut c = Command::new(env!("CARGO_BIN_EXE_dm-fit"));
        c.arg(&scene).arg("--out").arg(out).args([
            "--iters",
            "2",
            "--stage2-iters",
            "1",
            "--gain-evals",
            "4",
            "--patches",
            "8",
            "--residual",
            "pgnd",
            "--residual-iters",
            "2",
            // The residual stage's Adam carried over from stage 2: its
            // moments must survive the checkpoint at the stage's start.
            "--residual-adam",
            "continued",
            "--rgb-iters",
            "2",
        ]);
        if resume {
            c.arg("--resume");
        }
        c
    };
    let scratch = dir.path().join("runs");
    assert_kill_and_resume(
        "dm-fit",
        &KillCheck {
            command: &command,
            points: KILL_POINTS,
            seed: 41,
            scratch: &scratch,
            prepare: None,
            run_record_keys: &[],
            run_record_lines: &[],
        },
    );
}
