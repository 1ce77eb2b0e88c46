//! How sharply a clip pins the fitted material: the relative rise of the
//! training loss when the fitted E or ν is moved by the recovery tolerances
//! (E ×0.75 / ×1.25, ν ∓0.05), everything else held.
//!
//! A parameter the clip does not constrain is still given a value by the
//! fit; this says which values to trust. On the rope stretch scene, ν
//! ±0.05 changes the held-out Chamfer by ≤ 0.02 mm of 4.2 (docs/RESULTS.md):
//! ν there is whatever the optimiser's path left it at.

use crate::material_fit::{FitError, train_loss_on};
use dm_bundle::Bundle;
use dm_model::WorldModel;
use dm_model::device::Device;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Multiplicative step on E and additive step on ν probed on each side.
pub const YOUNGS_FACTORS: [f64; 2] = [0.75, 1.25];
pub const POISSON_SHIFT: f64 = 0.05;

/// `fit_report.json` `material.sensitivity`: the training loss of each
/// moved material relative to the fitted one, minus 1 (0.01 = 1 % higher;
/// negative: the move lowers the loss; `null` in JSON: the moved rollout
/// diverged).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaterialSensitivity {
    #[serde(rename = "E_x0.75")]
    pub youngs_down: f64,
    #[serde(rename = "E_x1.25")]
    pub youngs_up: f64,
    #[serde(rename = "nu_minus_0.05")]
    pub poisson_down: f64,
    #[serde(rename = "nu_plus_0.05")]
    pub poisson_up: f64,
}

/// `model` with every patch's E multiplied by `youngs_factor` and ν moved
/// by `poisson_shift`, both kept inside the model's bounds.
pub fn moved_material(model: &WorldModel, youngs_factor: f64, poisson_shift: f64) -> WorldModel {
    let bounds = model.bounds;
    let mut moved = model.clone();
    for raw in &mut moved.params.youngs_raw {
        *raw = bounds.youngs_raw(youngs_factor * bounds.youngs(*raw));
    }
    for raw in &mut moved.params.poisson_raw {
        *raw = bounds.poisson_raw(bounds.poisson(*raw) + poisson_shift);
    }
    moved
}

/// Probes the four moves on the first `frames` frames with the MPM world
/// on `device`; `base_loss` is the fitted model's own training loss there.
pub fn material_sensitivity(
    model: &WorldModel,
    bundle: &Bundle,
    frames: usize,
    base_loss: f64,
    device: Device,
) -> Result<MaterialSensitivity, FitError> {
    let relative = |youngs_factor: f64, poisson_shift: f64| -> Result<f64, FitError> {
        let loss = train_loss_on(
            &moved_material(model, youngs_factor, poisson_shift),
            bundle,
            frames,
            device,
        )?;
        Ok(loss / base_loss - 1.0)
    };
    // Four independent rollouts, side by side (each is deterministic).
    let moves = [
        (YOUNGS_FACTORS[0], 0.0),
        (YOUNGS_FACTORS[1], 0.0),
        (1.0, -POISSON_SHIFT),
        (1.0, POISSON_SHIFT),
    ];
    let changes = moves
        .par_iter()
        .map(|&(factor, shift)| relative(factor, shift))
        .collect::<Vec<_>>()
        .into_iter()
        // The first failing move's error, whatever the thread count.
        .collect::<Result<Vec<f64>, FitError>>()?;
    Ok(MaterialSensitivity {
        youngs_down: changes[0],
        youngs_up: changes[1],
        poisson_down: changes[2],
        poisson_up: changes[3],
    })
}
