// Each example uses a part of these helpers.
#![allow(dead_code)]

//! What the issue-3 analysis examples share: the bundle's model set to the
//! synthetic scene's true homogeneous material.

use dm_model::WorldModel;
use dm_synth::TruthFile;

/// `model` with the truth's homogeneous material: its E, ν and expert mix
/// on every patch (the gains and everything else kept).
pub fn with_true_material(model: &WorldModel, truth: &TruthFile) -> WorldModel {
    with_material(model, truth, 1.0, 0.0)
}

/// `model` with the truth's material, E scaled by `youngs_factor` and ν
/// moved by `poisson_shift`.
pub fn with_material(
    model: &WorldModel,
    truth: &TruthFile,
    youngs_factor: f64,
    poisson_shift: f64,
) -> WorldModel {
    let mut moved = model.clone();
    moved.params = dm_mpm::PatchParams::uniform(
        model.patches.patch_count(),
        &model.bounds,
        youngs_factor * truth.material.e_pa,
        truth.material.nu + poisson_shift,
        dm_synth::truth::HOMOGENEOUS_EXPERT_WEIGHTS.map(f64::ln),
    );
    moved
}
