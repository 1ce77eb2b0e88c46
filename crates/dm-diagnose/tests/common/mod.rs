//! What the diagnosis tests share: a scene's physics-only model fitted
//! briefly and written where `dm_diagnose::diagnose` reads a model.

use dm_bundle::Bundle;
use dm_fit::material_fit::{MaterialFitConfig, fit_material};
use dm_model::{ModelOptions, ResidualKind, WorldModel};
use std::path::{Path, PathBuf};

/// `bundle`'s default physics-only model after `iterations` material
/// steps, written to `dir/model.json`; returns `dir`.
pub fn fit_physics_only(bundle: &Bundle, iterations: usize, dir: &Path) -> PathBuf {
    let options = ModelOptions {
        residual: ResidualKind::None,
        ..ModelOptions::default()
    };
    let mut model = WorldModel::from_bundle(bundle, &options).expect("model");
    let fit = MaterialFitConfig {
        iterations,
        ..MaterialFitConfig::default()
    };
    fit_material(&mut model, bundle, &fit, &mut |_| {}).expect("base fit");
    std::fs::create_dir_all(dir).expect("model dir");
    dm_bundle::write_json_atomic(&dir.join("model.json"), &model).expect("model.json");
    dir.to_path_buf()
}
