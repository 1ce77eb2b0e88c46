//! `dm-prep import-phystwin` from the command line: success on the committed
//! tiny case; bad input exits non-zero naming the file and key, and leaves no
//! output directory.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures")
}

fn dm_prep(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dm-prep"))
        .args(args)
        .output()
        .expect("dm-prep runs")
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).expect("create dir");
    for entry in std::fs::read_dir(from).expect("read dir") {
        let entry = entry.expect("entry");
        let target = to.join(entry.file_name());
        if entry.path().is_dir() {
            copy_tree(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), &target).expect("copy");
        }
    }
}

#[test]
fn import_phystwin_writes_a_valid_bundle() {
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("bundle");
    let case = fixtures().join("phystwin_tiny");
    let output = dm_prep(&[
        "import-phystwin".as_ref(),
        case.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(
        stdout.contains("5 frames, 3 cameras, 24 tracked points, 30 controller points"),
        "{stdout}"
    );
    let bundle = dm_bundle::Bundle::open(&out).expect("valid bundle");
    bundle.validate_images().expect("valid images");

    // A second run refuses to overwrite.
    let again = dm_prep(&[
        "import-phystwin".as_ref(),
        case.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("already exists"));
}

#[test]
fn bad_cases_exit_non_zero_naming_file_and_key() {
    for (bad, expected) in [
        ("truncated.pkl", "final_data.pkl: field `(pickle)`"),
        (
            "missing_key.pkl",
            "final_data.pkl: field `object_visibilities`: missing",
        ),
    ] {
        let dir = tempfile::tempdir().expect("temp dir");
        let case = dir.path().join("case");
        copy_tree(&fixtures().join("phystwin_tiny"), &case);
        std::fs::copy(
            fixtures().join("phystwin_bad").join(bad),
            case.join("final_data.pkl"),
        )
        .expect("replace");
        let out = dir.path().join("bundle");
        let output = dm_prep(&[
            "import-phystwin".as_ref(),
            case.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ]);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(1), "{stderr}");
        assert!(
            stderr.contains(expected),
            "expected '{expected}' in: {stderr}"
        );
        assert!(!out.exists());
    }
}

#[test]
fn help_lists_the_subcommand() {
    let output = dm_prep(&["--help".as_ref()]);
    assert!(output.status.success());
    assert!(String::from_utf8_lossy(&output.stdout).contains("import-phystwin"));
}
