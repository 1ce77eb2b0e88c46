//! `dm-eval --suite` end to end: the committed CI suite (one tiny
//! rope scene, two one-step physics-only fits) runs, writes suite.json and
//! the tables, resumes from its cache, fills a marked section of a results
//! file, and a bad suite file is an error naming the file and the field.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn ci_suite() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../benchmarks/suite-ci.json")
}

fn run_suite(suite: &Path, out: &Path, extra: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dm-eval"))
        .arg("--suite")
        .arg(suite)
        .arg("--out")
        .arg(out)
        .arg("--skip-lpips")
        .args(extra)
        .output()
        .expect("dm-eval runs")
}

fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).expect("readable")).expect("valid JSON")
}

/// Turns the CI suite into a bad one.
type Corruption = Box<dyn Fn(&mut serde_json::Value)>;

const METRICS: [&str; 5] = ["chamfer", "track", "iou", "psnr", "ssim"];

#[test]
fn ci_suite_runs_resumes_and_writes_tables() {
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("suite");
    let results = dir.path().join("RESULTS.md");
    std::fs::write(&results, "# Results\n\nEarlier text.\n").expect("results file");
    let results_arg = results.to_str().expect("utf-8 path");

    let first = run_suite(&ci_suite(), &out, &["--results-md", results_arg]);
    assert!(
        first.status.success(),
        "{}",
        String::from_utf8_lossy(&first.stderr)
    );
    let report = read_json(&out.join("suite.json"));
    for key in [
        "suite",
        "command",
        "scenes",
        "variants",
        "runs",
        "tables",
        "cached_runs",
        "seconds",
    ] {
        assert!(report.get(key).is_some(), "suite.json lacks `{key}`");
    }
    assert_eq!(report["cached_runs"], 0);
    let runs = report["runs"].as_array().expect("runs");
    assert_eq!(runs.len(), 2, "one scene × two variants");
    let variants: Vec<&str> = runs
        .iter()
        .map(|r| r["variant"].as_str().expect("variant"))
        .collect();
    assert_eq!(variants, ["no_residual", "single"]);
    for run in runs {
        assert_eq!(run["scene"], "rope-s5-lift");
        assert_eq!(run["category"], "linear");
        assert_eq!(run["status"], "ok", "{run}");
        for split in ["train", "test"] {
            for key in METRICS {
                let value = run[split][key].as_f64().unwrap_or(f64::NAN);
                assert!(value.is_finite(), "{split}.{key} = {}", run[split][key]);
            }
            // --skip-lpips skips only when the network is missing.
            let lpips = &run[split]["lpips"];
            match run["lpips"].as_bool() {
                Some(true) => assert!(lpips.as_f64().is_some_and(f64::is_finite), "{lpips}"),
                _ => assert!(lpips.is_null(), "LPIPS was skipped: {lpips}"),
            }
        }
        // The variant's flags reached the fit.
        let actuators = run["fit"]["model"]["actuators"]
            .as_str()
            .expect("actuators");
        let expected = if run["variant"] == "single" {
            "single"
        } else {
            "dca"
        };
        assert_eq!(actuators, expected);
        assert_eq!(run["fit"]["iters"], 1);
    }
    let groups: Vec<&str> = report["tables"]
        .as_array()
        .expect("tables")
        .iter()
        .map(|t| t["group"].as_str().expect("group"))
        .collect();
    assert_eq!(groups, ["all", "linear"]);
    let all = &report["tables"][0]["rows"][0];
    assert_eq!(all["variant"], "no_residual");
    assert_eq!(all["runs"], 1);
    assert_eq!(all["diverged"], 0);
    assert_eq!(all["test"]["chamfer"], runs[0]["test"]["chamfer"]);

    let tables = std::fs::read_to_string(out.join("tables.md")).expect("tables.md");
    assert!(
        tables.contains(
            "| variant | IoU ↑ | Chamfer (m) ↓ | Track (m) ↓ | PSNR (dB) ↑ | SSIM ↑ | LPIPS ↓ | diverged |"
        ),
        "{tables}"
    );
    assert!(tables.contains("**All scenes**") && tables.contains("**Linear**"));
    assert!(tables.contains("| no_residual |") && tables.contains("| single |"));
    let markdown = std::fs::read_to_string(&results).expect("results file");
    assert!(
        markdown.starts_with("# Results\n\nEarlier text.\n"),
        "{markdown}"
    );
    assert!(markdown.contains("| single |"));

    // Rerun: every result comes from the cache; the tables are the same and
    // the results file's section is replaced, not repeated.
    let result_json = out.join("runs/rope-s5-lift/single/result.json");
    let written = std::fs::metadata(&result_json)
        .and_then(|m| m.modified())
        .expect("result.json");
    let second = run_suite(&ci_suite(), &out, &["--results-md", results_arg]);
    assert!(
        second.status.success(),
        "{}",
        String::from_utf8_lossy(&second.stderr)
    );
    let again = read_json(&out.join("suite.json"));
    assert_eq!(again["cached_runs"], 2);
    assert_eq!(again["runs"], report["runs"]);
    assert_eq!(
        std::fs::metadata(&result_json)
            .and_then(|m| m.modified())
            .expect("result.json"),
        written,
        "a cached result is not rewritten"
    );
    let markdown = std::fs::read_to_string(&results).expect("results file");
    assert_eq!(markdown.matches("dm-eval suite: begin").count(), 1);
    assert_eq!(markdown.matches("**All scenes**").count(), 1);
}

#[test]
fn bad_suite_file_names_file_and_field() {
    let dir = tempfile::tempdir().expect("temp dir");
    let ci: serde_json::Value = read_json(&ci_suite());
    let cases: [(&str, Corruption, &str); 3] = [
        (
            "bad-flag.json",
            Box::new(|s| s["variants"][1]["fit_args"] = serde_json::json!(["--actuators", "glue"])),
            "variants[1].fit_args",
        ),
        (
            "bad-preset.json",
            Box::new(|s| s["scenes"][0]["preset"] = serde_json::json!("blob")),
            "scenes[0].preset",
        ),
        (
            "duplicate.json",
            Box::new(|s| s["variants"][1]["name"] = serde_json::json!("no_residual")),
            "variants[1].name",
        ),
    ];
    for (name, corrupt, field) in cases {
        let mut suite = ci.clone();
        corrupt(&mut suite);
        let path = dir.path().join(name);
        std::fs::write(&path, serde_json::to_vec(&suite).expect("json")).expect("write");
        let out = dir.path().join("out");
        let result = run_suite(&path, &out, &[]);
        let stderr = String::from_utf8_lossy(&result.stderr);
        assert!(!result.status.success(), "{name} was accepted");
        assert!(
            stderr.contains(name),
            "{name}: error does not name the file: {stderr}"
        );
        assert!(
            stderr.contains(field),
            "{name}: error does not name `{field}`: {stderr}"
        );
        assert!(!out.exists(), "{name}: nothing is written for a bad suite");
    }
}

/// The foreign-physics source end to end (generate with MuJoCo → fit →
/// evaluate) on a tiny scene, so that it cannot rot: the committed CI
/// suite's scene is simulated by MuJoCo, and the demo's short fit predicts
/// its held-out frames better than the untrained model. Needs the Python
/// named by DM_MUJOCO_PYTHON (`make test` sets it).
#[test]
fn foreign_ci_suite_generates_fits_and_evaluates() {
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("suite");
    let suite = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../benchmarks/foreign-ci.json");
    let run = run_suite(&suite, &out, &[]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let truth = read_json(&out.join("scenes/rope-s3-lift/truth.json"));
    assert_eq!(truth["engine"]["engine"], "mujoco", "{}", truth["engine"]);
    let report = read_json(&out.join("suite.json"));
    let runs = report["runs"].as_array().expect("runs");
    let test_error = |variant: &str, key: &str| {
        let run = runs
            .iter()
            .find(|r| r["variant"] == variant)
            .unwrap_or_else(|| panic!("no `{variant}` run"));
        assert_eq!(run["status"], "ok", "{run}");
        run["test"][key].as_f64().expect("finite metric")
    };
    for key in ["track", "chamfer"] {
        let (untrained, fitted) = (test_error("untrained", key), test_error("no_residual", key));
        assert!(
            fitted < untrained,
            "held-out {key}: fitted {fitted} m, untrained {untrained} m"
        );
    }
}
