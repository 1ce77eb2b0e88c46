//! A tiny fitted-model directory for the playground tests: the untrained
//! world model of a tiny synthetic toy scene (what dm-fit writes, without
//! the fitting: the playground only reads model.json), optionally with
//! splats from a short appearance fit.

use std::path::PathBuf;

use dm_appearance::{AppearanceOptions, fit_appearance, save_appearance};
use dm_bundle::{Bundle, write_json_atomic};
use dm_model::{ModelOptions, ResidualKind, WorldModel};
use dm_synth::{Preset, SynthConfig};

pub struct TinyModel {
    pub dir: tempfile::TempDir,
    pub model_dir: PathBuf,
}

pub fn tiny_model(with_splats: bool) -> TinyModel {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = dir.path().join("scene");
    dm_synth::generate(
        &SynthConfig::tiny(Preset::Toy, 9),
        &scene,
        &dir.path().join("truth.json"),
        &mut |_, _, _| {},
    )
    .expect("scene generates");
    let bundle = Bundle::open(&scene).expect("bundle");
    let options = ModelOptions {
        residual: ResidualKind::None,
        ..ModelOptions::default()
    };
    let model = WorldModel::from_bundle(&bundle, &options).expect("model");
    let model_dir = dir.path().join("model");
    std::fs::create_dir_all(&model_dir).expect("model dir");
    write_json_atomic(&model_dir.join("model.json"), &model).expect("model.json");
    if with_splats {
        let appearance = AppearanceOptions {
            iterations: 3,
            ..AppearanceOptions::for_cameras(bundle.meta.cameras.len())
        };
        let (gaussians, record) =
            fit_appearance(&model, &bundle, &appearance, &mut |_| {}).expect("splat fit");
        save_appearance(&model_dir, &gaussians, &record).expect("splats saved");
    }
    TinyModel { dir, model_dir }
}
