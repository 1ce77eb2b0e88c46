//! `--resume` reads `checkpoint.json` through `Checkpoint::load`, which
//! refuses a model whose parts disagree and optimiser settings Adam would
//! refuse, naming the file and the field: the fuzz corpus's checkpoint
//! with one part changed at a time.

use dm_fit::run::Checkpoint;
use serde_json::{Value, json};
use std::path::Path;

/// One change to the checkpoint's JSON.
type Change = fn(&mut Value);

fn corpus_checkpoint() -> Value {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/corpus/checkpoint/checkpoint.json");
    serde_json::from_str(&std::fs::read_to_string(path).expect("corpus checkpoint")).expect("json")
}

#[test]
fn a_checkpoint_with_disagreeing_parts_is_refused_with_file_and_field() {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("checkpoint.json");
    let write = |value: &Value| {
        std::fs::write(&path, serde_json::to_string(value).expect("json")).expect("write")
    };
    write(&corpus_checkpoint());
    Checkpoint::load(&path).expect("the corpus checkpoint loads");

    let cases: Vec<(&str, Change)> = vec![
        ("model.colors", |c| {
            c["model"]["colors"].as_array_mut().expect("colors").pop();
        }),
        ("model.params.logits", |c| {
            c["model"]["params"]["logits"] = json!([]);
        }),
        ("adam.config", |c| c["adam"]["config"]["beta1"] = json!(1.0)),
        (
            "kept_residual.step",
            |c| {
                c["kept_residual"] = json!({"step": usize::MAX, "late_loss": 1.0, "parameters": []})
            },
        ),
    ];
    for (field, change) in cases {
        let mut checkpoint = corpus_checkpoint();
        change(&mut checkpoint);
        write(&checkpoint);
        let error = Checkpoint::load(&path)
            .err()
            .unwrap_or_else(|| panic!("{field}: loaded"))
            .to_string();
        assert!(
            error.contains("checkpoint.json") && error.contains(field),
            "{field}: {error}"
        );
    }
}
