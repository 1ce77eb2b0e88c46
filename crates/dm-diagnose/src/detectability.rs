//! "Detectability": for each library effect, the smallest magnitude this
//! clip would reveal. The effect is injected into the fitted model at a
//! magnitude, and the displacement it causes (its rollout minus the
//! fitted model's, at the particles matched to the tracks) is added to
//! the recorded tracks, so the clip's own track noise, its hand action
//! and the fitted model's misfit all stay in the data. The candidate's own
//! trials (the rollouts the naming scored) are then scored against those
//! tracks exactly as the naming scores them; the effect is revealed when
//! its score clears the `none` threshold. The magnitude is scanned at
//! [`SCAN_POINTS`] log-spaced values over [`search_range`] (the score need
//! not grow with the magnitude: a lag far beyond the trials' is matched by
//! none of them), then bisected on a log scale below the weakest revealed
//! one.
//!
//! The model injected into is the one that explains the clip best: the
//! fitted model when the cause is `none`, the extended model when a cause
//! is named (otherwise the named effect's own error, still in the tracks,
//! would reveal every effect that resembles it at any magnitude; a toy with
//! quadratic drag "revealed" a lag of 0.01 s). The named effect itself
//! gets no limit.
//!
//! The model did not see the injected effect, so none of it is absorbed
//! into the material or the gains as a real fit would absorb part of it:
//! an effect the material can mimic may go unnamed above its limit.

use crate::analysis::rollout;
use crate::candidates::{Candidate, apply, trials};
use crate::signatures::Signatures;
use crate::{DiagnoseError, Progress, relative_reduction, selection_frames};
use dm_bundle::{Bundle, Tracks};
use dm_model::WorldModel;
use dm_model::device::Device;
use dm_model::metrics::{match_tracks, split_mean, track_errors};
use serde::Serialize;
use std::collections::BTreeMap;

/// Bisection steps below the weakest revealed scan point (each narrows
/// the bracket's ratio to its square root: 3 steps take the scan's 2.5×
/// to 12 %).
pub const DEFAULT_DETECT_STEPS: usize = 3;
/// Log-spaced magnitudes scanned over the search range, its ends included.
pub const SCAN_POINTS: usize = 6;

/// `detectability.NAME` in `diagnosis.json`.
#[derive(Clone, Debug, Serialize)]
pub struct Limit {
    /// The weakest magnitude found that this clip reveals, in the units of
    /// `dm-synth --effect NAME:MAGNITUDE`; `null` when no magnitude
    /// searched is revealed.
    pub min_magnitude: Option<f64>,
    pub unit: String,
    /// `above`: larger magnitudes are stronger effects; `below` for
    /// plasticity, whose yield stretch is the weaker the larger it is.
    pub stronger: Stronger,
    /// The magnitudes searched, [low, high].
    pub searched: [f64; 2],
    /// The candidate's score at `min_magnitude` (the best scan score when
    /// nothing was revealed).
    pub score: f64,
    /// Each scanned magnitude with the candidate's score there.
    pub scan: Vec<[f64; 2]>,
    /// The effect's parameters at `min_magnitude` (at the strongest
    /// magnitude when nothing was revealed), in the candidate's terms, in
    /// the least visible of the orientations tried (tilt azimuth, ball
    /// centre, density axis and end).
    pub injected: BTreeMap<String, f64>,
    /// For an effect this clip cannot reveal: the variant of the recorded
    /// action revealing the weakest magnitude, and that magnitude (`null`
    /// when none does).
    pub next_action: Option<NextAction>,
}

/// Which way a magnitude grows the effect.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Stronger {
    Above,
    Below,
}

/// A library trial's rollout, kept from the naming to score injected
/// effects against.
pub(crate) struct TrialRun {
    pub candidate: Candidate,
    pub parameters: BTreeMap<String, f64>,
    pub positions: Vec<Vec<[f32; 3]>>,
}

/// How a candidate's dm-synth magnitude maps to its parameter.
struct MagnitudeScale {
    /// The candidate's parameter set to the magnitude.
    key: &'static str,
    unit: &'static str,
    /// Parameter per unit of magnitude (a lag's frames per second).
    per_magnitude: f64,
    stronger: Stronger,
}

fn magnitude_scale(candidate: Candidate, fps: f64) -> MagnitudeScale {
    let (key, unit, per_magnitude) = match candidate {
        Candidate::AirDrag => ("linear_per_s", "1/s", 1.0),
        Candidate::FloorFriction => ("coefficient", "μ", 1.0),
        Candidate::Plasticity => ("yield_stretch", "yield stretch", 1.0),
        Candidate::ViscousDamping => ("viscosity_pa_s", "Pa·s", 1.0),
        Candidate::StiffInclusion => ("stiffness_factor", "× stiffness", 1.0),
        Candidate::GroundTilt => ("tilt_deg", "deg", 1.0),
        Candidate::ActuatorLag => ("lag_frames", "s", fps),
        Candidate::DensityVariation => ("heavy_end_excess", "heavy-end excess", 1.0),
    };
    MagnitudeScale {
        key,
        unit,
        per_magnitude,
        // A smaller yield stretch is the stronger plasticity.
        stronger: if candidate == Candidate::Plasticity {
            Stronger::Below
        } else {
            Stronger::Above
        },
    }
}

/// The magnitudes searched for each effect, in dm-synth's units: from
/// well under what a few-second clip shows to well over dm-synth's test
/// ranges.
pub fn search_range(candidate: Candidate) -> [f64; 2] {
    match candidate {
        Candidate::AirDrag => [1.0, 100.0],
        Candidate::FloorFriction => [0.05, 2.0],
        Candidate::Plasticity => [0.003, 0.3],
        Candidate::ViscousDamping => [100.0, 1.0e5],
        // Stiffer balls need more substeps than a model may take.
        Candidate::StiffInclusion => [1.5, 30.0],
        Candidate::GroundTilt => [0.5, 20.0],
        Candidate::ActuatorLag => [0.01, 0.4],
        Candidate::DensityVariation => [0.2, 8.0],
    }
}

/// What the scoring of one injected magnitude needs.
struct Injection<'a> {
    model: &'a WorldModel,
    /// The hands, frames and splits.
    bundle: &'a Bundle,
    /// The tracks the injected displacement is added to.
    observed: &'a Tracks,
    base_positions: &'a [Vec<[f32; 3]>],
    matched: Vec<Option<usize>>,
    threshold: f64,
    device: Device,
}

impl Injection<'_> {
    /// The candidate's score on the recorded tracks with `candidate` at
    /// `parameters` injected; `None` where the injected model cannot be
    /// rolled out.
    fn score(
        &self,
        candidate: Candidate,
        parameters: &BTreeMap<String, f64>,
        trials: &[&TrialRun],
    ) -> Option<f64> {
        let injected = apply(self.model, candidate, parameters);
        let run = rollout(&injected, self.bundle, self.device).ok()?;
        let tracks = self.displaced_tracks(&run.positions);
        let frames = selection_frames(self.bundle.meta.split.train);
        let errors = |positions: &[Vec<[f32; 3]>]| {
            let per_frame = track_errors(positions, &tracks, &self.matched);
            (
                split_mean(&per_frame, frames.fit),
                split_mean(&per_frame, frames.validation),
            )
        };
        let (base_fit, base_validation) = errors(self.base_positions);
        let best = trials
            .iter()
            .map(|t| errors(&t.positions))
            .filter(|(fit, _)| fit.is_finite())
            .min_by(|a, b| a.0.total_cmp(&b.0))?;
        Some(relative_reduction(base_fit, best.0).min(relative_reduction(base_validation, best.1)))
    }

    /// The observed tracks moved by the injected effect's displacement of
    /// each track's matched particle.
    fn displaced_tracks(&self, injected: &[Vec<[f32; 3]>]) -> Tracks {
        displaced(self.observed, injected, self.base_positions, &self.matched)
    }
}

/// The library's trials on `model` rolled out (every candidate but
/// `named`); a trial that cannot be rolled out is left out.
pub(crate) fn trial_runs(
    model: &WorldModel,
    bundle: &Bundle,
    signatures: &Signatures,
    named: Option<Candidate>,
    device: Device,
    progress: Progress<'_>,
) -> Vec<TrialRun> {
    let all: Vec<_> = Candidate::ALL
        .iter()
        .filter(|&&c| Some(c) != named)
        .flat_map(|&c| trials(c, model, signatures))
        .collect();
    let runs = crate::in_batches(
        &all,
        &mut |done, total| progress("trials on the extended model", done, total),
        |trial| rollout(&trial.model, bundle, device).ok(),
    );
    all.into_iter()
        .zip(runs)
        .filter_map(|(trial, run)| {
            Some(TrialRun {
                candidate: trial.candidate,
                parameters: trial.parameters,
                positions: run?.positions,
            })
        })
        .collect()
}

/// Each library effect's detection limit on this clip (module docs), with
/// `steps` bisection steps: `model` is the one injected into, with its
/// rollout's `base_positions` and its library `trials` rolled out (a
/// candidate without trials gets no limit). An effect this clip cannot
/// reveal is tried under each [`ActionVariant`].
pub(crate) fn detectability(
    model: &WorldModel,
    bundle: &Bundle,
    base_positions: &[Vec<[f32; 3]>],
    trials: &[TrialRun],
    threshold: f64,
    steps: usize,
    device: Device,
    progress: Progress<'_>,
) -> Result<BTreeMap<String, Limit>, DiagnoseError> {
    let first: Vec<[f64; 3]> = base_positions
        .first()
        .map(|frame| frame.iter().map(|p| p.map(f64::from)).collect())
        .unwrap_or_default();
    let injection = Injection {
        model,
        bundle,
        observed: &bundle.tracks,
        base_positions,
        matched: match_tracks(&first, &bundle.tracks),
        threshold,
        device,
    };
    // Each effect's bisection on its own, the effects side by side.
    let found = crate::in_batches(
        &Candidate::ALL,
        &mut |done, total| progress("detectability of the library's effects", done, total),
        |&candidate| {
            let own: Vec<&TrialRun> = trials.iter().filter(|t| t.candidate == candidate).collect();
            least_visible(&injection, candidate, &own, steps)
        },
    );
    let mut limits = BTreeMap::new();
    for (candidate, limit) in Candidate::ALL.iter().zip(found) {
        if let Some(limit) = limit {
            limits.insert(candidate.name().to_string(), limit);
        }
    }
    let untestable: Vec<Candidate> = Candidate::ALL
        .iter()
        .copied()
        .filter(|c| {
            limits
                .get(c.name())
                .is_some_and(|l: &Limit| l.min_magnitude.is_none())
        })
        .collect();
    if untestable.is_empty() {
        return Ok(limits);
    }
    for (v, variant) in ActionVariant::ALL.iter().enumerate() {
        progress(
            &format!("detectability under the action {}", variant.name()),
            v,
            ActionVariant::ALL.len(),
        );
        let varied = variant.bundle(bundle);
        let Ok(run) = rollout(model, &varied, device) else {
            continue;
        };
        let observed = displaced(
            &bundle.tracks,
            &run.positions,
            base_positions,
            &injection.matched,
        );
        let varied_injection = Injection {
            model,
            bundle: &varied,
            observed: &observed,
            base_positions: &run.positions,
            matched: injection.matched.clone(),
            threshold,
            device,
        };
        let found = crate::in_batches(&untestable, &mut |_, _| {}, |&candidate| {
            let own: Vec<TrialRun> = trials
                .iter()
                .filter(|t| t.candidate == candidate)
                .filter_map(|t| {
                    let trial = apply(model, candidate, &t.parameters);
                    Some(TrialRun {
                        candidate,
                        parameters: t.parameters.clone(),
                        positions: rollout(&trial, &varied, device).ok()?.positions,
                    })
                })
                .collect();
            let own: Vec<&TrialRun> = own.iter().collect();
            least_visible(&varied_injection, candidate, &own, steps)
        });
        for (&candidate, found) in untestable.iter().zip(found) {
            let Some(found) = found else {
                continue;
            };
            let (Some(magnitude), Some(limit)) =
                (found.min_magnitude, limits.get_mut(candidate.name()))
            else {
                continue;
            };
            let weaker = |a: f64, b: f64| match found.stronger {
                Stronger::Above => a < b,
                Stronger::Below => a > b,
            };
            if limit
                .next_action
                .as_ref()
                .is_none_or(|n| weaker(magnitude, n.min_magnitude))
            {
                limit.next_action = Some(NextAction {
                    action: variant.name().into(),
                    min_magnitude: magnitude,
                });
            }
        }
    }
    Ok(limits)
}

/// A variant of the recorded hand action: the experiment to film next for
/// an effect this clip cannot reveal. Simulated with the model under the
/// variant's hands, the observations being its rollout plus this clip's
/// residual (its track offsets, noise and the model's misfit).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ActionVariant {
    /// The recorded hand path played twice as fast, then held.
    TwiceAsFast,
    /// The recorded hand path with twice its travel from the first frame.
    TwiceTheTravel,
}

impl ActionVariant {
    pub const ALL: [ActionVariant; 2] = [ActionVariant::TwiceAsFast, ActionVariant::TwiceTheTravel];

    pub fn name(self) -> &'static str {
        match self {
            ActionVariant::TwiceAsFast => "the recorded action twice as fast",
            ActionVariant::TwiceTheTravel => "the recorded action with twice the hand travel",
        }
    }

    /// `bundle` with its hand track replaced by the variant's.
    pub fn bundle(self, bundle: &Bundle) -> Bundle {
        let mut varied = bundle.clone();
        let recorded = &bundle.tracks.hand_points;
        let frames = recorded.shape()[0];
        let hands = &mut varied.tracks.hand_points;
        for t in 0..frames {
            for m in 0..recorded.shape()[1] {
                for a in 0..3 {
                    hands[[t, m, a]] = match self {
                        ActionVariant::TwiceAsFast => recorded[[(2 * t).min(frames - 1), m, a]],
                        ActionVariant::TwiceTheTravel => {
                            let start = recorded[[0, m, a]];
                            start + 2.0 * (recorded[[t, m, a]] - start)
                        }
                    };
                }
            }
        }
        varied
    }
}

/// `next_action` of a [`Limit`].
#[derive(Clone, Debug, Serialize)]
pub struct NextAction {
    /// The hand action ([`ActionVariant::name`]).
    pub action: String,
    /// The weakest magnitude it reveals (the limit's units).
    pub min_magnitude: f64,
}

/// `tracks` with each track moved by its matched particle's displacement
/// `moved − fitted` at every frame both rollouts have. Under a varied
/// action (`moved` its rollout, `fitted` the recorded one's, `tracks` the
/// recorded ones) this carries the clip's residual — offsets, noise and
/// the model's misfit — over to the new action at its recorded size.
fn displaced(
    tracks: &Tracks,
    moved: &[Vec<[f32; 3]>],
    fitted: &[Vec<[f32; 3]>],
    matched: &[Option<usize>],
) -> Tracks {
    let mut tracks = tracks.clone();
    let frames = tracks.frame_count().min(moved.len()).min(fitted.len());
    for t in 0..frames {
        for (k, particle) in matched.iter().enumerate() {
            let Some(i) = *particle else { continue };
            let (Some(m), Some(f)) = (moved[t].get(i), fitted[t].get(i)) else {
                continue;
            };
            for a in 0..3 {
                tracks.object_points[[t, k, a]] += m[a] - f[a];
            }
        }
    }
    tracks
}

/// Trials whose orientations the limit is measured in: the first trial's
/// and one turned from it (the tilt 90° round, the density gradient along
/// the second axis, the stiff ball in the middle instead of near an end).
/// A 3° tilt of a held cloth moved it 6.1 mm towards one azimuth and
/// 1.4 mm towards the azimuth 100° from it (draw 9104's null twin).
fn orientations<'a>(candidate: Candidate, trials: &[&'a TrialRun]) -> Vec<&'a TrialRun> {
    let picks: &[usize] = match candidate {
        Candidate::GroundTilt => &[0, 2],
        Candidate::DensityVariation => &[0, 2],
        Candidate::StiffInclusion => &[0, 1],
        _ => &[0],
    };
    picks
        .iter()
        .filter_map(|&i| trials.get(i).copied())
        .collect()
}

/// The limit of the least visible of the candidate's [`orientations`]: an
/// effect is ruled out above a magnitude only if every orientation tried
/// reveals it there. `None` without trials.
fn least_visible(
    injection: &Injection<'_>,
    candidate: Candidate,
    trials: &[&TrialRun],
    steps: usize,
) -> Option<Limit> {
    let mut worst: Option<Limit> = None;
    for reference in orientations(candidate, trials) {
        let limit = bisect(injection, candidate, &reference.parameters, trials, steps);
        let less_visible = match (&worst, limit.min_magnitude) {
            (None, _) => true,
            (Some(w), None) => w.min_magnitude.is_some(),
            (Some(w), Some(m)) => w.min_magnitude.is_some_and(|wm| match limit.stronger {
                Stronger::Above => m > wm,
                Stronger::Below => m < wm,
            }),
        };
        if less_visible {
            worst = Some(limit);
        }
        // Nothing can be less visible than not revealed at all.
        if worst.as_ref().is_some_and(|w| w.min_magnitude.is_none()) {
            break;
        }
    }
    worst
}

/// The weakest revealed magnitude of `candidate` oriented as `reference`
/// (a trial's parameters): a scan, then bisection on a log scale.
fn bisect(
    injection: &Injection<'_>,
    candidate: Candidate,
    reference: &BTreeMap<String, f64>,
    trials: &[&TrialRun],
    steps: usize,
) -> Limit {
    let scale = magnitude_scale(candidate, injection.bundle.meta.fps);
    // A density gradient keeps the reference trial's heavy end; every
    // other magnitude is positive as dm-synth's (a lag: the recorded hands
    // run late).
    let sign = match reference.get(scale.key) {
        Some(v) if candidate == Candidate::DensityVariation && *v < 0.0 => -1.0,
        _ => 1.0,
    };
    let parameters = |magnitude: f64| {
        let mut p = reference.clone();
        p.insert(
            scale.key.to_string(),
            sign * magnitude * scale.per_magnitude,
        );
        p
    };
    let score = |magnitude: f64| {
        injection
            .score(candidate, &parameters(magnitude), trials)
            .unwrap_or(f64::NEG_INFINITY)
    };
    let [low, high] = search_range(candidate);
    let stronger = scale.stronger;
    // Weakest first.
    let mut scan: Vec<f64> = (0..SCAN_POINTS)
        .map(|i| low * (high / low).powf(i as f64 / (SCAN_POINTS - 1).max(1) as f64))
        .collect();
    if stronger == Stronger::Below {
        scan.reverse();
    }
    let mut scores = Vec::with_capacity(SCAN_POINTS);
    let mut revealed = None;
    for (i, &magnitude) in scan.iter().enumerate() {
        let s = score(magnitude);
        scores.push([magnitude, s]);
        if s >= injection.threshold {
            revealed = Some((i, s));
            break;
        }
    }
    let limit = |min_magnitude: Option<f64>, at: f64, score: f64, scan: Vec<[f64; 2]>| Limit {
        min_magnitude,
        unit: scale.unit.to_string(),
        stronger,
        searched: [low, high],
        score,
        scan,
        injected: parameters(at),
        next_action: None,
    };
    let Some((first, first_score)) = revealed else {
        let best = scores
            .iter()
            .map(|s| s[1])
            .fold(f64::NEG_INFINITY, f64::max);
        let strongest = *scan.last().unwrap_or(&high);
        return limit(None, strongest, best, scores);
    };
    if first == 0 {
        return limit(Some(scan[0]), scan[0], first_score, scores);
    }
    // Invariant: `weak` is not revealed, `strong` is.
    let (mut weak, mut strong, mut strong_score) = (scan[first - 1], scan[first], first_score);
    for _ in 0..steps {
        let mid = (weak * strong).sqrt();
        let s = score(mid);
        if s >= injection.threshold {
            (strong, strong_score) = (mid, s);
        } else {
            weak = mid;
        }
    }
    limit(Some(strong), strong, strong_score, scores)
}
