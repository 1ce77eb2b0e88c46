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

use crate::learnt_effects::{self, ExtensionGrads, ForceFieldTerms};
use crate::loss::{
    LengthPreservation, LossTerms, LossWeights, ObservedFrame, PairSelection, TrackMatch,
    frame_loss,
};
use crate::optim::{
    Adam, AdamConfig, ClipConfig, OptimError, ParamSet, clip_global_norm, clip_physics_gradients,
};
use dm_bundle::Bundle;
use dm_model::device::{Device, DeviceWorld};
use dm_model::residual::{
    FrameStart, apply_residual, frame_inputs, frame_start, residual_backward,
};
use dm_model::{ExpertChoice, ModelError, WorldModel};
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::real::Vec3;
use dm_mpm::tape::EffectGrads;
use dm_mpm::{PatchParams, SimError};
use serde::{Deserialize, Serialize};
use std::time::Instant;

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
    #[error(transparent)]
    Appearance(#[from] dm_appearance::AppearanceError),
    #[error(transparent)]
    Chart(#[from] dm_view::ViewError),
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
    /// Adam rate of the learnt effect terms (None: `learning_rate`;
    /// [`crate::learnt_effects::group_rates`]).
    #[serde(default)]
    pub effect_learning_rate: Option<f64>,
    /// Substeps differentiated per frame (truncated BPTT).
    pub window: usize,
    /// Frames used (default: the bundle's train split).
    pub frames: Option<usize>,
    /// Adam learning rate of the residual network (method.md §5: 5e-3).
    pub residual_learning_rate: f64,
    /// Step the residual network only; the material stays as it is.
    pub freeze_material: bool,
    /// Also step the effect terms the model has switched on (drag and
    /// viscosity coefficients, a ground tilt) beside the material
    /// ([`crate::learnt_effects`]).
    #[serde(default = "learn_effects_by_default")]
    pub learn_effects: bool,
    /// Also step the particle damping rate, at most the category's default
    /// ([`crate::learnt_effects::write_back_damping`]).
    #[serde(default)]
    pub learn_damping: bool,
    /// Also step these terms of the grid's body force (a uniform push,
    /// drag along each world axis, a spring towards the model's attractor
    /// point), from wherever the model has them
    /// ([`crate::learnt_effects::FORCE_FIELD_GROUP`]).
    #[serde(default)]
    pub force_field_terms: ForceFieldTerms,
    /// Where the MPM world and its adjoint run (the residual network, the
    /// losses and the optimiser stay on the CPU).
    #[serde(default)]
    pub device: Device,
}

fn learn_effects_by_default() -> bool {
    true
}

impl MaterialFitConfig {
    /// A fresh Adam with [`Self::adam_config`].
    pub fn adam(&self, model: &WorldModel) -> Result<Adam, OptimError> {
        Adam::new(self.adam_config(model))
    }

    /// Adam's settings: the material learning rate and, for a model with a
    /// residual, the network's own (Adam refuses rates for absent groups).
    pub fn adam_config(&self, model: &WorldModel) -> AdamConfig {
        let mut config = AdamConfig::with_learning_rate(self.learning_rate);
        if model.residual.is_some() {
            config
                .group_learning_rates
                .insert(RESIDUAL_GROUP.into(), self.residual_learning_rate);
        }
        if self.learn_effects && !self.freeze_material {
            for (group, rate) in learnt_effects::group_rates(
                model,
                self.effect_learning_rate.unwrap_or(self.learning_rate),
            ) {
                config.group_learning_rates.insert(group.into(), rate);
            }
        }
        let effect_rate = self.effect_learning_rate.unwrap_or(self.learning_rate);
        if self.learn_damping && !self.freeze_material {
            config.group_learning_rates.insert(
                learnt_effects::DAMPING_GROUP.into(),
                learnt_effects::DAMPING_RATE_FACTOR * effect_rate,
            );
        }
        if self.force_field_terms.any() && !self.freeze_material {
            config.group_learning_rates.insert(
                learnt_effects::FORCE_FIELD_GROUP.into(),
                learnt_effects::FORCE_FIELD_RATE_FACTOR * effect_rate,
            );
        }
        config
    }
}

impl Default for MaterialFitConfig {
    fn default() -> Self {
        Self {
            iterations: 20,
            learning_rate: 0.1,
            effect_learning_rate: None,
            window: 20,
            frames: None,
            residual_learning_rate: 5e-3,
            freeze_material: false,
            learn_effects: true,
            learn_damping: false,
            force_field_terms: ForceFieldTerms::NONE,
            device: Device::Cpu,
        }
    }
}

/// One iteration's record.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IterationReport {
    pub iteration: usize,
    /// Mean loss L_dyn over the frames (m²), before the step; in stage 3
    /// it includes the weighted photometric term (see `rgb_l1`).
    pub loss: f64,
    pub youngs_median_pa: f64,
    pub poisson_median: f64,
    pub seconds: f64,
    /// Stage 3: mean masked L1 of the frozen Gaussians over the training
    /// frames and cameras (per pixel and channel), before the step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rgb_l1: Option<f64>,
    /// L_dyn over the last 30 % of the fitted frames, before the step
    /// ([`late_frames_loss`]); a report without it reads as `None`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub late_loss: Option<f64>,
    /// Where the step's `seconds` went (the rest: the optimiser's update);
    /// a report without it reads as zeros.
    #[serde(default)]
    pub phase_seconds: StepPhases,
}

/// Seconds of one loss-and-gradient pass by phase: the forward frames
/// (the world, the residual network's correction), L_dyn's terms on the
/// frames' positions, stage 3's photometric term, and the backward frames
/// (each frame's taped window run again, its adjoint, the network's VJP);
/// of the forward and backward frames, the residual network's share
/// (its inputs and Δv moved between the world and the network, the
/// network itself, its VJP).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StepPhases {
    pub forward: f64,
    pub loss: f64,
    pub photometric: f64,
    pub backward: f64,
    #[serde(default)]
    pub forward_residual: f64,
    #[serde(default)]
    pub backward_residual: f64,
}

impl std::ops::AddAssign for StepPhases {
    fn add_assign(&mut self, other: Self) {
        self.forward += other.forward;
        self.loss += other.loss;
        self.photometric += other.photometric;
        self.backward += other.backward;
        self.forward_residual += other.forward_residual;
        self.backward_residual += other.backward_residual;
    }
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

/// Parameter group of the residual network's weights in the optimiser.
pub const RESIDUAL_GROUP: &str = "residual";
/// Gradient-norm clip of the residual network (method.md §5).
pub const RESIDUAL_CLIP_NORM: f64 = 5.0;

/// Weight of the residual's regulariser Σ_p |Δv_p|² / n (method.md §5).
pub const RESIDUAL_REGULARISER: f64 = 1e-3;

/// A frame term's value and its gradient with respect to the positions.
pub type TermValue = (f64, Vec<[f64; 3]>);

/// An extra per-frame loss term (stage 3's photometric term), given the
/// predicted particle positions at the end of frames `first`, `first + 1`,
/// … (calls continue where the last one ended: frames 1, 2, … of the
/// forward rollout, in order); returns each frame's value and its gradient
/// with respect to that frame's positions.
pub trait FrameTerm {
    fn frames(
        &mut self,
        first: usize,
        positions: &[Vec<[f64; 3]>],
    ) -> Result<Vec<TermValue>, FitError>;

    /// [`FrameTerm::frames`] for one frame.
    fn frame(&mut self, frame: usize, positions: &[[f64; 3]]) -> Result<TermValue, FitError> {
        let mut terms = self.frames(frame, &[positions.to_vec()])?;
        terms.pop().ok_or_else(|| FitError::InvalidOption {
            option: "frames".into(),
            problem: "the frame term returned no value".into(),
        })
    }
}

/// Gradients of the train loss.
#[derive(Clone, Debug, PartialEq)]
pub struct LossGradients {
    /// Per-patch material parameters.
    pub patches: PatchParams,
    /// Residual network weights (when the model has a residual).
    pub residual: Option<Vec<f64>>,
    /// L_dyn of each predicted frame 1, 2, … (before the step; without the
    /// regulariser and the extra term), for [`late_frames_loss`].
    pub frame_losses: Vec<f64>,
    /// Gradients of the effect terms (drag, viscosity, friction, gravity), summed
    /// over the differentiated frames.
    pub effects: EffectGrads,
    /// Gradients of the model extension's stiff ball and density gradient.
    pub extension: ExtensionGrads,
    /// Where the pass's time went.
    pub phases: StepPhases,
}

/// Share of the fitted frames, at their end, that [`late_frames_loss`]
/// averages: the same share as the held-out split that follows them.
pub const LATE_FRAMES_SHARE: f64 = 0.3;

/// Mean of the last [`LATE_FRAMES_SHARE`] of `frame_losses` (at least one
/// frame): how well an open-loop rollout holds up where it has drifted
/// longest, the nearest thing inside the training frames to the held-out
/// frames after them.
pub fn late_frames_loss(frame_losses: &[f64]) -> f64 {
    if frame_losses.is_empty() {
        return f64::INFINITY;
    }
    let count = ((frame_losses.len() as f64 * LATE_FRAMES_SHARE).round() as usize)
        .clamp(1, frame_losses.len());
    let late = &frame_losses[frame_losses.len() - count..];
    late.iter().sum::<f64>() / count as f64
}

/// The train-split loss L_dyn (+ the residual's regulariser) of `model`
/// over `frames` frames and its gradient with respect to the patch
/// parameters and the residual's weights; `extra` adds a per-frame term.
pub fn loss_and_gradient(
    model: &WorldModel,
    bundle: &Bundle,
    frames: usize,
    window: usize,
    extra: Option<&mut dyn FrameTerm>,
) -> Result<(f64, LossGradients), FitError> {
    loss_and_gradient_on(model, bundle, frames, window, Device::Cpu, extra)
}

/// [`loss_and_gradient`] with the MPM world and its adjoint on `device`.
pub fn loss_and_gradient_on(
    model: &WorldModel,
    bundle: &Bundle,
    frames: usize,
    window: usize,
    device: Device,
    extra: Option<&mut dyn FrameTerm>,
) -> Result<(f64, LossGradients), FitError> {
    let frames = frames.min(bundle.frame_count());
    if frames < 2 {
        return Err(FitError::InvalidOption {
            option: "frames".into(),
            problem: "need at least 2 frames".into(),
        });
    }
    let steps = frames - 1;
    let mut world = DeviceWorld::of_model(model, device)?;
    let network = model.residual_network_on(device)?;
    let n = world.particle_count();
    let fixed = FixedTerms::new(model, bundle)?;
    // Σ_p |Δv_p|² / n per frame, averaged over frames like L_dyn.
    let regulariser = RESIDUAL_REGULARISER / (n * steps) as f64;

    // Forward: the state entering each frame's taped window (the backward
    // pass runs only that window again), loss gradients at frame ends.
    let mut checkpoints = Vec::with_capacity(steps);
    let mut starts: Vec<FrameStart> = Vec::with_capacity(steps);
    let mut corrections = Vec::with_capacity(steps);
    let mut frame_grads: Vec<Vec<[f64; 3]>> = Vec::with_capacity(steps);
    let mut frame_losses = Vec::with_capacity(steps);
    // Per frame: the regulariser's and L_dyn's parts of the loss, summed
    // with the extra term's in frame order once that is known.
    let mut loss_parts = Vec::with_capacity(steps);
    // The extra term's inputs: every frame's positions, taken together
    // after the rollout (its views are independent of each other).
    let mut extra_positions = Vec::new();
    let substeps = world.config().substeps_per_frame;
    let window_start = substeps - window.min(substeps);
    let mut phases = StepPhases::default();
    let mut clock = Instant::now();
    for t in 0..steps {
        if network.is_some() {
            let residual_clock = Instant::now();
            starts.push(frame_start(world.host()?));
            phases.forward_residual += residual_clock.elapsed().as_secs_f64();
        }
        let (from, to, grasp) = model.hand_step(bundle, t);
        checkpoints.push(world.step_frame_keeping(&from, &to, &grasp, window_start)?);
        let mut regularised = 0.0;
        if let Some(network) = &network {
            let residual_clock = Instant::now();
            let (dv, _) = world.edit(|w| apply_residual(w, network, &starts, t))??;
            regularised = regulariser * dv.iter().flatten().map(|c| c * c).sum::<f64>();
            corrections.push(dv);
            phases.forward_residual += residual_clock.elapsed().as_secs_f64();
        }
        phases.forward += lap(&mut clock);
        let positions = world.positions()?;
        let value = fixed.frame(bundle, t + 1, &positions)?;
        loss_parts.push((regularised, value.value / steps as f64));
        frame_losses.push(value.value);
        frame_grads.push(
            value
                .grad
                .iter()
                .map(|g| g.map(|c| c / steps as f64))
                .collect::<Vec<[f64; 3]>>(),
        );
        if extra.is_some() {
            extra_positions.push(positions);
        }
        phases.loss += lap(&mut clock);
    }
    let extra_terms = match extra {
        Some(term) => term.frames(1, &extra_positions)?,
        None => Vec::new(),
    };
    phases.photometric += lap(&mut clock);
    let mut loss = 0.0;
    for (t, (regularised, dynamic)) in loss_parts.into_iter().enumerate() {
        loss += regularised;
        loss += dynamic;
        if let Some((value, term_grad)) = extra_terms.get(t) {
            loss += value;
            for (g, d) in frame_grads[t].iter_mut().zip(term_grad) {
                for c in 0..3 {
                    g[c] += d[c];
                }
            }
        }
    }

    // Backward: replay each frame with a tape, newest first.
    let mut carried = ParticleGrads::<f32>::zeros(n);
    let mut grad_mu = vec![0.0f32; n];
    let mut grad_lambda = vec![0.0f32; n];
    let mut grad_weights = vec![[0.0f32; 3]; n];
    let mut grad_residual = network.as_ref().map(|net| vec![0.0; net.parameter_count()]);
    let mut grad_effects = EffectGrads::default();
    let mut grad_mass = vec![0.0f64; n];
    for t in (0..steps).rev() {
        for (c, g) in carried.x.iter_mut().zip(&frame_grads[t]) {
            *c += Vec3::new(g[0] as f32, g[1] as f32, g[2] as f32);
        }
        world.set_state(&checkpoints[t])?;
        let (from, to, _) = model.hand_step(bundle, t);
        let tape = world.step_frame_rest_taped(&from, &to, window)?;
        let mut x_start_grad = None;
        if let (Some(network), Some(grad_residual)) = (&network, grad_residual.as_mut()) {
            let residual_clock = Instant::now();
            let inputs = frame_inputs(world.host()?, &starts, t);
            let correction = world.edit(|w| w.apply_velocity_correction(&corrections[t]))??;
            let grads = residual_backward(
                network,
                &inputs,
                &corrections[t],
                &correction,
                &mut carried,
                regulariser,
            )?;
            grad_residual
                .iter_mut()
                .zip(&grads.parameters)
                .for_each(|(g, d)| *g += d);
            x_start_grad = Some(grads.x_start);
            phases.backward_residual += residual_clock.elapsed().as_secs_f64();
        }
        let g = world.backward_frame(&tape, &carried)?;
        grad_effects += g.effects;
        for (sum, g) in grad_mass.iter_mut().zip(&g.mass) {
            *sum += f64::from(*g);
        }
        for p in 0..n {
            grad_mu[p] += g.mu[p];
            grad_lambda[p] += g.lambda[p];
            for e in 0..3 {
                grad_weights[p][e] += g.weights[p][e];
            }
        }
        carried = g.state;
        if let Some(x_start_grad) = x_start_grad {
            for (c, g) in carried.x.iter_mut().zip(&x_start_grad) {
                *c += Vec3::new(g[0] as f32, g[1] as f32, g[2] as f32);
            }
        }
    }
    phases.backward += lap(&mut clock);
    let extension = &model.extension;
    let masses: Vec<f64> = world.state()?.mass.iter().map(|m| f64::from(*m)).collect();
    let grad_extension = ExtensionGrads {
        // The base material is rebuilt only when a ball needs it.
        stiffness_log_factor: match extension.stiff_ball {
            Some(_) => extension.stiffness_log_factor_gradient(
                &model.particles,
                &model.particle_material(),
                &grad_mu,
                &grad_lambda,
            ),
            None => 0.0,
        },
        density_excess: extension.density_excess_gradient(&model.particles, &masses, &grad_mass),
        density_axis: extension.density_axis_gradient(&model.particles, &masses, &grad_mass),
    };
    // The fitted fields are the material before the stiff ball scales it.
    extension.base_material_grads(&model.particles, &mut grad_mu, &mut grad_lambda);
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
    Ok((
        loss,
        LossGradients {
            patches: grads,
            residual: grad_residual,
            frame_losses,
            effects: grad_effects,
            extension: grad_extension,
            phases,
        },
    ))
}

/// Seconds since `clock`, which restarts.
fn lap(clock: &mut Instant) -> f64 {
    let now = Instant::now();
    let seconds = now.duration_since(*clock).as_secs_f64();
    *clock = now;
    seconds
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

/// One clipped Adam step of the material stage on `model` (in place);
/// `extra` adds a per-frame term to L_dyn (stage 3).
pub fn material_step(
    model: &mut WorldModel,
    bundle: &Bundle,
    config: &MaterialFitConfig,
    adam: &mut Adam,
    iteration: usize,
    extra: Option<&mut dyn FrameTerm>,
) -> Result<IterationReport, FitError> {
    let start = std::time::Instant::now();
    let (loss, grads) = loss_and_gradient_on(
        model,
        bundle,
        fit_frames(bundle, config),
        config.window,
        config.device,
        extra,
    )?;
    let late_loss = late_frames_loss(&grads.frame_losses);
    let mut all_grads = to_param_set(&grads.patches)?;
    let mut params = to_param_set(&model.params)?;
    let learn_effects = config.learn_effects && !config.freeze_material;
    if learn_effects {
        // Physics groups like E: clipped per group and globally with it.
        (params, all_grads) =
            learnt_effects::add_groups(model, &grads.effects, &grads.extension, params, all_grads)?;
    }
    let learn_damping = config.learn_damping && !config.freeze_material;
    if learn_damping {
        (params, all_grads) =
            learnt_effects::add_damping_group(&model.physics, &grads.effects, params, all_grads)?;
    }
    let learn_force_field = config.force_field_terms.any() && !config.freeze_material;
    if learn_force_field {
        (params, all_grads) = learnt_effects::add_force_field_group(
            &model.physics,
            &grads.effects,
            config.force_field_terms,
            params,
            all_grads,
        )?;
    }
    clip_physics_gradients(&mut all_grads, &ClipConfig::default())?;
    let (youngs, poisson) = model.material_medians();
    if let (Some(residual_grads), Some(state)) = (grads.residual, model.residual.as_ref()) {
        let mut residual_grads = ParamSet::new().with_group(RESIDUAL_GROUP, residual_grads)?;
        clip_global_norm(&mut residual_grads, RESIDUAL_CLIP_NORM)?;
        let clipped = residual_grads
            .get(RESIDUAL_GROUP)
            .unwrap_or_default()
            .to_vec();
        all_grads = all_grads.with_group(RESIDUAL_GROUP, clipped)?;
        params = params.with_group(RESIDUAL_GROUP, state.parameters.clone())?;
    }
    if config.freeze_material {
        // Only the residual's group is stepped: the stage's own Adam holds
        // moments of that group alone (see `Stage::Residual`).
        let residual_only = |set: &ParamSet| match set.get(RESIDUAL_GROUP) {
            Some(values) => ParamSet::new().with_group(RESIDUAL_GROUP, values.to_vec()),
            None => Ok(ParamSet::new()),
        };
        params = residual_only(&params)?;
        all_grads = residual_only(&all_grads)?;
    }
    adam.step(&mut params, &all_grads)?;
    if !config.freeze_material {
        from_param_set(&params, &mut model.params);
    }
    if learn_effects {
        learnt_effects::write_back(model, &params);
    }
    if learn_damping {
        learnt_effects::write_back_damping(
            &mut model.physics,
            &params,
            dm_model::default_particle_damping(bundle.meta.category),
        );
    }
    if learn_force_field {
        learnt_effects::write_back_force_field(
            &mut model.physics,
            &params,
            config.force_field_terms,
        );
    }
    if let (Some(state), Some(values)) = (model.residual.as_mut(), params.get(RESIDUAL_GROUP)) {
        state.parameters.copy_from_slice(values);
    }
    Ok(IterationReport {
        iteration,
        loss,
        youngs_median_pa: youngs,
        poisson_median: poisson,
        seconds: start.elapsed().as_secs_f64(),
        rgb_l1: None,
        late_loss: Some(late_loss),
        phase_seconds: grads.phases,
    })
}

/// Runs the material stage on `model` in place, reporting each iteration.
pub fn fit_material(
    model: &mut WorldModel,
    bundle: &Bundle,
    config: &MaterialFitConfig,
    on_iteration: &mut dyn FnMut(&IterationReport),
) -> Result<Vec<IterationReport>, FitError> {
    let mut adam = config.adam(model)?;
    let mut reports = Vec::with_capacity(config.iterations);
    for iteration in 0..config.iterations {
        let report = material_step(model, bundle, config, &mut adam, iteration, None)?;
        on_iteration(&report);
        reports.push(report);
    }
    Ok(reports)
}

/// Forward-only mean loss L_dyn over the first `frames` frames (for the
/// gain search); a diverging rollout scores infinity.
pub fn train_loss(model: &WorldModel, bundle: &Bundle, frames: usize) -> Result<f64, FitError> {
    train_loss_on(model, bundle, frames, Device::Cpu)
}

/// [`train_loss`] with the MPM world on `device`.
pub fn train_loss_on(
    model: &WorldModel,
    bundle: &Bundle,
    frames: usize,
    device: Device,
) -> Result<f64, FitError> {
    let losses = train_frame_losses_on(model, bundle, frames, device)?;
    Ok(losses.iter().sum::<f64>() / losses.len().max(1) as f64)
}

/// Forward-only L_dyn of each predicted frame 1, 2, … up to `frames`; a
/// diverging rollout scores infinity on every frame.
pub fn train_frame_losses(
    model: &WorldModel,
    bundle: &Bundle,
    frames: usize,
) -> Result<Vec<f64>, FitError> {
    train_frame_losses_on(model, bundle, frames, Device::Cpu)
}

/// [`train_frame_losses`] with the MPM world on `device`.
pub fn train_frame_losses_on(
    model: &WorldModel,
    bundle: &Bundle,
    frames: usize,
    device: Device,
) -> Result<Vec<f64>, FitError> {
    let frames = frames.min(bundle.frame_count());
    let steps = frames.saturating_sub(1);
    let fixed = FixedTerms::new(model, bundle)?;
    let mut world = DeviceWorld::of_model(model, device)?;
    let network = model.residual_network_on(device)?;
    let mut starts: Vec<FrameStart> = Vec::new();
    let mut losses = Vec::with_capacity(steps);
    for t in 0..steps {
        if network.is_some() {
            starts.push(frame_start(world.host()?));
        }
        let (from, to, grasp) = model.hand_step(bundle, t);
        if world.step_frame(&from, &to, &grasp).is_err() {
            return Ok(vec![f64::INFINITY; steps]);
        }
        if let Some(network) = &network {
            world.edit(|w| apply_residual(w, network, &starts, t))??;
        }
        losses.push(fixed.frame(bundle, t + 1, &world.positions()?)?.value);
    }
    Ok(losses)
}
