//! `dm-eval --suite` killed with SIGKILL at 20 seeded moments and run
//! again: every rerun writes the uninterrupted run's scenes, fits, results
//! and tables, and no output file is ever seen half-written
//! (dm_fuzz::kill).

use dm_fuzz::kill::{KillCheck, assert_kill_and_resume};
use std::path::Path;
use std::process::Command;

/// Kill moments (the floor).
const KILL_POINTS: usize = 20;

#[test]
fn a_killed_suite_resumes_to_the_uninterrupted_files() {
    let dir = tempfile::tempdir().expect("temp dir");
    let suite = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../benchmarks/suite-ci.json");
    // suite.json records the command: every run says `--out out`.
    let command = |out: &Path, _rerun: bool| {
        let mut c = Command::new(env!("CARGO_BIN_EXE_dm-eval"));
        c.current_dir(out.parent().expect("a run directory"))
            .arg("--suite")
            .arg(&suite)
            .arg("--out")
            .arg(out.file_name().expect("named out"))
            .arg("--skip-lpips");
        c
    };
    let scratch = dir.path().join("runs");
    assert_kill_and_resume(
        "dm-eval --suite",
        &KillCheck {
            command: &command,
            points: KILL_POINTS,
            seed: 42,
            scratch: &scratch,
            prepare: None,
            // How many runs came from the cache: a rerun's record, not a result.
            run_record_keys: &["cached_runs"],
            run_record_lines: &["from the cache of an earlier invocation"],
        },
    );
}
