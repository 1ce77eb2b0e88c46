//! `dm-synth` from the command line: determinism from the seed,
//! independent of thread count; the truth stays outside the bundle; bad
//! input fails with a clear message and writes nothing.

use std::path::Path;
use std::process::{Command, Output};

const TINY: &[&str] = &[
    "--frames",
    "12",
    "--width",
    "48",
    "--height",
    "36",
    "--truth-particles",
    "1500",
    "--tracks",
    "40",
    "--bundle-particles",
    "400",
];

fn synth(out: &Path, extra: &[&str], threads: &str) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dm-synth"))
        .args(["--preset", "cloth", "--seed", "3", "--out"])
        .arg(out)
        .args(TINY)
        .args(extra)
        .env("RAYON_NUM_THREADS", threads)
        .output()
        .expect("dm-synth runs")
}

/// Every file of a directory tree with its bytes, sorted by path.
fn tree(root: &Path) -> Vec<(String, Vec<u8>)> {
    let mut files = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).expect("readable dir") {
            let path = entry.expect("entry").path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let rel = path
                    .strip_prefix(root)
                    .expect("inside root")
                    .display()
                    .to_string();
                files.push((rel, std::fs::read(&path).expect("readable file")));
            }
        }
    }
    files.sort();
    files
}

#[test]
fn synth_is_deterministic_across_thread_counts() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let out_a = synth(&a, &["--effect", "air_drag"], "1");
    assert!(
        out_a.status.success(),
        "{}",
        String::from_utf8_lossy(&out_a.stderr)
    );
    let out_b = synth(&b, &["--effect", "air_drag"], "2");
    assert!(
        out_b.status.success(),
        "{}",
        String::from_utf8_lossy(&out_b.stderr)
    );
    let (ta, tb) = (tree(&a), tree(&b));
    assert!(
        ta.len() > 12 * 3 * 4,
        "expected images for 3 cameras x 12 frames"
    );
    assert_eq!(ta.len(), tb.len());
    for ((na, da), (nb, db)) in ta.iter().zip(&tb) {
        assert_eq!(na, nb);
        assert!(da == db, "{na} differs between 1 and 2 threads");
    }
    let truth_a = std::fs::read(dir.path().join("a.truth.json")).expect("truth beside bundle");
    let truth_b = std::fs::read(dir.path().join("b.truth.json")).expect("truth beside bundle");
    let ja: serde_json::Value = serde_json::from_slice(&truth_a).expect("json");
    let jb: serde_json::Value = serde_json::from_slice(&truth_b).expect("json");
    for key in ["preset", "seed", "material", "effect"] {
        assert_eq!(ja[key], jb[key], "truth key {key}");
    }
    assert_eq!(ja["effect"]["name"], "air_drag");
    assert!(ja["material"]["E_pa"].as_f64().is_some_and(|e| e > 0.0));
    // Nothing in the bundle may reveal the effect.
    for (name, bytes) in &ta {
        if name.ends_with(".json") {
            let text = String::from_utf8_lossy(bytes);
            assert!(!text.contains("air_drag"), "{name} leaks the hidden effect");
        }
    }
}

#[test]
fn synth_rejects_unknown_effect_and_writes_nothing() {
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("scene");
    let result = synth(&out, &["--effect", "moon_gravity"], "2");
    assert!(!result.status.success());
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(
        stderr.contains("moon_gravity") && stderr.contains("--effect"),
        "{stderr}"
    );
    assert!(!out.exists());
}

#[test]
fn synth_refuses_to_overwrite_an_existing_bundle() {
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("scene");
    std::fs::create_dir(&out).expect("mkdir");
    std::fs::write(out.join("keep.txt"), "precious").expect("write");
    let result = synth(&out, &[], "2");
    assert!(!result.status.success());
    assert!(String::from_utf8_lossy(&result.stderr).contains("scene"));
    assert_eq!(
        std::fs::read_to_string(out.join("keep.txt")).expect("kept"),
        "precious"
    );
}
