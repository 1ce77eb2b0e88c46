//! Stage 1 of the fit (method.md §7): the material fields (per-patch E, ν
//! and expert logits) learnt by gradient descent through the
//! differentiable simulator on the train frames.
//!
//! One iteration: an open-loop rollout from frame 0 driven by the observed
//! hands, keeping each frame's start state; the loss L_dyn of every frame
//! (track + shape + length preservation, `LossWeights`);
//! then frames are replayed backwards, each re-simulated with a tape of
//! its last `window` substeps and differentiated, the state adjoint
//! carried from frame to frame (truncated BPTT); the per-particle
//! material gradients go back to the patches, and Adam takes a clipped step.

use crate::loss::{
    LengthPreservation, LossTerms, LossWeights, ObservedFrame, PairSelection, TrackMatch,
    frame_loss,
};
use crate::optim::{Adam, AdamConfig, ClipConfig, OptimError, ParamSet, clip_physics_gradients};
use dm_bundle::Bundle;
use dm_model::{ExpertChoice, ModelError, WorldModel, hand_step};
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::real::Vec3;
use dm_mpm::{PatchParams, SimError};
use serde::{Deserialize, Serialize};

/// Why a fit failed.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error(transparent)]
    Simulation(#[from] SimError),
    #[error(transparent)]
    Optimiser(#[from] OptimError),
    #[error(transparent)]
    Loss(#[from] crate::loss::LossError),
    #[error(transparent)]
    Bundle(#[from] dm_bundle::BundleError),
    #[error("invalid fit option `{option}`: {problem}")]
    InvalidOption { option: String, problem: String },
}

/// Options of the material stage.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaterialFitConfig {
    /// Gradient steps.
    pub iterations: usize,
    /// Adam learning rate on the unbounded parameters.
    pub learning_rate: f64,
    /// Substeps differentiated per frame (truncated BPTT).
    pub window: usize,
    /// Frames used (default: the bundle's train split).
    pub frames: Option<usize>,
}

impl Default for MaterialFitConfig {
    fn default() -> Self {
        Self {
            iterations: 20,
            learning_rate: 0.1,
            window: 20,
            frames: None,
        }
    }
}

/// One iteration's record.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IterationReport {
    pub iteration: usize,
    /// Mean loss L_dyn over the frames (m²), before the step.
    pub loss: f64,
    pub youngs_median_pa: f64,
    pub poisson_median: f64,
    pub seconds: f64,
}

/// What stays fixed over a fit: frame-0 track matches and length pairs.
struct FixedTerms {
    track: TrackMatch,
    length: LengthPreservation,
    surface_count: usize,
}

impl FixedTerms {
    fn new(model: &WorldModel, bundle: &Bundle) -> Result<Self, FitError> {
        Ok(Self {
            track: TrackMatch::new(
                &model.particles,
                &ObservedFrame::from_tracks(&bundle.tracks, 0)?.points,
            )?,
            length: LengthPreservation::new(&model.particles, PairSelection::default())?,
            surface_count: model.surface_count,
        })
    }

    /// L_dyn of frame `t` for the predicted positions, with its gradient.
    fn frame(
        &self,
        bundle: &Bundle,
        t: usize,
        predicted: &[[f64; 3]],
    ) -> Result<crate::loss::LossValue, FitError> {
        let terms = LossTerms {
            track: &self.track,
            length: &self.length,
            surface_count: self.surface_count,
        };
        let observed = ObservedFrame::from_tracks(&bundle.tracks, t)?;
        Ok(frame_loss(&LossWeights::default(), &terms, predicted, &observed)?.total)
    }
}

/// The train-split loss L_dyn of `model` over `frames` frames and its
/// gradient with respect to the patch parameters.
pub fn loss_and_gradient(
    model: &WorldModel,
    bundle: &Bundle,
    frames: usize,
    window: usize,
) -> Result<(f64, PatchParams), FitError> {
    let frames = frames.min(bundle.frame_count());
    if frames < 2 {
        return Err(FitError::InvalidOption {
            option: "frames".into(),
            problem: "need at least 2 frames".into(),
        });
    }
    let steps = frames - 1;
    let mut world = model.world()?;
    let n = world.particle_count();
    let fixed = FixedTerms::new(model, bundle)?;

    // Forward: checkpoints at frame starts, loss gradients at frame ends.
    let mut checkpoints = Vec::with_capacity(steps);
    let mut frame_grads: Vec<Vec<[f64; 3]>> = Vec::with_capacity(steps);
    let mut loss = 0.0;
    for t in 0..steps {
        checkpoints.push(world.state());
        let (from, to, grasp) = hand_step(bundle, t);
        world.step_frame(&from, &to, &grasp)?;
        let value = fixed.frame(bundle, t + 1, &world.positions())?;
        loss += value.value / steps as f64;
        frame_grads.push(
            value
                .grad
                .iter()
                .map(|g| g.map(|c| c / steps as f64))
                .collect(),
        );
    }

    // Backward: replay each frame with a tape, newest first.
    let mut carried = ParticleGrads::<f32>::zeros(n);
    let mut grad_mu = vec![0.0f32; n];
    let mut grad_lambda = vec![0.0f32; n];
    let mut grad_weights = vec![[0.0f32; 3]; n];
    for t in (0..steps).rev() {
        for (c, g) in carried.x.iter_mut().zip(&frame_grads[t]) {
            *c += Vec3::new(g[0] as f32, g[1] as f32, g[2] as f32);
        }
        world.set_state(&checkpoints[t])?;
        let (from, to, grasp) = hand_step(bundle, t);
        let tape = world.step_frame_taped(&from, &to, &grasp, window)?;
        let g = world.backward_frame(&tape, &carried)?;
        for p in 0..n {
            grad_mu[p] += g.mu[p];
            grad_lambda[p] += g.lambda[p];
            for e in 0..3 {
                grad_weights[p][e] += g.weights[p][e];
            }
        }
        carried = g.state;
    }
    let mut grads = model.patches.particle_material_vjp(
        &model.params,
        &model.bounds,
        &grad_mu,
        &grad_lambda,
        &grad_weights,
    );
    if model.options.experts == ExpertChoice::Nh {
        // A single expert has no mixture to learn.
        grads.logits.iter_mut().for_each(|l| *l = [0.0; 3]);
    }
    Ok((loss, grads))
}

pub(crate) fn to_param_set(p: &PatchParams) -> Result<ParamSet, OptimError> {
    ParamSet::new()
        .with_group("youngs_raw", p.youngs_raw.clone())?
        .with_group("poisson_raw", p.poisson_raw.clone())?
        .with_group("logits", p.logits.iter().flatten().copied().collect())
}

pub(crate) fn from_param_set(set: &ParamSet, into: &mut PatchParams) {
    if let Some(v) = set.get("youngs_raw") {
        into.youngs_raw.copy_from_slice(v);
    }
    if let Some(v) = set.get("poisson_raw") {
        into.poisson_raw.copy_from_slice(v);
    }
    if let Some(v) = set.get("logits") {
        for (l, chunk) in into.logits.iter_mut().zip(v.chunks_exact(3)) {
            *l = [chunk[0], chunk[1], chunk[2]];
        }
    }
}

/// Frames the material stage uses: the train split unless told otherwise.
pub fn fit_frames(bundle: &Bundle, config: &MaterialFitConfig) -> usize {
    config
        .frames
        .unwrap_or(bundle.meta.split.train[1])
        .min(bundle.frame_count())
}

/// One clipped Adam step of the material stage on `model` (in place).
pub fn material_step(
    model: &mut WorldModel,
    bundle: &Bundle,
    config: &MaterialFitConfig,
    adam: &mut Adam,
    iteration: usize,
) -> Result<IterationReport, FitError> {
    let start = std::time::Instant::now();
    let (loss, grads) =
        loss_and_gradient(model, bundle, fit_frames(bundle, config), config.window)?;
    let mut grads = to_param_set(&grads)?;
    clip_physics_gradients(&mut grads, &ClipConfig::default())?;
    let (youngs, poisson) = model.material_medians();
    let mut params = to_param_set(&model.params)?;
    adam.step(&mut params, &grads)?;
    from_param_set(&params, &mut model.params);
    Ok(IterationReport {
        iteration,
        loss,
        youngs_median_pa: youngs,
        poisson_median: poisson,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Runs the material stage on `model` in place, reporting each iteration.
pub fn fit_material(
    model: &mut WorldModel,
    bundle: &Bundle,
    config: &MaterialFitConfig,
    on_iteration: &mut dyn FnMut(&IterationReport),
) -> Result<Vec<IterationReport>, FitError> {
    let mut adam = Adam::new(AdamConfig::with_learning_rate(config.learning_rate))?;
    let mut reports = Vec::with_capacity(config.iterations);
    for iteration in 0..config.iterations {
        let report = material_step(model, bundle, config, &mut adam, iteration)?;
        on_iteration(&report);
        reports.push(report);
    }
    Ok(reports)
}

/// Forward-only mean loss L_dyn over the first `frames` frames (for the
/// gain search); a diverging rollout scores infinity.
pub fn train_loss(model: &WorldModel, bundle: &Bundle, frames: usize) -> Result<f64, FitError> {
    let frames = frames.min(bundle.frame_count());
    let fixed = FixedTerms::new(model, bundle)?;
    let mut world = model.world()?;
    let mut loss = 0.0;
    for t in 0..frames.saturating_sub(1) {
        let (from, to, grasp) = hand_step(bundle, t);
        if world.step_frame(&from, &to, &grasp).is_err() {
            return Ok(f64::INFINITY);
        }
        loss += fixed.frame(bundle, t + 1, &world.positions())?.value;
    }
    Ok(loss / (frames.saturating_sub(1)).max(1) as f64)
}
