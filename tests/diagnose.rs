//! Diagnosis end to end, as a regression on two known scenes: a short
//! dm-synth scene (the evaluation's draw 1000, whose effect the diagnosis
//! names) is fitted briefly and dm-diagnose must name its effect; a null
//! scene (draw 1500) must give `none`. Each scene costs one short fit and
//! one diagnosis (about two minutes on 2 cores), so CI runs one of each.
//! The naming rate on fresh draws comes from the evaluation command,
//! `cargo run --release -p dm-studies --example diagnose_eval`
//! (docs/diagnose.md).

use dm_diagnose::DiagnoseOptions;
use dm_studies::diagnosis_evaluation::{SceneVariant, quick_fit_options, run_scene};

/// The known scenes: a draw whose hidden effect the diagnosis names, and a
/// null draw (seeds of the development set, not the reported fresh ones).
const HIDDEN_SEED: u64 = 1000;
const NULL_SEED: u64 = 1500;

#[test]
fn hidden_effect_is_named_and_null_scene_gives_none() {
    let dir = tempfile::tempdir().expect("temp dir");
    // The detection limits and the discovery have their own tests
    // (dm-diagnose's tests/detectability.rs and tests/discover.rs); here
    // they would only add rollouts and steps.
    let options = DiagnoseOptions {
        refit_iters: 0,
        detect_steps: 0,
        discover_iters: 0,
        ..DiagnoseOptions::default()
    };
    // CI's 2 cores afford the quick fit; the evaluation's longer fit is in
    // docs/RESULTS.md.
    let fit = quick_fit_options();
    let (hidden, d) = run_scene(
        HIDDEN_SEED,
        false,
        &SceneVariant::default(),
        &dir.path().join("hidden"),
        &fit,
        &options,
    )
    .expect("hidden scene");
    assert_eq!(
        hidden.cause, hidden.expected,
        "hidden {} ({:?}) named {}: {:?}",
        hidden.hidden, hidden.magnitude, hidden.cause, d.candidates
    );
    assert!(dir.path().join("hidden/diagnosis/report.md").is_file());
    assert!(
        dir.path()
            .join("hidden/diagnosis/extended_model/model.json")
            .is_file()
    );
    assert!(hidden.track_after < hidden.track_before);
    // The run record: diagnosis.json keeps the options it ran with.
    let diagnosis: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("hidden/diagnosis/diagnosis.json"))
            .expect("diagnosis.json"),
    )
    .expect("diagnosis.json parses");
    let recorded: DiagnoseOptions =
        serde_json::from_value(diagnosis["options"].clone()).expect("options record");
    assert_eq!(recorded, options);
    // Every trial's per-frame error is kept as evidence, one entry per frame
    // (none for a trial that diverged).
    let trials: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("hidden/diagnosis/trials.json"))
            .expect("trials.json"),
    )
    .expect("trials.json parses");
    let frames = trials["base_track_per_frame"]
        .as_array()
        .expect("base curve")
        .len();
    let records = trials["trials"].as_array().expect("trial list");
    assert!(records.len() >= 8 && frames > 0);
    assert!(
        records
            .iter()
            .all(|r| matches!(r["track_per_frame"].as_array().map(Vec::len), Some(n) if n == frames || n == 0))
    );

    let (null, d) = run_scene(
        NULL_SEED,
        true,
        &SceneVariant::default(),
        &dir.path().join("null"),
        &fit,
        &options,
    )
    .expect("null scene");
    assert_eq!(
        null.cause, "none",
        "null scene named {}: {:?}",
        null.cause, d.candidates
    );
}
