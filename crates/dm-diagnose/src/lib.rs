//! Diagnosis of a fitted world model.
//!
//! * **Show** ([`analysis`]): the fitted model rolled out open loop, its
//!   errors per frame and per region, residual accelerations (observed
//!   minus simulated) and the learned residual's Δv.
//! * **Name** ([`candidates`], [`signatures`]): each library effect is
//!   added to the fitted model (material and gains held fixed), its
//!   parameter chosen on the training split's first frames, and scored by
//!   the relative reduction of the track error it brings there and on the
//!   split's last quarter ([`selection_frames`]); the signatures in the
//!   residual accelerations are printed as evidence. The cause is the best
//!   candidate when its score clears [`NONE_THRESHOLD`].
//! * **Detectability** ([`detectability`]): the smallest magnitude of each
//!   library effect that this clip would reveal.
//! * **Extend / Measure**: the chosen effect's parameter is refined on the
//!   training frames, the material refitted with the effect in place
//!   (gradients through the differentiable simulator), and the extended
//!   model written with its gain on the test split, which no choice used.
//!
//! Output contract (docs/diagnose.md): `diagnosis.json` and `report.md`
//! with PNG plots.

pub mod analysis;
pub mod candidates;
pub mod detectability;
pub mod discover;
mod plots;
mod report;
pub mod signatures;

use analysis::{Rollout, main_axis, match_tracks, per_track_error, region_errors, rollout};
use candidates::{Candidate, Trial, apply, refinements, trials, with_learnt_parameters};
use dm_bundle::{Bundle, write_json_atomic};
use dm_fit::material_fit::{MaterialFitConfig, fit_material, train_loss_on};
use dm_model::WorldModel;
use dm_model::device::Device;
use dm_model::metrics::split_mean;
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A cause is named only when its score (the smaller of the relative
/// reductions of the track error on the fit and the validation frames) is
/// at least this.
/// On fresh evaluation draws null scenes scored ≤ 0.076 and correctly
/// named effects 0.23–0.37 (docs/diagnose.md, docs/RESULTS.md).
pub const NONE_THRESHOLD: f64 = 0.10;

#[derive(Debug, thiserror::Error)]
pub enum DiagnoseError {
    #[error(transparent)]
    Model(#[from] dm_model::ModelError),
    #[error(transparent)]
    Simulation(#[from] dm_mpm::SimError),
    #[error(transparent)]
    Bundle(#[from] dm_bundle::BundleError),
    #[error(transparent)]
    Fit(#[from] dm_fit::material_fit::FitError),
    #[error(transparent)]
    Chart(#[from] dm_view::ViewError),
    #[error("{path}: {problem}")]
    Input { path: PathBuf, problem: String },
    #[error("writing {path}: {problem}")]
    Output { path: PathBuf, problem: String },
}

/// Options of a diagnosis: `dm-diagnose`'s CLI and the run record saved
/// as `options` in `diagnosis.json`.
#[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize, clap::Args)]
pub struct DiagnoseOptions {
    /// Material Adam steps of the refit with the chosen effect in place
    /// (0: effect parameter only).
    #[arg(long, default_value_t = DEFAULT_REFIT_ITERS)]
    pub refit_iters: usize,
    /// Score (the smaller of the candidate's Track-error reductions on the
    /// fitted and the validation training frames) below which the cause is `none`.
    #[arg(long = "threshold", value_name = "THRESHOLD", default_value_t = NONE_THRESHOLD)]
    pub none_threshold: f64,
    /// Score each candidate by a fresh fit with its effect in place (the
    /// model's own dm-fit options) instead of on top of the existing fit;
    /// one fit per candidate.
    #[arg(long)]
    pub fit_candidates: bool,
    /// Adam steps learning the discovered body force with the material
    /// (0: no discovery).
    #[arg(long, default_value_t = DEFAULT_DISCOVER_ITERS)]
    #[serde(default = "default_discover_iters")]
    pub discover_iters: usize,
    /// Bisection steps of each library effect's detection limit
    /// (0: no limits).
    #[arg(long, default_value_t = detectability::DEFAULT_DETECT_STEPS)]
    #[serde(default = "default_detect_steps")]
    pub detect_steps: usize,
    /// Where rollouts and refits run (cuda: the first NVIDIA GPU; variants with viscosity or a body force run on the CPU).
    #[arg(long, value_enum, default_value_t = Device::Cpu)]
    #[serde(default)]
    pub device: Device,
}

fn default_detect_steps() -> usize {
    detectability::DEFAULT_DETECT_STEPS
}

/// Adam steps learning the discovered body force with the material.
pub const DEFAULT_DISCOVER_ITERS: usize = 12;

fn default_discover_iters() -> usize {
    DEFAULT_DISCOVER_ITERS
}

/// Material steps of the refit with the named effect in place.
pub const DEFAULT_REFIT_ITERS: usize = 2;

impl Default for DiagnoseOptions {
    fn default() -> Self {
        Self {
            refit_iters: DEFAULT_REFIT_ITERS,
            none_threshold: NONE_THRESHOLD,
            fit_candidates: false,
            discover_iters: DEFAULT_DISCOVER_ITERS,
            detect_steps: detectability::DEFAULT_DETECT_STEPS,
            device: Device::Cpu,
        }
    }
}

/// One candidate's entry in `diagnosis.json`.
#[derive(Clone, Debug, Serialize)]
pub struct CandidateScore {
    pub name: String,
    /// min(validation reduction, fit reduction): what the candidate
    /// explains on both the frames that chose its parameter and the
    /// validation frames after them. Names the cause.
    pub score: f64,
    /// Relative reduction of the track error on the training frames that
    /// chose the parameter (all but the training split's last quarter).
    pub fit_reduction: f64,
    /// Relative reduction of the track error on the training split's last
    /// quarter, which no parameter choice saw.
    pub validation_reduction: f64,
    /// Relative reduction of the test-split track error (reported, used for
    /// no choice).
    pub held_out_reduction: f64,
    /// Relative reduction of the whole training split's track error
    /// (reported, used for no choice).
    pub train_reduction: f64,
    pub parameters: BTreeMap<String, f64>,
    pub signature: String,
    /// Whether the signature points this candidate's way (None: no cheap
    /// signature).
    pub signature_agrees: Option<bool>,
}

/// `gain` of `diagnosis.json`: test split, metres.
#[derive(Clone, Debug, Serialize)]
pub struct Gain {
    pub track_before: f64,
    pub track_after: f64,
    pub chamfer_before: f64,
    pub chamfer_after: f64,
}

/// Fitted effect parameters against the truth file's.
#[derive(Clone, Debug, Serialize)]
pub struct TruthComparison {
    pub truth_effect: String,
    pub name_correct: bool,
    pub truth_params: serde_json::Value,
    /// `fitted / truth − 1` of the parameter both carry, when they do.
    pub relative_error: Option<f64>,
}

/// `diagnosis.json`.
#[derive(Clone, Debug, Serialize)]
pub struct Diagnosis {
    pub cause: String,
    pub confidence: f64,
    pub candidates: Vec<CandidateScore>,
    pub extended_model: Option<String>,
    pub gain: Gain,
    pub effect_parameters: BTreeMap<String, f64>,
    pub threshold: f64,
    /// Whether each candidate was scored by a fit from the start
    /// (`--fit-candidates`) rather than added to the fitted model.
    pub candidates_fitted: bool,
    pub signatures: signatures::Signatures,
    pub regions_test: Vec<analysis::RegionError>,
    pub truth: Option<TruthComparison>,
    pub refit: Option<RefitRecord>,
    /// The open-ended body force fitted beside the library (`null` with
    /// `--discover-iters 0`).
    pub discovered: Option<discover::Discovered>,
    /// Where the model with the discovered terms was written.
    pub discovered_model: Option<String>,
    /// Each library effect's detection limit on this clip (empty with
    /// `--detect-steps 0`).
    pub detectability: BTreeMap<String, detectability::Limit>,
    /// The run record: the options this diagnosis ran with.
    pub options: DiagnoseOptions,
}

/// What the refit did.
#[derive(Clone, Debug, Serialize)]
pub struct RefitRecord {
    pub effect_trials: usize,
    pub material_iterations: usize,
    /// Training loss (dm-fit's L_dyn) before and after the material steps.
    pub train_loss_before: f64,
    pub train_loss_after: f64,
    /// Whether the material steps were kept (they are dropped when they
    /// raise the training track error).
    pub material_kept: bool,
    pub note: String,
}

/// One candidate trial in `trials.json`: every parameter setting tried,
/// with its per-frame track error, so a reader (or a script) can see how
/// each candidate moved the error over time, not only its two means.
#[derive(Clone, Debug, Serialize)]
pub struct TrialRecord {
    pub candidate: String,
    pub parameters: BTreeMap<String, f64>,
    /// Train / test split means (metres; `null` in the JSON when the trial
    /// diverged).
    pub track_train: f64,
    pub track_test: f64,
    /// Track error per frame (metres; empty when the trial diverged).
    pub track_per_frame: Vec<f64>,
}

impl TrialRecord {
    fn new(candidate: &str, parameters: &BTreeMap<String, f64>, scored: &Scored) -> Self {
        TrialRecord {
            candidate: candidate.into(),
            parameters: parameters.clone(),
            track_train: scored.track_train,
            track_test: scored.track_test,
            track_per_frame: scored.track_per_frame.clone(),
        }
    }
}

/// `trials.json`: the fitted model's per-frame track error and every trial's.
#[derive(Serialize)]
struct TrialsFile<'a> {
    /// Frame ranges [start, end) of the splits.
    train_frames: [usize; 2],
    test_frames: [usize; 2],
    base_track_per_frame: &'a [f64],
    trials: &'a [TrialRecord],
    /// With `fit_candidates`: each candidate's fit from the start.
    candidate_fits: &'a [TrialRecord],
}

/// The share of the training frames held back from every choice of a
/// parameter (a candidate's trial, a discovered term's coefficient): the
/// candidates are scored there, so the test split is left to the reported
/// gain alone.
pub const VALIDATION_SHARE: f64 = 0.25;

/// The training split cut into the frames that choose parameters and the
/// validation frames after them (the last [`VALIDATION_SHARE`]; two frames
/// at least each where the split has four).
pub fn selection_frames(train: [usize; 2]) -> SelectionFrames {
    let [start, end] = train;
    let length = end.saturating_sub(start);
    let validation = ((VALIDATION_SHARE * length as f64).round() as usize).max(2);
    let fit_end = end.saturating_sub(validation).max(start + 2).min(end);
    SelectionFrames {
        fit: [start, fit_end],
        validation: [fit_end, end],
    }
}

/// Frame ranges [start, end) of [`selection_frames`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct SelectionFrames {
    pub fit: [usize; 2],
    pub validation: [usize; 2],
}

/// Track / Chamfer of a rollout over the splits (infinite if it diverged).
#[derive(Clone, Debug)]
pub(crate) struct Scored {
    track_fit: f64,
    track_validation: f64,
    track_train: f64,
    track_test: f64,
    chamfer_test: f64,
    track_per_frame: Vec<f64>,
}

fn score_model(
    model: &WorldModel,
    bundle: &Bundle,
    device: Device,
) -> Result<(Scored, Rollout), DiagnoseError> {
    let run = rollout(model, bundle, device)?;
    let errors = analysis::errors(model, bundle, &run.positions);
    let split = &bundle.meta.split;
    let frames = selection_frames(split.train);
    Ok((
        Scored {
            track_fit: split_mean(&errors.track, frames.fit),
            track_validation: split_mean(&errors.track, frames.validation),
            track_train: split_mean(&errors.track, split.train),
            track_test: split_mean(&errors.track, split.test),
            chamfer_test: split_mean(&errors.chamfer, split.test),
            track_per_frame: errors.track,
        },
        run,
    ))
}

/// A trial's errors; a diverging or unbuildable trial scores infinity
/// (e.g. a stiffness needing more substeps than allowed).
pub(crate) fn score_trial(model: &WorldModel, bundle: &Bundle, device: Device) -> Scored {
    score_model(model, bundle, device)
        .map(|(s, _)| s)
        .unwrap_or_else(|_| Scored::failed())
}

/// The track error of a model's open-loop rollout on a bundle: the means
/// over the bundle's train and test splits and over the training split's
/// two parts of [`selection_frames`], metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SplitTrackError {
    pub train: f64,
    pub test: f64,
    pub fit: f64,
    pub validation: f64,
}

impl SplitTrackError {
    /// The diagnosis's score of `self` against `base`: the smaller of the
    /// relative reductions on the fit and on the validation frames.
    pub fn score_against(&self, base: &SplitTrackError) -> f64 {
        relative_reduction(base.fit, self.fit)
            .min(relative_reduction(base.validation, self.validation))
    }
}

/// `model` rolled out on `bundle` and scored as the diagnosis scores a
/// candidate: the splits' mean track error, infinite where the rollout
/// diverges or the model cannot be built.
pub fn split_track_error(model: &WorldModel, bundle: &Bundle) -> SplitTrackError {
    let scored = score_trial(model, bundle, Device::Cpu);
    SplitTrackError {
        train: scored.track_train,
        test: scored.track_test,
        fit: scored.track_fit,
        validation: scored.track_validation,
    }
}

impl Scored {
    /// What a diverging or failed trial scores.
    fn failed() -> Self {
        Scored {
            track_fit: f64::INFINITY,
            track_validation: f64::INFINITY,
            track_train: f64::INFINITY,
            track_test: f64::INFINITY,
            chamfer_test: f64::INFINITY,
            track_per_frame: Vec::new(),
        }
    }
}

/// Progress: (what, done, total).
pub type Progress<'a> = &'a mut dyn FnMut(&str, usize, usize);

/// Trials evaluated at once: each is a world of its own (on the GPU with
/// a stream of its own), so a batch fills the device where one small
/// world cannot.
const BATCH: usize = 8;

/// `evaluate` on every item in order, [`BATCH`] at a time side by side;
/// `progress(done, total)` before each batch. The results do not
/// depend on the thread count (each world steps the same on any).
pub(crate) fn in_batches<T: Sync, R: Send>(
    items: &[T],
    progress: &mut dyn FnMut(usize, usize),
    evaluate: impl Fn(&T) -> R + Sync,
) -> Vec<R> {
    use rayon::prelude::*;
    let mut out = Vec::with_capacity(items.len());
    for (b, batch) in items.chunks(BATCH).enumerate() {
        progress(b * BATCH, items.len());
        out.extend(batch.par_iter().map(&evaluate).collect::<Vec<_>>());
    }
    out
}

/// Runs the whole diagnosis of `model_dir` (dm-fit's output) on `bundle`
/// and writes `out/diagnosis.json`, `out/report.md`, plots and, when a
/// cause is named, `out/extended_model/model.json`: [`show`] where the
/// model departs, [`name`] the cause, [`extend`] the model with it,
/// [`detection_limits`] of the library's effects in this clip,
/// [`measure`] the gain, and [`discover_outside_library`].
pub fn diagnose(
    model_dir: &Path,
    bundle_dir: &Path,
    out: &Path,
    truth: Option<&Path>,
    options: &DiagnoseOptions,
    progress: Progress<'_>,
) -> Result<Diagnosis, DiagnoseError> {
    let bundle = Bundle::open(bundle_dir)?;
    let model_path = model_dir.join("model.json");
    let model = WorldModel::load(&model_path)?;
    let truth_value: Option<serde_json::Value> = truth
        .map(dm_bundle::read_json::<serde_json::Value>)
        .transpose()?;
    std::fs::create_dir_all(out).map_err(|e| DiagnoseError::Output {
        path: out.to_path_buf(),
        problem: e.to_string(),
    })?;

    let shown = show(&model, &bundle, options.device, progress)?;
    let mut named = name(model_dir, &model, &bundle, &shown, options, out, progress)?;
    let (extended, refit) = extend(&model, &model_path, &bundle, &mut named, options, progress)?;
    let limits = detection_limits(
        &model,
        &bundle,
        &shown,
        &named,
        extended.as_ref(),
        options,
        progress,
    )?;
    let measured = measure(out, &shown.base, extended.as_ref())?;
    let truth_cmp = truth_value.as_ref().map(|t| {
        compare_truth(
            t,
            &named.cause,
            &measured.effect_parameters,
            bundle.meta.fps,
        )
    });
    let (discovered, discovered_model) =
        discover_outside_library(&model, &bundle, &shown.base, options, out, progress)?;

    let Named {
        candidates,
        cause,
        confidence,
        trial_records,
        fit_records,
        ..
    } = named;
    let diagnosis = Diagnosis {
        cause,
        confidence,
        candidates,
        extended_model: measured.extended_model,
        gain: measured.gain,
        effect_parameters: measured.effect_parameters,
        threshold: options.none_threshold,
        candidates_fitted: options.fit_candidates,
        signatures: shown.signatures,
        regions_test: shown.regions_test,
        truth: truth_cmp,
        refit,
        discovered,
        discovered_model,
        detectability: limits,
        options: options.clone(),
    };
    progress("plots and report", 0, 1);
    let split = bundle.meta.split;
    let plot_inputs = plots::PlotInputs {
        bundle: &bundle,
        split,
        base_track: &shown.base.track_per_frame,
        extended_track: measured.after_per_frame.as_deref(),
        per_track_test: &shown.per_track_test,
        samples: &shown.samples,
        residual_dv: &shown.base_run.residual_dv,
        diagnosis: &diagnosis,
        up: shown.up,
        axis: shown.axis,
    };
    let plot_files = plots::write_plots(&plot_inputs, out)?;
    report::write_report(out, &diagnosis, &plot_files, &bundle, &shown.base_run)?;
    write_json_atomic(
        &out.join("trials.json"),
        &TrialsFile {
            train_frames: split.train,
            test_frames: split.test,
            base_track_per_frame: &shown.base.track_per_frame,
            trials: &trial_records,
            candidate_fits: &fit_records,
        },
    )?;
    write_json_atomic(&out.join("diagnosis.json"), &diagnosis)?;
    Ok(diagnosis)
}

/// What [`show`] finds: the fitted model's rollout and errors, where they
/// sit, and the residual accelerations' signatures.
struct Shown {
    base: Scored,
    base_run: Rollout,
    per_track_test: Vec<f64>,
    regions_test: Vec<analysis::RegionError>,
    samples: Vec<analysis::AccelSample>,
    signatures: signatures::Signatures,
    up: [f64; 3],
    axis: [f64; 3],
}

/// "Show": the fitted model rolled out, its errors per split, track and
/// region, and the signatures of the training frames' residual
/// accelerations (they orient the trials).
fn show(
    model: &WorldModel,
    bundle: &Bundle,
    device: Device,
    progress: Progress<'_>,
) -> Result<Shown, DiagnoseError> {
    progress("base rollout", 0, 1);
    let (base, base_run) = score_model(model, bundle, device)?;
    let split = bundle.meta.split;
    let matched = match_tracks(bundle, &base_run.positions);
    let up = model
        .physics
        .floor
        .as_ref()
        .map_or([0.0, 0.0, 1.0], |f| f.up);
    let floor_height = model.physics.floor.as_ref().map_or(0.0, |f| f.height);
    let axis = main_axis(&model.particles);
    let per_track_test = per_track_error(&matched, split.test);
    let regions_test = region_errors(bundle, &per_track_test, up, axis);
    let samples = analysis::residual_accelerations(&matched, bundle.meta.fps);
    // The signatures orient the trials, so they read only the frames that
    // choose the trials' parameters.
    let fit_end = selection_frames(split.train).fit[1];
    let fit_samples: Vec<_> = samples
        .iter()
        .copied()
        .filter(|s| s.frame + analysis::ACCEL_STRIDE < fit_end)
        .collect();
    let near_hand = near_hand_tracks(bundle);
    let hand_centroid: Vec<[f64; 3]> = (0..fit_end)
        .map(|t| centroid(&dm_model::hand_anchors(bundle, t)))
        .collect();
    let fit_matched = analysis::Matched {
        observed: matched.observed[..fit_end.min(matched.observed.len())].to_vec(),
        simulated: matched.simulated[..fit_end.min(matched.simulated.len())].to_vec(),
    };
    let signatures = signatures::signatures(
        &fit_samples,
        &fit_matched,
        &near_hand,
        &hand_centroid,
        up,
        floor_height,
        axis,
    );
    Ok(Shown {
        base,
        base_run,
        per_track_test,
        regions_test,
        samples,
        signatures,
        up,
        axis,
    })
}

/// What [`name`] decides, and the evidence behind it.
struct Named {
    /// Scores, best first.
    candidates: Vec<CandidateScore>,
    /// Each candidate's best trial and its scores.
    best_per_candidate: BTreeMap<&'static str, (Trial, Scored)>,
    cause: String,
    confidence: f64,
    trial_records: Vec<TrialRecord>,
    fit_records: Vec<TrialRecord>,
    /// Every trial's rollout (the detection limits score against them).
    trial_runs: Vec<detectability::TrialRun>,
}

/// "Name": every candidate's trials scored on the training frames (with
/// `--fit-candidates` the best one fitted from the start), each
/// candidate scored by min(train, held-out) reduction, the best named if
/// it clears the threshold.
fn name(
    model_dir: &Path,
    model: &WorldModel,
    bundle: &Bundle,
    shown: &Shown,
    options: &DiagnoseOptions,
    out: &Path,
    progress: Progress<'_>,
) -> Result<Named, DiagnoseError> {
    let base = &shown.base;
    let all_trials: Vec<Trial> = Candidate::ALL
        .iter()
        .flat_map(|&c| trials(c, model, &shown.signatures))
        .collect();
    let total = all_trials.len();
    let mut best_per_candidate: BTreeMap<&'static str, (Trial, Scored)> = BTreeMap::new();
    let mut trial_records = Vec::with_capacity(total);
    let mut trial_runs = Vec::with_capacity(total);
    let outcomes = in_batches(
        &all_trials,
        &mut |done, total| {
            let name = all_trials.get(done).map_or("", |t| t.candidate.name());
            progress(&format!("candidates ({name}…)"), done, total);
        },
        |trial| score_model(&trial.model, bundle, options.device),
    );
    for (trial, outcome) in all_trials.into_iter().zip(outcomes) {
        // A diverging or unbuildable trial scores infinity (e.g. a
        // stiffness needing more substeps than allowed).
        let scored = match outcome {
            Ok((scored, run)) => {
                trial_runs.push(detectability::TrialRun {
                    candidate: trial.candidate,
                    parameters: trial.parameters.clone(),
                    positions: run.positions,
                });
                scored
            }
            Err(_) => Scored::failed(),
        };
        let name = trial.candidate.name();
        trial_records.push(TrialRecord::new(name, &trial.parameters, &scored));
        let better = best_per_candidate
            .get(name)
            .is_none_or(|(_, s)| scored.track_fit < s.track_fit);
        if better {
            best_per_candidate.insert(name, (trial, scored));
        }
    }
    let mut fit_records = Vec::new();
    if options.fit_candidates {
        let fits = fit_candidates(
            model_dir,
            bundle,
            &best_per_candidate,
            options.device,
            out,
            progress,
        )?;
        for CandidateFit {
            name,
            model: fitted,
            scored,
        } in fits
        {
            if let Some((trial, best)) = best_per_candidate.get_mut(name) {
                trial.parameters =
                    with_learnt_parameters(trial.candidate, &trial.parameters, &fitted);
                fit_records.push(TrialRecord::new(name, &trial.parameters, &scored));
                trial.model = fitted;
                *best = scored;
            }
        }
    }
    let mut candidates: Vec<CandidateScore> = Candidate::ALL
        .iter()
        .filter_map(|c| {
            let (trial, scored) = best_per_candidate.get(c.name())?;
            let (signature, signature_agrees) = c.signature_text(&shown.signatures);
            let fit_reduction = relative_reduction(base.track_fit, scored.track_fit);
            let validation_reduction =
                relative_reduction(base.track_validation, scored.track_validation);
            Some(CandidateScore {
                name: c.name().into(),
                // A real effect explains error where its parameter was fitted
                // and on the frames after them; a term that only reshuffles the
                // error of a misfit model helps on one part at most.
                score: validation_reduction.min(fit_reduction),
                fit_reduction,
                validation_reduction,
                held_out_reduction: relative_reduction(base.track_test, scored.track_test),
                train_reduction: relative_reduction(base.track_train, scored.track_train),
                parameters: trial.parameters.clone(),
                signature,
                signature_agrees,
            })
        })
        .collect();
    candidates.sort_by(|a, b| b.score.total_cmp(&a.score));
    let best = candidates.first().map_or(0.0, |c| c.score.max(0.0));
    let second = candidates.get(1).map_or(0.0, |c| c.score.max(0.0));
    let cause = if best >= options.none_threshold {
        candidates[0].name.clone()
    } else {
        "none".to_string()
    };
    Ok(Named {
        confidence: confidence(best, second, options.none_threshold),
        candidates,
        best_per_candidate,
        cause,
        trial_records,
        fit_records,
        trial_runs,
    })
}

/// (before − after) / before, or −1 where `after` is not finite.
pub(crate) fn relative_reduction(before: f64, after: f64) -> f64 {
    if after.is_finite() && before > 0.0 {
        (before - after) / before
    } else {
        -1.0
    }
}

/// The extended model, its scores and its effect parameters.
type Extension = (WorldModel, Scored, BTreeMap<String, f64>);

/// "Extend": the named candidate's trial refined on the training frames,
/// then its material refitted with the effect in place (kept only if it
/// lowers the training error); nothing when the cause is `none`.
fn extend(
    model: &WorldModel,
    model_path: &Path,
    bundle: &Bundle,
    named: &mut Named,
    options: &DiagnoseOptions,
    progress: Progress<'_>,
) -> Result<(Option<Extension>, Option<RefitRecord>), DiagnoseError> {
    if named.cause == "none" {
        return Ok((None, None));
    }
    let (trial, scored) = named
        .best_per_candidate
        .remove(named.cause.as_str())
        .ok_or_else(|| DiagnoseError::Input {
            path: model_path.to_path_buf(),
            problem: "internal: the named candidate has no trial".into(),
        })?;
    let mut best_trial = (trial, scored);
    // A candidate fitted from the start already carries its refitted
    // material and gains; refining its effect on the original fit's
    // material would mix the two.
    let refine = if options.fit_candidates {
        Vec::new()
    } else {
        refinements(&best_trial.0, model)
    };
    let effect_trials = refine.len();
    for (i, t) in refine.into_iter().enumerate() {
        progress("refining the effect parameter", i, effect_trials);
        let s = score_trial(&t.model, bundle, options.device);
        if s.track_train < best_trial.1.track_train {
            best_trial = (t, s);
        }
    }
    let (trial, mut scored) = best_trial;
    let mut extended_model = trial.model.clone();
    let (record, refitted) = if options.fit_candidates {
        let device = options.device.for_model(&extended_model)?;
        let before = train_loss_on(&extended_model, bundle, bundle.meta.split.train[1], device)?;
        (
            RefitRecord {
                effect_trials: 0,
                material_iterations: 0,
                train_loss_before: before,
                train_loss_after: before,
                material_kept: false,
                note: "fitted from the start with the effect in place (--fit-candidates)".into(),
            },
            None,
        )
    } else {
        refit_material(&extended_model, bundle, options, progress)?
    };
    if let Some(refitted) = refitted {
        let s = score_trial(&refitted, bundle, options.device);
        if s.track_train < scored.track_train {
            extended_model = refitted;
            scored = s;
        }
    }
    let record = RefitRecord {
        material_kept: extended_model != trial.model,
        effect_trials,
        ..record
    };
    let parameters = with_learnt_parameters(trial.candidate, &trial.parameters, &extended_model);
    Ok((Some((extended_model, scored, parameters)), Some(record)))
}

/// What [`measure`] reports.
struct Measured {
    gain: Gain,
    effect_parameters: BTreeMap<String, f64>,
    after_per_frame: Option<Vec<f64>>,
    extended_model: Option<String>,
}

/// "Measure": the extended model written to `out/extended_model/` and
/// its test-split gain over the fitted model (none without a cause).
fn measure(
    out: &Path,
    base: &Scored,
    extended: Option<&Extension>,
) -> Result<Measured, DiagnoseError> {
    let Some((model, scored, parameters)) = extended else {
        return Ok(Measured {
            gain: Gain {
                track_before: base.track_test,
                track_after: base.track_test,
                chamfer_before: base.chamfer_test,
                chamfer_after: base.chamfer_test,
            },
            effect_parameters: BTreeMap::new(),
            after_per_frame: None,
            extended_model: None,
        });
    };
    let dir = out.join("extended_model");
    write_model(&dir, model)?;
    Ok(Measured {
        gain: Gain {
            track_before: base.track_test,
            track_after: scored.track_test,
            chamfer_before: base.chamfer_test,
            chamfer_after: scored.chamfer_test,
        },
        effect_parameters: parameters.clone(),
        after_per_frame: Some(scored.track_per_frame.clone()),
        extended_model: Some(dir.display().to_string()),
    })
}

/// "Detectability" (`detectability.rs`): each library effect's limit,
/// injected into the fitted model or, when a cause is named, into the
/// extended model (its trials rolled out again there); nothing with
/// `--detect-steps 0`.
fn detection_limits(
    model: &WorldModel,
    bundle: &Bundle,
    shown: &Shown,
    named: &Named,
    extended: Option<&Extension>,
    options: &DiagnoseOptions,
    progress: Progress<'_>,
) -> Result<BTreeMap<String, detectability::Limit>, DiagnoseError> {
    if options.detect_steps == 0 {
        return Ok(BTreeMap::new());
    }
    let limits = |model: &WorldModel,
                  positions: &[Vec<[f32; 3]>],
                  runs: &[detectability::TrialRun],
                  progress: Progress<'_>| {
        detectability::detectability(
            model,
            bundle,
            positions,
            runs,
            options.none_threshold,
            options.detect_steps,
            options.device,
            progress,
        )
    };
    match extended {
        Some((extended, _, _)) => {
            let cause = Candidate::ALL
                .iter()
                .copied()
                .find(|c| c.name() == named.cause);
            let runs = detectability::trial_runs(
                extended,
                bundle,
                &shown.signatures,
                cause,
                options.device,
                progress,
            );
            let positions = rollout(extended, bundle, options.device)?.positions;
            limits(extended, &positions, &runs, progress)
        }
        None => limits(
            model,
            &shown.base_run.positions,
            &named.trial_runs,
            progress,
        ),
    }
}

/// "Discover" (`discover.rs`): the body force outside the library, its
/// model written to `out/discovered_model/`; nothing with
/// `--discover-iters 0`.
fn discover_outside_library(
    model: &WorldModel,
    bundle: &Bundle,
    base: &Scored,
    options: &DiagnoseOptions,
    out: &Path,
    progress: Progress<'_>,
) -> Result<(Option<discover::Discovered>, Option<String>), DiagnoseError> {
    if options.discover_iters == 0 {
        return Ok((None, None));
    }
    let found = discover::discover(model, bundle, base, options.discover_iters, progress)?;
    let path = match &found.model {
        Some(m) => {
            let dir = out.join("discovered_model");
            write_model(&dir, m)?;
            Some(dir.display().to_string())
        }
        None => None,
    };
    Ok((Some(found.discovered), path))
}

/// `dir/model.json`, the directory made first.
fn write_model(dir: &Path, model: &WorldModel) -> Result<(), DiagnoseError> {
    std::fs::create_dir_all(dir).map_err(|e| DiagnoseError::Output {
        path: dir.to_path_buf(),
        problem: e.to_string(),
    })?;
    write_json_atomic(&dir.join("model.json"), model)?;
    Ok(())
}

/// Confidence in the answer, 0–1. For a named cause: the margin over the
/// runner-up relative to the best score, times how far the best clears
/// the threshold (saturating at twice the threshold). For `none`: how far
/// the best score stays below the threshold.
pub fn confidence(best: f64, second: f64, threshold: f64) -> f64 {
    if best >= threshold {
        let margin = ((best - second) / best).clamp(0.0, 1.0);
        let clearance = (best / (2.0 * threshold)).clamp(0.0, 1.0);
        (0.5 + 0.5 * margin) * clearance
    } else {
        (1.0 - best / threshold).clamp(0.0, 1.0)
    }
}

fn centroid(points: &[[f64; 3]]) -> [f64; 3] {
    let n = points.len().max(1) as f64;
    [0, 1, 2].map(|a| points.iter().map(|p| p[a]).sum::<f64>() / n)
}

/// The third of the tracks nearest the hands at frame 0.
fn near_hand_tracks(bundle: &Bundle) -> Vec<usize> {
    let hands = dm_model::hand_anchors(bundle, 0);
    let p = &bundle.tracks.object_points;
    let mut d: Vec<(f64, usize)> = (0..p.shape()[1])
        .map(|k| {
            let x = [0, 1, 2].map(|a| p[[0, k, a]] as f64);
            let dist = hands
                .iter()
                .map(|h| analysis::norm([h[0] - x[0], h[1] - x[1], h[2] - x[2]]))
                .fold(f64::INFINITY, f64::min);
            (dist, k)
        })
        .collect();
    d.sort_by(|a, b| a.0.total_cmp(&b.0));
    d.iter().take((d.len() / 3).max(1)).map(|x| x.1).collect()
}

/// A candidate's fit from the start and its errors.
struct CandidateFit {
    name: &'static str,
    model: WorldModel,
    scored: Scored,
}

/// Each candidate's best trial fitted from the start: the fitted model's
/// own dm-fit options (its run record), the bundle's default starting
/// model with the effect added. A fit that fails (e.g. diverges) scores
/// infinity.
fn fit_candidates(
    model_dir: &Path,
    bundle: &Bundle,
    best: &BTreeMap<&'static str, (Trial, Scored)>,
    device: Device,
    out: &Path,
    progress: Progress<'_>,
) -> Result<Vec<CandidateFit>, DiagnoseError> {
    let report_path = model_dir.join("fit_report.json");
    let report: dm_fit::run::FitReport = dm_bundle::read_json(&report_path)?;
    let mut options = report.options;
    let mut fitted = Vec::with_capacity(best.len());
    for (i, (&name, (trial, _))) in best.iter().enumerate() {
        progress(
            &format!("fitting with {name} from the start"),
            i,
            best.len(),
        );
        let start = WorldModel::from_bundle(bundle, &options.model)?;
        let start = apply(&start, trial.candidate, &trial.parameters);
        options.device = device.for_model(&start)?;
        let dir = out.join("candidate_fits").join(name);
        let result = dm_fit::run::run_fit_from(bundle, &options, start, &dir, &mut |_| {})
            .and_then(|_| Ok(WorldModel::load(&dir.join("model.json"))?));
        match result {
            Ok(model) => fitted.push(CandidateFit {
                name,
                scored: score_trial(&model, bundle, device),
                model,
            }),
            Err(_) => fitted.push(CandidateFit {
                name,
                model: trial.model.clone(),
                scored: Scored::failed(),
            }),
        }
    }
    Ok(fitted)
}

/// A few material Adam steps with the effect in place (every effect's
/// state adjoint exists in dm-mpm).
fn refit_material(
    model: &WorldModel,
    bundle: &Bundle,
    options: &DiagnoseOptions,
    progress: Progress<'_>,
) -> Result<(RefitRecord, Option<WorldModel>), DiagnoseError> {
    let frames = bundle.meta.split.train[1];
    let device = options.device.for_model(model)?;
    let before = train_loss_on(model, bundle, frames, device)?;
    let blank = |note: &str| RefitRecord {
        effect_trials: 0,
        material_iterations: 0,
        train_loss_before: before,
        train_loss_after: before,
        material_kept: false,
        note: note.into(),
    };
    if options.refit_iters == 0 {
        return Ok((blank("material refit disabled (--refit-iters 0)"), None));
    }
    let mut refitted = model.clone();
    let config = MaterialFitConfig {
        iterations: options.refit_iters,
        device,
        ..MaterialFitConfig::default()
    };
    let mut done = 0;
    let result = fit_material(&mut refitted, bundle, &config, &mut |_| {
        done += 1;
        progress("refitting the material", done, options.refit_iters);
    });
    if let Err(e) = result {
        return Ok((
            blank(&format!("material refit failed, kept the effect fit: {e}")),
            None,
        ));
    }
    let after = train_loss_on(&refitted, bundle, frames, device)?;
    Ok((
        RefitRecord {
            effect_trials: 0,
            material_iterations: options.refit_iters,
            train_loss_before: before,
            train_loss_after: after,
            material_kept: false,
            note: "effect parameter by search on the train split, then material Adam steps \
                   through the simulator with the effect in place (gains held)"
                .into(),
        },
        Some(refitted),
    ))
}

/// The truth file's effect against the diagnosis. Parameter keys map
/// truth → fitted (with unit conversions where they differ).
fn compare_truth(
    truth: &serde_json::Value,
    cause: &str,
    fitted: &BTreeMap<String, f64>,
    fps: f64,
) -> TruthComparison {
    let effect = truth.get("effect").filter(|e| !e.is_null());
    let truth_name = effect
        .and_then(|e| e.get("name"))
        .and_then(|n| n.as_str())
        .unwrap_or("none")
        .to_string();
    let library_name = if truth_name == "air_drag_quadratic" {
        "air_drag".to_string()
    } else {
        truth_name.clone()
    };
    let truth_params = effect
        .and_then(|e| e.get("params"))
        .cloned()
        .unwrap_or(serde_json::Value::Null);
    let get = |k: &str| truth_params.get(k).and_then(|v| v.as_f64());
    let pairs: [(&str, &str, f64); 9] = [
        ("linear_per_s", "linear_per_s", 1.0),
        ("quadratic_per_m", "quadratic_per_m", 1.0),
        ("coefficient", "coefficient", 1.0),
        ("yield_stretch", "yield_stretch", 1.0),
        ("stiffness_factor", "stiffness_factor", 1.0),
        ("viscosity_pa_s", "viscosity_pa_s", 1.0),
        ("tilt_deg", "tilt_deg", 1.0),
        ("lag_s", "lag_frames", 1.0 / fps),
        ("heavy_end_excess", "heavy_end_excess", 1.0),
    ];
    let relative_error = if library_name == cause {
        pairs.iter().find_map(|(tk, fk, scale)| {
            let t = get(tk)?;
            let f = fitted.get(*fk)? * scale;
            // The density gradient's sign depends on the axis direction; compare magnitudes.
            let f = if *fk == "heavy_end_excess" {
                f.abs()
            } else {
                f
            };
            (t != 0.0).then(|| f / t - 1.0)
        })
    } else {
        None
    };
    TruthComparison {
        name_correct: library_name == cause,
        truth_effect: truth_name,
        truth_params,
        relative_error,
    }
}

/// Re-exported for the CLI and tests: the model with one candidate applied.
pub fn model_with(
    base: &WorldModel,
    candidate: Candidate,
    parameters: &BTreeMap<String, f64>,
) -> WorldModel {
    apply(base, candidate, parameters)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Batched trials come back in the trials' order whatever the thread
    /// count, with progress reported before each batch.
    #[test]
    fn batches_keep_the_order_on_any_thread_count() {
        let items: Vec<u64> = (0..19).collect();
        let slow_square = |&i: &u64| {
            std::thread::sleep(std::time::Duration::from_millis(19 - i));
            i * i
        };
        let mut reported = Vec::new();
        let wide = in_batches(
            &items,
            &mut |done, total| reported.push((done, total)),
            slow_square,
        );
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .expect("pool")
            .install(|| in_batches(&items, &mut |_, _| {}, slow_square));
        let expected: Vec<u64> = items.iter().map(|i| i * i).collect();
        assert_eq!(wide, expected);
        assert_eq!(one, expected);
        assert_eq!(reported, [(0, 19), (8, 19), (16, 19)]);
    }

    #[test]
    fn validation_frames_are_the_training_splits_last_quarter() {
        let frames = selection_frames([0, 25]);
        assert_eq!(frames.fit, [0, 19]);
        assert_eq!(frames.validation, [19, 25]);
        // At least two frames each, and never past the split.
        let short = selection_frames([3, 7]);
        assert_eq!((short.fit, short.validation), ([3, 5], [5, 7]));
        let tiny = selection_frames([0, 3]);
        assert_eq!((tiny.fit, tiny.validation), ([0, 2], [2, 3]));
    }
}
