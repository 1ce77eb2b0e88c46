//! The whole fit of one scene (method.md §7): stage 1, material with
//! default actuator gains; CMA-ES selection of the gains warm-started from
//! stage 1; stage 2, material again with the selected gains; the residual
//! network's own stage and the residual check; stage 3 against the images;
//! the report. Each stage is a method of `FitRun`; every step ends with a
//! checkpoint, so an interrupted fit resumes where it stopped.

use crate::identifiability::{
    DEFAULT_TRACK_NOISE_MM, DEFAULT_TRACK_OFFSET_MM, TrackNoise, identifiability_at,
};
use crate::material_fit::{
    FitError, IterationReport, MaterialFitConfig, RESIDUAL_GROUP, fit_frames, late_frames_loss,
    material_step, train_frame_losses_on, train_loss_on,
};
use crate::optim::{Adam, Bounds, Cmaes, CmaesOptions};
use crate::residual_check::{
    ResidualCheck, check_residual, compare_with_physics_only, fit_physics_only,
    physics_only_options,
};
use crate::rgb_stage::{DEFAULT_RGB_WEIGHT, RgbTerm};
use crate::sensitivity::material_sensitivity;
use dm_appearance::{AppearanceOptions, fit_appearance, load_appearance, save_appearance};
use dm_bundle::{Bundle, BundleError, write_file_atomic, write_json_atomic, write_npy_file};
use dm_model::device::Device;
use dm_model::{ActuatorChoice, ModelOptions, WorldModel};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

/// Options of `dm-fit`: its CLI and the run record in `fit_report.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct FitOptions {
    #[command(flatten)]
    pub model: ModelOptions,
    /// Gradient steps of stage 1 (material, default gains).
    #[arg(long, default_value_t = 12)]
    pub iters: usize,
    /// Gradient steps of stage 2 (material, selected gains); why 18:
    /// docs/fit.md.
    #[arg(long, default_value_t = 18)]
    pub stage2_iters: usize,
    /// Adam learning rate on the unbounded material parameters.
    #[arg(long, default_value_t = 0.1)]
    pub lr: f64,
    /// Adam rate of the learnt effect terms (docs/fit.md); unset, it is
    /// `--lr`.
    #[arg(long)]
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub effect_lr: Option<f64>,
    /// Adam learning rate of the residual network (method.md §5).
    #[arg(long, default_value_t = 5e-3)]
    #[serde(default = "default_residual_lr")]
    pub residual_lr: f64,
    /// Gradient steps on the residual network alone after stage 2, the
    /// material and gains frozen (0 skips; only with --residual pgnd|mlp).
    #[arg(long, default_value_t = 36)]
    #[serde(default)]
    pub residual_iters: usize,
    /// Which network the residual-only stage keeps. A run record without
    /// this key reads as `last`.
    #[arg(long, value_enum, default_value_t = ResidualKeep::LateFrames)]
    #[serde(default)]
    pub residual_keep: ResidualKeep,
    /// The residual-only stage's Adam: a fresh one, or stage 2's carried on
    /// (its step count and its moments of the network; docs/fit.md). A run
    /// record without this key reads as `fresh`.
    #[arg(long, value_enum, default_value_t = ResidualAdam::Fresh)]
    #[serde(default)]
    pub residual_adam: ResidualAdam,
    /// Keep the residual network only if it lowers the training Track
    /// error by at least this fraction against the same fit without it (0:
    /// no check). Costs one physics-only fit, in `OUT/residual_check/`.
    #[arg(long, default_value_t = DEFAULT_RESIDUAL_MIN_GAIN, value_parser = parse_min_gain)]
    #[serde(default)]
    pub residual_min_gain: f64,
    /// Substeps differentiated per frame (truncated BPTT).
    #[arg(long, default_value_t = 20)]
    pub window: usize,
    /// Rollouts spent on the CMA-ES gain search (0 keeps the default gains).
    #[arg(long, default_value_t = 24)]
    pub gain_evals: u64,
    /// Seed of the gain search.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Let the gain search also choose the grasp radius (log-scaled in
    /// [5, 60] mm), starting from the model's.
    #[arg(long)]
    #[serde(default)]
    pub search_grasp_radius: bool,
    /// Iterations of stage 3, RGB-guided refinement (method.md §6): the
    /// first-frame Gaussians are fitted, frozen, and their photometric
    /// error joins L_dyn (0 skips the stage and the splat fit).
    #[arg(long, default_value_t = 30)]
    #[serde(default)]
    pub rgb_iters: usize,
    /// Weight of the photometric term L_rgb in stage 3.
    #[arg(long, default_value_t = DEFAULT_RGB_WEIGHT)]
    #[serde(default = "default_rgb_weight")]
    pub rgb_weight: f64,
    /// The particle damping rate: learnt in stages 2 and 3, at most the
    /// category's default (docs/fit.md), or kept at that default. A run
    /// record without this key reads as `fixed`.
    #[arg(long, value_enum, default_value_t = ParticleDamping::Fixed)]
    #[serde(default)]
    pub damping: ParticleDamping,
    /// Where the MPM world, the residual network and their adjoints run
    /// (cuda: the first NVIDIA GPU; losses and optimiser stay on the CPU).
    #[arg(long, value_enum, default_value_t = Device::Cpu)]
    #[serde(default)]
    pub device: Device,
    /// Keep the effect terms a start model carries (drag, viscosity,
    /// friction, a ground tilt) fixed instead of learning them.
    #[arg(long)]
    #[serde(default)]
    pub freeze_effects: bool,
    /// After the fit, bound how precisely the training tracks determine
    /// ln E, ν, ln k_p and ln k_d (Cramér–Rao; 9 rollouts), in
    /// fit_report.json's `material.identifiability`.
    #[arg(long)]
    #[serde(default)]
    pub identifiability: bool,
    /// Track noise the bound assumes, mm per axis and frame (dm-synth's).
    #[arg(long, default_value_t = DEFAULT_TRACK_NOISE_MM)]
    #[serde(default = "default_track_noise_mm")]
    pub track_noise_mm: f64,
    /// Constant offset per track and axis the bound assumes, mm (dm-synth's
    /// per-track bias).
    #[arg(long, default_value_t = DEFAULT_TRACK_OFFSET_MM)]
    #[serde(default = "default_track_offset_mm")]
    pub track_offset_mm: f64,
}

fn default_track_noise_mm() -> f64 {
    DEFAULT_TRACK_NOISE_MM
}

fn default_track_offset_mm() -> f64 {
    DEFAULT_TRACK_OFFSET_MM
}

impl FitOptions {
    /// Refuses a track noise the bound cannot use (checked before the fit
    /// starts, so a long fit never ends on it): σ must be positive, the
    /// offset not negative, both finite.
    pub fn validate_track_noise(&self) -> Result<(), FitError> {
        let checks = [
            (
                "--track-noise-mm",
                self.track_noise_mm,
                self.track_noise_mm > 0.0,
            ),
            (
                "--track-offset-mm",
                self.track_offset_mm,
                self.track_offset_mm >= 0.0,
            ),
        ];
        for (option, value, valid) in checks {
            if !(valid && value.is_finite()) {
                return Err(FitError::InvalidOption {
                    option: option.into(),
                    problem: format!(
                        "{value} mm: needs a finite value, positive for the noise and not negative for the offset"
                    ),
                });
            }
        }
        Ok(())
    }

    /// The track noise `--identifiability` assumes, in metres.
    pub fn track_noise(&self) -> TrackNoise {
        TrackNoise {
            sigma_m: 1e-3 * self.track_noise_mm,
            offset_sigma_m: 1e-3 * self.track_offset_mm,
        }
    }
}

/// Whether a fit learns the particle damping rate.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum ParticleDamping {
    /// The category's default (method.md §2).
    #[default]
    Fixed,
    /// Stepped with the material in stages 2 and 3, between 0.5 /s and
    /// the default.
    Learnt,
}

/// Which iterate of the residual-only stage the fit keeps.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum ResidualKeep {
    /// The network after the stage's last step.
    #[default]
    Last,
    /// The network (the stage's start included) with the lowest L_dyn over
    /// the last 30 % of the training frames (docs/fit.md).
    LateFrames,
}

/// Where the residual-only stage's Adam starts (docs/fit.md).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum ResidualAdam {
    /// A new optimiser: its first step moves every weight by the full
    /// learning rate.
    #[default]
    Fresh,
    /// Stage 2's optimiser restricted to the network's weights.
    Continued,
}

/// The network of the residual-only stage with the lowest late-frames
/// loss so far ([`ResidualKeep::LateFrames`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct KeptResidual {
    /// Steps of the stage taken before these weights (0: its start).
    pub step: usize,
    pub late_loss: f64,
    pub parameters: Vec<f64>,
}

fn default_residual_lr() -> f64 {
    5e-3
}

/// `--residual-min-gain`'s default, chosen on seeds outside the benchmark
/// (7 and 8, 24 scenes): the smallest threshold (in hundredths) that drops
/// every effect-free scene whose network made the held-out Track error
/// more than 5 % worse. The largest training gain among those was 16.7 %
/// (cloth s8 stretch, +7.2 % held out); the four others gained 2.7–7.5 %
/// (docs/RESULTS.md).
pub const DEFAULT_RESIDUAL_MIN_GAIN: f64 = 0.17;

fn parse_min_gain(text: &str) -> Result<f64, String> {
    let value: f64 = text.parse().map_err(|e| format!("{e}"))?;
    if (0.0..1.0).contains(&value) {
        Ok(value)
    } else {
        Err(format!(
            "{value}: a fraction of the training error, at least 0 and below 1"
        ))
    }
}

fn default_rgb_weight() -> f64 {
    DEFAULT_RGB_WEIGHT
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    Material1,
    Gains,
    Material2,
    /// The residual network alone, the physics frozen (method.md §7 trains
    /// the residual on top of fitted physics).
    Residual,
    /// Stage 3: RGB-guided refinement with frozen Gaussians.
    Rgb,
    Done,
}

/// One evaluated gain pair of the CMA-ES search.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GainTrial {
    pub kp: f64,
    pub kd: f64,
    /// Grasp radius of the trial, metres (records before
    /// `--search-grasp-radius` existed have none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grasp_radius: Option<f64>,
    pub loss: f64,
}

/// Range of `--search-grasp-radius`, metres: from about one particle
/// spacing of a demo-scale scene to a palm (the option's help quotes it).
pub const GRASP_RADIUS_SEARCH_M: [f64; 2] = [0.005, 0.06];

/// Everything needed to resume a fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Checkpoint {
    pub options: FitOptions,
    pub stage: Stage,
    pub iteration: usize,
    pub model: WorldModel,
    pub adam: Adam,
    pub history: Vec<IterationReport>,
    pub gain_search: Vec<GainTrial>,
    pub seconds: f64,
    /// Wall seconds per part of the fit ([`StageTimes`]), summed over
    /// resumed runs.
    #[serde(default)]
    pub stage_seconds: StageTimes,
    /// The residual-only stage's best network so far (`--residual-keep
    /// late-frames`).
    #[serde(default)]
    pub kept_residual: Option<KeptResidual>,
    /// `--residual-min-gain`'s decision, taken at the end of the dynamics
    /// stages.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub residual_check: Option<ResidualCheck>,
}

impl Checkpoint {
    /// Reads a checkpoint file and checks that its model's parts agree, its
    /// optimiser's settings are valid and its kept network's step lies in
    /// the residual stage; errors name the file and field.
    pub fn load(path: &Path) -> Result<Self, FitError> {
        let saved: Self = dm_bundle::read_json(path)?;
        saved.model.check_consistent().map_err(|(field, problem)| {
            BundleError::new(path, format!("model.{field}"), problem)
        })?;
        saved
            .adam
            .check_config()
            .map_err(|e| BundleError::new(path, "adam.config", e.to_string()))?;
        if let Some(kept) = &saved.kept_residual
            && kept.step > saved.options.residual_iters
        {
            return Err(BundleError::new(
                path,
                "kept_residual.step",
                format!(
                    "step {} of a residual stage of {} steps",
                    kept.step, saved.options.residual_iters
                ),
            )
            .into());
        }
        Ok(saved)
    }
}

/// `fit_report.json` (contract keys: `material.E_median_pa`,
/// `material.nu_median`, `dca.kp`, `dca.kd`, `loss.final`, `seconds`,
/// `options`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FitReport {
    pub material: serde_json::Value,
    pub dca: serde_json::Value,
    pub loss: serde_json::Value,
    /// `kind` (pgnd | mlp | none: the saved model's network, none when
    /// `--residual-min-gain` dropped it), the weight count, and `check`.
    pub residual: serde_json::Value,
    pub seconds: f64,
    /// Where the time went: `seconds` split by part, plus `report` (the
    /// final loss and the probes, not in `seconds`); empty in reports
    /// written without it.
    #[serde(default)]
    pub seconds_by_stage: StageTimes,
    /// The material steps' seconds in the history by phase
    /// ([`crate::material_fit::StepPhases`]).
    #[serde(default)]
    pub seconds_by_phase: crate::material_fit::StepPhases,
    pub options: FitOptions,
    pub frames: usize,
    pub gain_search: Vec<GainTrial>,
}

pub const CHECKPOINT_FILE: &str = "checkpoint.json";

/// Wall seconds per part of a fit, by name: the stages (`material1`,
/// `gains`, `material2`, `residual`, `rgb`), and within them the residual
/// check's physics-only fit (`residual_check`), stage 3's first-frame
/// Gaussians (`appearance`) and, in the report only, `report`.
pub type StageTimes = std::collections::BTreeMap<String, f64>;

impl Stage {
    /// The stage's name in [`StageTimes`].
    fn timing_name(self) -> &'static str {
        match self {
            Stage::Material1 => "material1",
            Stage::Gains => "gains",
            Stage::Material2 => "material2",
            Stage::Residual => "residual",
            Stage::Rgb => "rgb",
            Stage::Done => "done",
        }
    }
}

/// The material step's settings for `stage`: the particle damping is
/// learnt (`--damping learnt`) only once the material has had its first
/// fit, in stages 2 and 3 (docs/fit.md).
pub(crate) fn material_config(
    options: &FitOptions,
    iterations: usize,
    stage: Stage,
) -> MaterialFitConfig {
    MaterialFitConfig {
        iterations,
        learning_rate: options.lr,
        effect_learning_rate: options.effect_lr,
        window: options.window,
        frames: None,
        residual_learning_rate: options.residual_lr,
        freeze_material: false,
        learn_effects: !options.freeze_effects,
        learn_damping: options.damping == ParticleDamping::Learnt
            && matches!(stage, Stage::Material2 | Stage::Rgb),
        force_field_terms: crate::learnt_effects::ForceFieldTerms::NONE,
        device: options.device,
    }
}

/// The gain search's box: log10 of k_p (1/s²) and of k_d (1/s).
pub const GAIN_SEARCH_LOG10: [[f64; 2]; 2] = [[0.0, 5.0], [-1.0, 3.0]];

/// CMA-ES over (log10 kp, log10 kd) in [1, 1e5] × [0.1, 1e3] (1/s², 1/s),
/// and with `--search-grasp-radius` log10 of the grasp radius in
/// [`GRASP_RADIUS_SEARCH_M`], starting from the current values; the train
/// track loss of a forward rollout is the fitness.
fn select_gains(
    model: &mut WorldModel,
    bundle: &Bundle,
    options: &FitOptions,
) -> Result<Vec<GainTrial>, FitError> {
    let frames = fit_frames(bundle, &material_config(options, 0, Stage::Material1));
    let radius = options.search_grasp_radius;
    let [r_lo, r_hi] = GRASP_RADIUS_SEARCH_M.map(f64::log10);
    let mut start = vec![model.actuator.kp.log10(), model.actuator.kd.log10()];
    let [kp_range, kd_range] = GAIN_SEARCH_LOG10;
    let (mut lo, mut hi) = (
        vec![kp_range[0], kd_range[0]],
        vec![kp_range[1], kd_range[1]],
    );
    if radius {
        start.push(model.actuator.grasp_radius.log10().clamp(r_lo, r_hi));
        lo.push(r_lo);
        hi.push(r_hi);
    }
    let bounds = Bounds::new(lo, hi)?;
    // Hansen's default population, 4 + ⌊3 ln n⌋: 6 for 2 dimensions, 7 for
    // 3; a smaller budget shrinks it so that at least one generation runs.
    let population = options.gain_evals.clamp(2, if radius { 7 } else { 6 });
    let cma_options = CmaesOptions {
        seed: options.seed,
        population_size: Some(population as usize),
        max_evaluations: Some(options.gain_evals.max(population)),
        ..CmaesOptions::default()
    };
    let mut search = Cmaes::new(&start, 0.5, Some(bounds), cma_options)?;
    let mut trials = Vec::new();
    let mut best = GainTrial {
        kp: model.actuator.kp,
        kd: model.actuator.kd,
        grasp_radius: radius.then_some(model.actuator.grasp_radius),
        loss: train_loss_on(model, bundle, frames, options.device)?,
    };
    trials.push(best);
    while search.should_stop().is_none() && (trials.len() as u64) < options.gain_evals {
        let population = search.ask();
        // The candidates' rollouts are independent: run them side by side
        // (each is deterministic, so the outcome does not depend on the
        // thread count), which also spares each rollout's substeps most of
        // their fork-join waits.
        let generation: Vec<GainTrial> = population
            .par_iter()
            .map(|x| {
                let mut candidate = model.clone();
                candidate.actuator.kp = 10f64.powf(x[0]);
                candidate.actuator.kd = 10f64.powf(x[1]);
                if radius {
                    candidate.actuator.grasp_radius = 10f64.powf(x[2]);
                }
                Ok(GainTrial {
                    kp: candidate.actuator.kp,
                    kd: candidate.actuator.kd,
                    grasp_radius: radius.then_some(candidate.actuator.grasp_radius),
                    loss: train_loss_on(&candidate, bundle, frames, options.device)?,
                })
            })
            .collect::<Vec<_>>()
            .into_iter()
            // The first failing candidate's error, whatever the thread count.
            .collect::<Result<_, FitError>>()?;
        for trial in &generation {
            if trial.loss < best.loss {
                best = *trial;
            }
        }
        let fitness: Vec<f64> = generation.iter().map(|trial| trial.loss).collect();
        trials.extend(generation);
        search.tell(&fitness)?;
    }
    model.actuator.kp = best.kp;
    model.actuator.kd = best.kd;
    if let Some(r) = best.grasp_radius {
        model.actuator.grasp_radius = r;
    }
    Ok(trials)
}

/// How a call to [`run_fit`] ended.
#[derive(Clone, Debug)]
pub enum FitOutcome {
    Finished(Box<FitReport>),
    /// Stopped after the requested number of steps; resume to continue.
    Paused {
        stage: Stage,
        iteration: usize,
    },
}

/// Runs (or resumes) the fit and writes the model directory. With
/// `stop_after = Some(n)` it pauses after n checkpointed steps (time-boxed
/// runs; rerun with `resume` to continue).
pub fn run_fit(
    bundle: &Bundle,
    options: &FitOptions,
    out: &Path,
    resume: bool,
    stop_after: Option<usize>,
    progress: &mut dyn FnMut(&str),
) -> Result<FitOutcome, FitError> {
    run_fit_until(bundle, options, out, resume, stop_after, None, progress)
}

/// [`run_fit`] that also pauses, checkpointed, after the step during which
/// `cancel` is set (an interrupt from the caller's thread or `progress`).
pub fn run_fit_until(
    bundle: &Bundle,
    options: &FitOptions,
    out: &Path,
    resume: bool,
    stop_after: Option<usize>,
    cancel: Option<&AtomicBool>,
    progress: &mut dyn FnMut(&str),
) -> Result<FitOutcome, FitError> {
    let start = StagesStart {
        resume,
        stop_after,
        cancel,
        ..StagesStart::default()
    };
    fit_stages(bundle, options, out, start, progress)
}

/// The same stages from a given starting model instead of the bundle's
/// default one (dm-diagnose fits a candidate effect from the start, on the
/// same terms as the model it is compared with). Not resumable: the
/// checkpoint's options do not record the starting model.
pub fn run_fit_from(
    bundle: &Bundle,
    options: &FitOptions,
    initial: WorldModel,
    out: &Path,
    progress: &mut dyn FnMut(&str),
) -> Result<FitOutcome, FitError> {
    let start = StagesStart {
        initial: Some(initial),
        ..StagesStart::default()
    };
    fit_stages(bundle, options, out, start, progress)
}

/// Where a fit's stages start and when they pause ([`fit_stages`]).
#[derive(Default)]
pub(crate) struct StagesStart<'a> {
    /// Go on from the checkpoint in the model directory, if there is one.
    pub resume: bool,
    /// Pause after this many checkpointed steps.
    pub stop_after: Option<usize>,
    /// The starting model, else the bundle's default one.
    pub initial: Option<WorldModel>,
    /// Pause after the step during which this is set.
    pub cancel: Option<&'a AtomicBool>,
}

/// The stages of one fit, started and paused as `start` says. Each step is
/// one method of [`FitRun`]; the [`Checkpoint`] carries everything that
/// flows from one step to the next and is written after each.
pub(crate) fn fit_stages(
    bundle: &Bundle,
    options: &FitOptions,
    out: &Path,
    start: StagesStart,
    progress: &mut dyn FnMut(&str),
) -> Result<FitOutcome, FitError> {
    let StagesStart {
        resume,
        stop_after,
        initial,
        cancel,
    } = start;
    options.validate_track_noise()?;
    let mut run = FitRun {
        bundle,
        options,
        out,
        resume,
        // The physics-only fit of the check starts where this one does.
        check_start: initial
            .as_ref()
            .filter(|_| run_checks_residual(options))
            .cloned(),
        parts: Vec::new(),
        progress,
        concurrent_check: None,
    };
    let mut state = run.start(initial)?;
    // Only once the options and the bundle have given a model: a refused run
    // leaves no empty output directory behind.
    std::fs::create_dir_all(out).map_err(|e| dm_bundle::BundleError::io(out, "creating", &e))?;
    // On the GPU the check's physics-only fit runs beside this one from the
    // start: both fits' worlds are small, and the GPU has room for both. Not
    // from a rayon worker: waiting there for a thread whose own parallel
    // loops need the workers could hold them all.
    let dynamics = matches!(
        state.stage,
        Stage::Material1 | Stage::Gains | Stage::Material2 | Stage::Residual
    );
    if options.device == Device::Cuda
        && stop_after.is_none()
        && run_checks_residual(options)
        && state.model.residual.is_some()
        && state.residual_check.is_none()
        && dynamics
        && rayon::current_thread_index().is_none()
    {
        (run.progress)(
            "residual check: fitting the same physics without the network, beside this fit",
        );
        let start = run.check_start_model()?;
        run.concurrent_check = Some(ConcurrentCheck::start(bundle, options, start, out, resume));
    }
    let checkpoint_path = out.join(CHECKPOINT_FILE);
    let mut steps = 0;
    while state.stage != Stage::Done {
        if stop_after.is_some_and(|n| steps >= n)
            || cancel.is_some_and(|c| c.load(Ordering::Relaxed))
        {
            return Ok(FitOutcome::Paused {
                stage: state.stage,
                iteration: state.iteration,
            });
        }
        steps += 1;
        let stage = state.stage.timing_name();
        let clock = std::time::Instant::now();
        run.step(&mut state)?;
        let elapsed = clock.elapsed().as_secs_f64();
        state.seconds += elapsed;
        // Parts timed inside the step are charged to themselves, the rest
        // to the step's stage.
        let mut rest = elapsed;
        for (part, seconds) in run.parts.drain(..) {
            *state.stage_seconds.entry(part.into()).or_default() += seconds;
            rest -= seconds;
        }
        *state.stage_seconds.entry(stage.into()).or_default() += rest;
        write_json_atomic(&checkpoint_path, &state)?;
        run.relay_check_progress();
    }
    let clock = std::time::Instant::now();
    let mut report = run.final_report(&state)?;
    report
        .seconds_by_stage
        .insert("report".into(), clock.elapsed().as_secs_f64());
    run.write_outputs(&state, &report)?;
    Ok(FitOutcome::Finished(Box::new(report)))
}

/// Whether the residual check (`--residual-min-gain`) runs at the end of
/// the dynamics stages.
fn run_checks_residual(options: &FitOptions) -> bool {
    options.residual_min_gain > 0.0
}

/// What every stage of one fit reads and none changes: the scene, the
/// options, the model directory and the progress lines. What the stages
/// change is the [`Checkpoint`] passed to each.
struct FitRun<'a> {
    bundle: &'a Bundle,
    options: &'a FitOptions,
    out: &'a Path,
    /// Whether the residual check's own fit resumes from its checkpoint.
    resume: bool,
    /// Where the residual check's physics-only fit starts when the fit
    /// itself started from a given model ([`run_fit_from`]); else from the
    /// bundle's default model without a network.
    check_start: Option<WorldModel>,
    /// Parts of the current step timed on their own ([`StageTimes`]).
    parts: Vec<(&'static str, f64)>,
    progress: &'a mut dyn FnMut(&str),
    /// The residual check's physics-only fit, when it runs beside this one.
    concurrent_check: Option<ConcurrentCheck>,
}

/// The residual check's physics-only fit on a thread of its own, beside
/// the main fit: the progress lines it sends, and its checkpoint once it
/// ends.
struct ConcurrentCheck {
    lines: std::sync::mpsc::Receiver<String>,
    /// Set when the main fit ends without the check (an error): the
    /// physics-only fit then stops after its current step, resumable.
    cancel: Arc<AtomicBool>,
    fit: Option<std::thread::JoinHandle<Result<Option<Checkpoint>, FitError>>>,
}

impl ConcurrentCheck {
    fn start(
        bundle: &Bundle,
        options: &FitOptions,
        start: WorldModel,
        out: &Path,
        resume: bool,
    ) -> Self {
        let (sender, lines) = std::sync::mpsc::channel();
        let cancel = Arc::new(AtomicBool::new(false));
        let (bundle, options, out) = (bundle.clone(), options.clone(), out.to_path_buf());
        let stop = cancel.clone();
        let fit = std::thread::spawn(move || {
            let mut progress = |line: &str| {
                // The main fit has stopped listening only when it ended.
                let _ = sender.send(line.to_string());
            };
            fit_physics_only(
                &bundle,
                &options,
                start,
                &out,
                resume,
                Some(&stop),
                &mut progress,
            )
        });
        Self {
            lines,
            cancel,
            fit: Some(fit),
        }
    }

    /// Passes the fit's lines on as they come until it ends; its
    /// checkpoint.
    fn finish(mut self, progress: &mut dyn FnMut(&str)) -> Result<Checkpoint, FitError> {
        // Ends when the fit's thread drops its sender (a panic included).
        for line in self.lines.iter() {
            progress(&line);
        }
        let Some(fit) = self.fit.take() else {
            unreachable!("`finish` consumes the check, and only it and `drop` take the fit")
        };
        match fit.join() {
            Ok(Ok(Some(checkpoint))) => Ok(checkpoint),
            Ok(Ok(None)) => unreachable!("only `drop` cancels the check's fit"),
            Ok(Err(error)) => Err(error),
            Err(panic) => std::panic::resume_unwind(panic),
        }
    }
}

impl Drop for ConcurrentCheck {
    /// A main fit that ends early (an error) stops the check's fit after
    /// its current step and waits for it: nothing goes on writing behind
    /// the caller's back.
    fn drop(&mut self) {
        if let Some(fit) = self.fit.take() {
            self.cancel.store(true, Ordering::Relaxed);
            let _ = fit.join();
        }
    }
}

impl FitRun<'_> {
    /// The saved checkpoint with `resume` (refused when written with other
    /// options), else stage 1's start from `initial` or the bundle's
    /// default model.
    fn start(&mut self, initial: Option<WorldModel>) -> Result<Checkpoint, FitError> {
        let options = self.options;
        let checkpoint_path = self.out.join(CHECKPOINT_FILE);
        if self.resume && checkpoint_path.is_file() {
            let saved = Checkpoint::load(&checkpoint_path)?;
            if saved.options != *options {
                return Err(FitError::InvalidOption {
                    option: "--resume".into(),
                    problem: format!(
                        "{} was written with different options",
                        checkpoint_path.display()
                    ),
                });
            }
            (self.progress)(&format!(
                "resuming at {:?}, iteration {}",
                saved.stage, saved.iteration
            ));
            return Ok(saved);
        }
        let model = match initial {
            Some(model) => model,
            None => WorldModel::from_bundle(self.bundle, &options.model)?,
        };
        Ok(Checkpoint {
            options: options.clone(),
            stage: Stage::Material1,
            iteration: 0,
            adam: material_config(options, 0, Stage::Material1).adam(&model)?,
            model,
            history: Vec::new(),
            gain_search: Vec::new(),
            seconds: 0.0,
            stage_seconds: StageTimes::new(),
            kept_residual: None,
            residual_check: None,
        })
    }

    /// One checkpointed step: a gradient step of the current stage, or the
    /// move to the next stage once it has run all of its steps.
    fn step(&mut self, state: &mut Checkpoint) -> Result<(), FitError> {
        let options = self.options;
        match state.stage {
            Stage::Material1 | Stage::Material2 | Stage::Residual => {
                let total = match state.stage {
                    Stage::Material1 => options.iters,
                    Stage::Material2 => options.stage2_iters,
                    _ if state.model.residual.is_some() => options.residual_iters,
                    _ => 0,
                };
                if state.iteration < total {
                    self.dynamics_step(state, total)
                } else {
                    self.end_dynamics_stage(state)
                }
            }
            Stage::Gains => self.gain_stage(state),
            Stage::Rgb if state.iteration < options.rgb_iters => self.rgb_step(state),
            Stage::Rgb => {
                state.stage = Stage::Done;
                Ok(())
            }
            Stage::Done => Ok(()),
        }
    }

    /// One step of stage 1 (material, default gains), stage 2 (material,
    /// selected gains) or the residual stage (the network alone, the
    /// physics frozen; with `--residual-keep late-frames` the best network
    /// so far is remembered).
    fn dynamics_step(&mut self, state: &mut Checkpoint, total: usize) -> Result<(), FitError> {
        let options = self.options;
        let config = MaterialFitConfig {
            freeze_material: state.stage == Stage::Residual,
            ..material_config(options, total, state.stage)
        };
        let index = state.history.len();
        let keeping =
            state.stage == Stage::Residual && options.residual_keep == ResidualKeep::LateFrames;
        let weights_before = keeping
            .then(|| state.model.residual.as_ref().map(|r| r.parameters.clone()))
            .flatten();
        let report = material_step(
            &mut state.model,
            self.bundle,
            &config,
            &mut state.adam,
            index,
            None,
        )?;
        if keeping {
            keep_if_better(
                &mut state.kept_residual,
                state.iteration,
                report.late_loss,
                weights_before,
            );
        }
        (self.progress)(&format!(
            "{:?} {}/{}: loss {:.3e} m², E {:.3e} Pa, nu {:.3}",
            state.stage,
            state.iteration + 1,
            total,
            report.loss,
            report.youngs_median_pa,
            report.poisson_median
        ));
        state.history.push(report);
        state.iteration += 1;
        Ok(())
    }

    /// The end of stage 1, stage 2 or the residual stage: the kept network
    /// put back, the next stage and its Adam, and after the last dynamics
    /// stage the residual check.
    fn end_dynamics_stage(&mut self, state: &mut Checkpoint) -> Result<(), FitError> {
        let options = self.options;
        let residual_stage_runs = options.residual_iters > 0 && state.model.residual.is_some();
        let previous = state.stage;
        if previous == Stage::Residual
            && let Some(message) = restore_kept_residual(state, self.bundle, options)?
        {
            (self.progress)(&message);
        }
        state.stage = match previous {
            Stage::Material1 => Stage::Gains,
            Stage::Material2 if residual_stage_runs => Stage::Residual,
            _ if options.rgb_iters > 0 => Stage::Rgb,
            _ => Stage::Done,
        };
        // The residual stage's Adam holds the network's group only; it
        // carries on from stage 2's (`--residual-adam continued`) or starts
        // fresh, and the stage after it starts fresh. (A learnt tilt has
        // its own rate: not in the residual stage's Adam, whose parameters
        // hold no tilt group.)
        if residual_stage_runs && previous != Stage::Material1 {
            let config = MaterialFitConfig {
                freeze_material: state.stage == Stage::Residual,
                ..material_config(options, 0, state.stage)
            };
            state.adam = match options.residual_adam {
                ResidualAdam::Continued if state.stage == Stage::Residual => state
                    .adam
                    .continued_for_group(RESIDUAL_GROUP, config.adam_config(&state.model))?,
                _ => config.adam(&state.model)?,
            };
        }
        let dynamics_done = matches!(state.stage, Stage::Rgb | Stage::Done);
        if dynamics_done && run_checks_residual(options) && state.model.residual.is_some() {
            self.residual_check(state)?;
        }
        state.iteration = 0;
        Ok(())
    }

    /// `--residual-min-gain`: the same dynamics fitted without the network
    /// (under `out/residual_check`) and compared with this fit; below the
    /// threshold the fit goes on from the physics-only one, exactly as
    /// `--residual none` would have.
    fn residual_check(&mut self, state: &mut Checkpoint) -> Result<(), FitError> {
        let clock = std::time::Instant::now();
        let (check, physics_only) = match self.concurrent_check.take() {
            Some(concurrent) => {
                let physics_only = concurrent.finish(self.progress)?;
                let check = compare_with_physics_only(
                    self.bundle,
                    self.options,
                    &state.model,
                    &physics_only,
                    self.progress,
                )?;
                (check, physics_only)
            }
            None => check_residual(
                self.bundle,
                self.options,
                self.check_start_model()?,
                &state.model,
                self.out,
                self.resume,
                self.progress,
            )?,
        };
        self.parts
            .push(("residual_check", clock.elapsed().as_secs_f64()));
        if !check.kept {
            state.model = physics_only.model;
            state.adam = physics_only.adam;
            state.history = physics_only.history;
            state.gain_search = physics_only.gain_search;
            state.kept_residual = None;
        }
        state.residual_check = Some(check);
        Ok(())
    }

    /// Where the check's physics-only fit starts, built as `--residual
    /// none` builds it: no network to make and strip.
    fn check_start_model(&self) -> Result<WorldModel, FitError> {
        Ok(match &self.check_start {
            Some(model) => model.clone(),
            None => {
                WorldModel::from_bundle(self.bundle, &physics_only_options(self.options).model)?
            }
        })
    }

    /// Passes on the progress lines the concurrent check's fit has sent.
    fn relay_check_progress(&mut self) {
        if let Some(check) = &self.concurrent_check {
            for line in check.lines.try_iter() {
                (self.progress)(&line);
            }
        }
    }

    /// The actuator gains (CMA-ES, when there are evaluations to spend and
    /// the actuators are compliant), then stage 2's fresh Adam.
    fn gain_stage(&mut self, state: &mut Checkpoint) -> Result<(), FitError> {
        let options = self.options;
        if options.gain_evals > 0 && options.model.actuators != ActuatorChoice::Rigid {
            (self.progress)("selecting actuator gains (CMA-ES)");
            state.gain_search = select_gains(&mut state.model, self.bundle, options)?;
        }
        state.adam = material_config(options, 0, Stage::Material2).adam(&state.model)?;
        state.stage = Stage::Material2;
        Ok(())
    }

    /// One step of stage 3: the material and gains against the images
    /// through the first-frame Gaussians, which its first step fits and
    /// saves (`gaussians.ply`, `appearance.json`) and the later ones load.
    fn rgb_step(&mut self, state: &mut Checkpoint) -> Result<(), FitError> {
        let (bundle, options) = (self.bundle, self.options);
        let (gaussians, cameras) = if state.iteration == 0 {
            (self.progress)("stage 3: fitting the first-frame Gaussians");
            let clock = std::time::Instant::now();
            let appearance_options = AppearanceOptions::for_cameras(bundle.meta.cameras.len());
            let (gaussians, record) =
                fit_appearance(&state.model, bundle, &appearance_options, &mut |_| {})?;
            save_appearance(self.out, &gaussians, &record)?;
            self.parts
                .push(("appearance", clock.elapsed().as_secs_f64()));
            (self.progress)(&format!(
                "stage 3: {} Gaussians, frame-0 PSNR {:.1} dB (training cameras)",
                record.gaussian_count, record.mean_train_psnr_db
            ));
            (gaussians, record.train_cameras)
        } else {
            let (gaussians, record) = load_appearance(self.out, &state.model)?;
            (gaussians, record.train_cameras)
        };
        let config = material_config(options, options.rgb_iters, Stage::Rgb);
        let steps = fit_frames(bundle, &config).saturating_sub(1);
        let mut term = RgbTerm::new(
            bundle,
            gaussians,
            &state.model.particles,
            &cameras,
            options.rgb_weight,
            steps,
        )?;
        let index = state.history.len();
        let mut report = material_step(
            &mut state.model,
            bundle,
            &config,
            &mut state.adam,
            index,
            Some(&mut term),
        )?;
        report.rgb_l1 = Some(term.mean_l1());
        (self.progress)(&format!(
            "Rgb {}/{}: loss {:.3e}, masked L1 {:.4}, E {:.3e} Pa, nu {:.3}",
            state.iteration + 1,
            options.rgb_iters,
            report.loss,
            term.mean_l1(),
            report.youngs_median_pa,
            report.poisson_median
        ));
        state.history.push(report);
        state.iteration += 1;
        Ok(())
    }

    /// `fit_report.json` of the finished fit: the final training loss, the
    /// material's sensitivity probe and, with `--identifiability`, the
    /// Cramér–Rao bounds.
    fn final_report(&mut self, state: &Checkpoint) -> Result<FitReport, FitError> {
        let (bundle, options) = (self.bundle, self.options);
        let frames = fit_frames(bundle, &material_config(options, 0, Stage::Material1));
        let final_loss = train_loss_on(&state.model, bundle, frames, options.device)?;
        let (youngs, poisson) = state.model.material_medians();
        (self.progress)("probing how sharply the clip pins E and ν");
        let sensitivity =
            material_sensitivity(&state.model, bundle, frames, final_loss, options.device)?;
        let identifiability = if options.identifiability {
            (self.progress)("bounding how precisely the tracks determine E, ν and the gains");
            Some(identifiability_at(
                &state.model,
                bundle,
                frames,
                options.track_noise(),
                &mut |_| {},
            )?)
        } else {
            None
        };
        Ok(FitReport {
            material: serde_json::json!({
                "E_median_pa": youngs,
                "nu_median": poisson,
                "particle_damping_per_s": state.model.physics.particle_damping,
                "sensitivity": sensitivity,
                "identifiability": identifiability,
            }),
            dca: serde_json::json!({
                "kp": state.model.actuator.kp,
                "kd": state.model.actuator.kd,
                "grasp_radius_m": state.model.actuator.grasp_radius,
                "mode": state.model.actuator.mode,
            }),
            loss: serde_json::json!({
                "initial": state.history.first().map(|r| r.loss),
                "final": final_loss,
                "history": state.history,
            }),
            residual: serde_json::json!({
                "kind": state.model.options.residual,
                "parameters": state.model.residual.as_ref().map_or(0, |r| r.parameters.len()),
                "check": state.residual_check,
                "keep": options.residual_keep,
                "kept_step": state.kept_residual.as_ref().map(|k| k.step),
                "kept_late_loss": state.kept_residual.as_ref().map(|k| k.late_loss),
            }),
            seconds: state.seconds,
            seconds_by_stage: state.stage_seconds.clone(),
            seconds_by_phase: state.history.iter().fold(Default::default(), |mut sum, r| {
                sum += r.phase_seconds;
                sum
            }),
            options: options.clone(),
            frames,
            gain_search: state.gain_search.clone(),
        })
    }

    /// The model directory's files: the model, `fit_report.json` and the
    /// loss curve with the stages' starts and the kept network marked.
    fn write_outputs(&self, state: &Checkpoint, report: &FitReport) -> Result<(), FitError> {
        let (options, out) = (self.options, self.out);
        write_model(&state.model, out)?;
        write_json_atomic(&out.join("fit_report.json"), report)?;
        let curve: Vec<f64> = state.history.iter().map(|r| r.loss).collect();
        // Where stage 2, the residual stage and stage 3 start in the history.
        let mut stage_starts = vec![options.iters, options.iters + options.stage2_iters];
        if options.residual_iters > 0 && state.model.residual.is_some() {
            stage_starts.push(options.iters + options.stage2_iters + options.residual_iters);
        }
        let late: Vec<f64> = state
            .history
            .iter()
            .map(|r| r.late_loss.unwrap_or(f64::NAN))
            .collect();
        let residual_start = options.iters + options.stage2_iters;
        let kept = state
            .kept_residual
            .as_ref()
            .map(|k| (residual_start + k.step, k.late_loss));
        let png = crate::plot::loss_curve(
            &curve,
            &late,
            &stage_starts,
            kept,
            state.residual_check.as_ref(),
        )?;
        write_file_atomic(&out.join("loss_curve.png"), |temp| {
            png.save_with_format(temp, image::ImageFormat::Png)
                .map_err(|e| std::io::Error::other(e.to_string()))
        })?;
        Ok(())
    }
}

/// Remembers `weights` (the network before step `step` of the residual
/// stage, whose late-frames loss is `late_loss`) when they beat the kept
/// ones.
fn keep_if_better(
    kept: &mut Option<KeptResidual>,
    step: usize,
    late_loss: Option<f64>,
    weights: Option<Vec<f64>>,
) {
    let (Some(late_loss), Some(parameters)) = (late_loss, weights) else {
        return;
    };
    if late_loss.is_finite() && kept.as_ref().is_none_or(|k| late_loss < k.late_loss) {
        *kept = Some(KeptResidual {
            step,
            late_loss,
            parameters,
        });
    }
}

/// At the end of the residual stage: scores the last network on the late
/// frames and puts the kept one back if it is better. Returns what was
/// done, for the progress line.
fn restore_kept_residual(
    state: &mut Checkpoint,
    bundle: &Bundle,
    options: &FitOptions,
) -> Result<Option<String>, FitError> {
    if options.residual_keep != ResidualKeep::LateFrames {
        return Ok(None);
    }
    let frames = fit_frames(bundle, &material_config(options, 0, Stage::Material1));
    let last = late_frames_loss(&train_frame_losses_on(
        &state.model,
        bundle,
        frames,
        options.device,
    )?);
    let step = state.iteration;
    keep_if_better(
        &mut state.kept_residual,
        step,
        Some(last),
        state.model.residual.as_ref().map(|r| r.parameters.clone()),
    );
    let (Some(kept), Some(residual)) = (&state.kept_residual, state.model.residual.as_mut()) else {
        return Ok(None);
    };
    residual.parameters.clone_from(&kept.parameters);
    Ok(Some(format!(
        "residual stage: kept the network after {} of {} steps (late-frames loss {:.3e} m², last {:.3e} m²)",
        kept.step, step, kept.late_loss, last
    )))
}

/// The model directory: `model.json` (everything to rebuild the world) and
/// the per-particle material fields as `.npy`.
fn write_model(model: &WorldModel, out: &Path) -> Result<(), FitError> {
    write_json_atomic(&out.join("model.json"), model)?;
    let (youngs, poisson, weights) = model.patches.particle_fields(&model.params, &model.bounds);
    let field =
        |values: Vec<f64>| ndarray::Array1::from_vec(values.iter().map(|&v| v as f32).collect());
    let weights = ndarray::Array2::from_shape_fn((weights.len(), 3), |(i, k)| weights[i][k] as f32);
    for (name, array) in [
        ("youngs_pa.npy", field(youngs)),
        ("poisson.npy", field(poisson)),
    ] {
        write_file_atomic(&out.join(name), |temp| {
            write_npy_file(temp, &array).map_err(|e| std::io::Error::other(e.to_string()))
        })?;
    }
    write_file_atomic(&out.join("expert_weights.npy"), |temp| {
        write_npy_file(temp, &weights).map_err(|e| std::io::Error::other(e.to_string()))
    })?;
    // The weights also live in model.json; safetensors is for other tools.
    if let Some(network) = model.residual_network()? {
        network
            .save(&out.join("residual.safetensors"))
            .map_err(dm_model::ModelError::from)?;
    }
    Ok(())
}
