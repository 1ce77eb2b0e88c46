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

/// The scene bundle and its truth file, errors naming the file.
pub fn open_scene(
    bundle: &std::path::Path,
    truth: &std::path::Path,
) -> anyhow::Result<(dm_bundle::Bundle, TruthFile)> {
    use anyhow::Context;
    let opened = dm_bundle::Bundle::open(bundle)
        .with_context(|| format!("reading bundle {}", bundle.display()))?;
    let truth_file: TruthFile =
        dm_bundle::read_json(truth).with_context(|| format!("reading {}", truth.display()))?;
    Ok((opened, truth_file))
}

/// Actuator values that replace the start model's where given.
#[derive(clap::Args, Clone, Copy, Debug)]
pub struct GripOverride {
    /// Spring gain k_p (1/s²).
    #[arg(long)]
    pub kp: Option<f64>,
    /// Damper gain k_d (1/s).
    #[arg(long)]
    pub kd: Option<f64>,
    /// Grasp radius (m).
    #[arg(long)]
    pub grasp_radius: Option<f64>,
}

impl GripOverride {
    pub fn apply(&self, actuator: &mut dm_mpm::ActuatorConfig) {
        if let Some(kp) = self.kp {
            actuator.kp = kp;
        }
        if let Some(kd) = self.kd {
            actuator.kd = kd;
        }
        if let Some(radius) = self.grasp_radius {
            actuator.grasp_radius = radius;
        }
    }
}
