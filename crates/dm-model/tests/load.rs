//! `WorldModel::load` refuses a model file whose parts disagree, naming
//! the file and the field, before any index or allocation trusts them: the
//! fuzz corpus's model (an untrained tiny rope) with one part changed at a
//! time.

use dm_model::WorldModel;
use serde_json::{Value, json};
use std::path::{Path, PathBuf};

/// One change to the model's JSON.
type Change = Box<dyn Fn(&mut Value)>;

fn corpus_model() -> Value {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/corpus/model-json/model.json");
    serde_json::from_str(&std::fs::read_to_string(path).expect("corpus model")).expect("json")
}

/// Writes `model` and loads it; returns the error's text.
fn load_error(dir: &Path, model: &Value) -> String {
    let path: PathBuf = dir.join("model.json");
    std::fs::write(&path, serde_json::to_string(model).expect("json")).expect("write");
    match WorldModel::load(&path) {
        Ok(_) => panic!("loaded an inconsistent model"),
        Err(e) => e.to_string(),
    }
}

/// A residual state of `size` with `parameters` weights.
fn residual(size: Value, parameters: usize) -> Value {
    json!({
        "spec": {
            "kind": "pgnd",
            "size": size,
            "alpha": 0.5,
            "grid_origin": [0.0, 0.0, 0.0],
            "grid_dx": 0.05,
            "domain_size": 1.6,
            "seed": 0
        },
        "parameters": vec![0.0; parameters],
    })
}

#[test]
fn the_corpus_model_loads() {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("model.json");
    std::fs::write(&path, serde_json::to_string(&corpus_model()).expect("json")).expect("write");
    let model = WorldModel::load(&path).expect("a consistent model");
    assert!(model.check_consistent().is_ok());
}

#[test]
fn inconsistent_parts_are_refused_with_file_and_field() {
    let dir = tempfile::tempdir().expect("temp dir");
    let patches = corpus_model()["patches"]["centres"]
        .as_array()
        .expect("centres")
        .len();
    let cases: Vec<(&str, Change)> = vec![
        (
            "patches.neighbours",
            Box::new(move |m| m["patches"]["neighbours"][3][1] = json!(patches)),
        ),
        (
            "patches.neighbours",
            Box::new(|m| m["patches"]["neighbours"] = json!([])),
        ),
        (
            "colors",
            Box::new(|m| {
                m["colors"].as_array_mut().expect("colors").pop();
            }),
        ),
        (
            "params.youngs_raw",
            Box::new(|m| {
                m["params"]["youngs_raw"]
                    .as_array_mut()
                    .expect("youngs")
                    .push(json!(0.0))
            }),
        ),
        (
            "surface_count",
            Box::new(|m| m["surface_count"] = json!(1_000_000)),
        ),
        (
            "particle_volume",
            Box::new(|m| m["particle_volume"] = json!(0.0)),
        ),
        (
            "physics",
            Box::new(|m| m["physics"]["wall_cells"] = json!(u64::MAX)),
        ),
        (
            "options",
            Box::new(|m| m["options"]["hand_smoothing"] = json!(1e300)),
        ),
        (
            "residual.spec",
            Box::new(|m| {
                m["residual"] = residual(
                    json!({"encoder": [64, 128, 64], "decoder": 2_147_483_648u64, "groups": 8}),
                    10,
                )
            }),
        ),
        (
            "residual.parameters",
            Box::new(|m| {
                m["residual"] =
                    residual(json!({"encoder": [8, 8, 8], "decoder": 8, "groups": 2}), 10)
            }),
        ),
    ];
    for (field, change) in cases {
        let mut model = corpus_model();
        change(&mut model);
        let error = load_error(dir.path(), &model);
        assert!(
            error.contains("model.json") && error.contains(field),
            "{field}: {error}"
        );
    }
}
