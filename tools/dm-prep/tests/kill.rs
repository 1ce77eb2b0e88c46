//! `dm-prep all` killed with SIGKILL at 20 seeded moments and run again:
//! every rerun resumes from its cached stages to the uninterrupted run's
//! bundle and stage outputs, leaving none of the killed runs' temporary
//! stage directories behind, and no output file is ever seen half-written
//! (dm_fuzz::kill).

use dm_fuzz::kill::{KillCheck, assert_kill_and_resume};
use dm_synth::{Preset, SynthConfig};
use dm_synth_capture::SynthCaptureSink;
use std::path::Path;
use std::process::Command;

/// Kill moments (the floor).
const KILL_POINTS: usize = 20;

#[test]
fn a_killed_capture_preparation_resumes_to_the_uninterrupted_files() {
    let dir = tempfile::tempdir().expect("temp dir");
    let capture = dir.path().join("capture");
    let mut sink = SynthCaptureSink::new(&capture);
    dm_synth::generate_with_capture(
        &SynthConfig {
            frames: 10,
            truth_particles: 3000,
            bundle_particles: 500,
            ..SynthConfig::new(Preset::Rope, 7)
        },
        &dir.path().join("truth"),
        &dir.path().join("truth.json"),
        Some(&mut sink),
        &mut |_, _, _| {},
    )
    .expect("scene generates");
    sink.finish().expect("capture closes");
    // The bundle and the stage cache both under the run's directory. A
    // run killed after the bundle was renamed into place has finished it:
    // the rerun replaces it with the same bundle (`--overwrite`), its
    // stages all cached.
    let command = |out: &Path, _rerun: bool| {
        let mut c = Command::new(env!("CARGO_BIN_EXE_dm-prep"));
        c.current_dir(out.parent().expect("a run directory"))
            .arg("all")
            .arg("--capture")
            .arg(&capture)
            .args(["--out", "out/bundle", "--work", "out/work", "--overwrite"]);
        c
    };
    let scratch = dir.path().join("runs");
    let report = assert_kill_and_resume(
        "dm-prep all",
        &KillCheck {
            command: &command,
            points: KILL_POINTS,
            seed: 44,
            scratch: &scratch,
            prepare: None,
            run_record_keys: &[],
            run_record_lines: &[],
        },
    );
    // A rerun removes the stage directories its killed predecessor left.
    assert!(
        report.leftover_temporaries.is_empty(),
        "{:?}",
        report.leftover_temporaries
    );
}
