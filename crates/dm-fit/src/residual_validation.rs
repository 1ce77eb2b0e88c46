//! `--residual-validate`: whether the residual network helps on frames it
//! has not seen, decided on the training clip alone.
//!
//! Every score inside the fit (the training loss, the late-frames loss of
//! `--residual-keep late-frames`) is taken on frames the network trained
//! on. On a rope without any hidden effect the network lowered all of them
//! and still raised the held-out error by 27 % (docs/RESULTS.md, issue 4):
//! what it learnt on the hands' slow start did not hold on their faster
//! motion later. So the same fit runs twice on the first 70 % of the
//! training frames, with the network and without it, and both are rolled
//! out open loop over the remaining 30 %, which neither has seen. The full
//! fit keeps the network only if it was the better of the two there.

use crate::material_fit::{FitError, LATE_FRAMES_SHARE, fit_frames, train_frame_losses};
use crate::run::{FitOptions, FitOutcome, fit_stages, material_config};
use dm_bundle::Bundle;
use dm_model::{ResidualKind, WorldModel};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Where the two shortened fits are written, under the model directory.
pub const VALIDATION_DIR: &str = "residual_validation";

/// The decision and its evidence (`residual.validation` in fit_report.json).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResidualValidation {
    /// The shortened fits trained on frames `[0, fit_frames)`.
    pub fit_frames: usize,
    /// Frames scored, `[start, end)`: the rest of the training split.
    pub scored_frames: [usize; 2],
    /// Mean L_dyn (m²) over the scored frames of the shortened fit with
    /// the network, rolled out open loop from frame 0.
    pub loss_with: f64,
    /// The same for the shortened fit without it.
    pub loss_without: f64,
    /// Whether the full fit keeps the network (`loss_with < loss_without`).
    pub kept: bool,
}

/// Frames the shortened fits train on: the training split less its last
/// [`LATE_FRAMES_SHARE`], at least 2, leaving at least one frame to score.
pub fn validation_fit_frames(frames: usize) -> Result<usize, FitError> {
    let fit = (frames as f64 * (1.0 - LATE_FRAMES_SHARE)).round() as usize;
    if fit < 2 || fit >= frames {
        return Err(FitError::InvalidOption {
            option: "--residual-validate".into(),
            problem: format!(
                "the training split has {frames} frames; a shortened fit of at least 2 frames \
                 and at least one frame to score it need 3"
            ),
        });
    }
    Ok(fit)
}

/// Mean of the per-frame losses of `model`'s open-loop rollout over the
/// frames `[start, end)` (frame 0 is the start state and has none).
pub fn scored_loss(
    model: &WorldModel,
    bundle: &Bundle,
    [start, end]: [usize; 2],
) -> Result<f64, FitError> {
    // train_frame_losses()[i] is the loss of frame i + 1.
    let losses = train_frame_losses(model, bundle, end)?;
    let scored = &losses[start - 1..end - 1];
    Ok(scored.iter().sum::<f64>() / scored.len() as f64)
}

/// The model without its network, as `--residual none` would have built it.
pub fn without_residual(mut model: WorldModel) -> WorldModel {
    model.residual = None;
    model.options.residual = ResidualKind::None;
    model
}

/// Runs the two shortened fits of `start` (a model with a network) under
/// `out/`[`VALIDATION_DIR`] and scores them. With `resume`, each continues
/// from its own checkpoint.
pub fn validate_residual(
    bundle: &Bundle,
    options: &FitOptions,
    start: &WorldModel,
    out: &Path,
    resume: bool,
    progress: &mut dyn FnMut(&str),
) -> Result<ResidualValidation, FitError> {
    let frames = fit_frames(bundle, &material_config(options, 0));
    let fit = validation_fit_frames(frames)?;
    let shortened = |residual: ResidualKind| FitOptions {
        model: dm_model::ModelOptions {
            residual,
            ..options.model.clone()
        },
        train_frames: Some(fit),
        residual_validate: false,
        // The decision is about the dynamics: no splats, no bound.
        rgb_iters: 0,
        identifiability: false,
        ..options.clone()
    };
    let variants = [
        ("with", shortened(options.model.residual), start.clone()),
        (
            "without",
            shortened(ResidualKind::None),
            without_residual(start.clone()),
        ),
    ];
    let mut losses = [0.0; 2];
    for (slot, (name, sub_options, model)) in losses.iter_mut().zip(variants) {
        let dir = out.join(VALIDATION_DIR).join(name);
        progress(&format!(
            "residual validation: fitting frames 0–{} {name} the network",
            fit - 1
        ));
        let mut sub_progress = |message: &str| progress(&format!("  [{name}] {message}"));
        let fitted = match fit_stages(
            bundle,
            &sub_options,
            &dir,
            resume,
            None,
            Some(model),
            &mut sub_progress,
        )? {
            FitOutcome::Finished(_) => dm_bundle::read_json::<WorldModel>(&dir.join("model.json"))?,
            FitOutcome::Paused { .. } => unreachable!("a fit without --stop-after runs to the end"),
        };
        *slot = scored_loss(&fitted, bundle, [fit, frames])?;
    }
    let [loss_with, loss_without] = losses;
    let validation = ResidualValidation {
        fit_frames: fit,
        scored_frames: [fit, frames],
        loss_with,
        loss_without,
        kept: loss_with < loss_without,
    };
    progress(&format!(
        "residual validation: frames {fit}–{} open loop, loss {loss_with:.3e} m² with the network, \
         {loss_without:.3e} without: {}",
        frames - 1,
        if validation.kept {
            "keeping it"
        } else {
            "fitting without it"
        }
    ));
    Ok(validation)
}
