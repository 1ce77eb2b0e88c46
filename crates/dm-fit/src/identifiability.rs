//! How well a clip *can* determine the fitted parameters, whatever the
//! optimiser does: the Cramér–Rao lower bound of the observed tracks.
//!
//! [`sensitivity`](crate::sensitivity) says how much the training loss
//! moves when E or ν is moved; this says how many standard deviations of
//! the measurement noise that move is worth once the other fitted
//! parameters (the actuator gains) may compensate. For Gaussian track noise
//! of σ per axis and frame, plus a constant offset of σ_o per track and
//! axis (the sensor's bias and the track's match to a particle), the
//! tracks' Fisher information about θ is
//!
//! ```text
//! F = Σ_{track, axis} Jᵀ Σ⁻¹ J,   Σ = σ² I + σ_o² 1 1ᵀ,
//! Σ⁻¹ = (I − c 1 1ᵀ) / σ²,        c = σ_o² / (σ² + m σ_o²),
//! ```
//!
//! with J the (m × P) sensitivity of that track's simulated positions over
//! its m observed training frames to the P parameters, taken by central
//! differences of whole rollouts. Any unbiased estimator's covariance is
//! at least F⁻¹; fixing a parameter (treating it as known) uses the
//! inverse of the remaining block instead. The bound is optimistic: it
//! ignores the noise on the hand tracks that drive the model and the
//! model's own mismatch to the world, so a parameter whose bound is wider
//! than a tolerance cannot be recovered to that tolerance from the clip.

use crate::loss::{ObservedFrame, TrackMatch};
use crate::material_fit::FitError;
use crate::sensitivity::moved_material;
use dm_bundle::Bundle;
use dm_model::WorldModel;
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// A fitted parameter the information is taken over. Scale parameters are
/// taken in log space, so their bound reads as a relative error.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Parameter {
    /// ln E of every patch at once (the homogeneous direction).
    LnYoungs,
    /// ν of every patch at once.
    Poisson,
    /// ln k_p of the actuators.
    LnKp,
    /// ln k_d of the actuators.
    LnKd,
}

impl Parameter {
    pub const ALL: [Parameter; 4] = [
        Parameter::LnYoungs,
        Parameter::Poisson,
        Parameter::LnKp,
        Parameter::LnKd,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Parameter::LnYoungs => "ln_E",
            Parameter::Poisson => "nu",
            Parameter::LnKp => "ln_kp",
            Parameter::LnKd => "ln_kd",
        }
    }

    /// Central-difference half step: about a third of the recovery tolerance
    /// on the material (ln 1.25 ≈ 0.22 on E, 0.05 on ν), so the secant
    /// measures the scale the tolerance asks about while staying close to
    /// linear; the gains get the same relative step as E.
    pub fn default_step(self) -> f64 {
        match self {
            Parameter::LnYoungs | Parameter::LnKp | Parameter::LnKd => 0.075,
            Parameter::Poisson => 0.02,
        }
    }

    /// Whether the actuator gains, not the material, hold this parameter.
    pub fn is_gain(self) -> bool {
        matches!(self, Parameter::LnKp | Parameter::LnKd)
    }

    /// `model` with this parameter moved by `delta` (E and ν kept inside
    /// the model's bounds, as the fit's own activations keep them).
    pub fn moved(self, model: &WorldModel, delta: f64) -> WorldModel {
        match self {
            Parameter::LnYoungs => moved_material(model, delta.exp(), 0.0),
            Parameter::Poisson => moved_material(model, 1.0, delta),
            Parameter::LnKp => {
                let mut moved = model.clone();
                moved.actuator.kp *= delta.exp();
                moved
            }
            Parameter::LnKd => {
                let mut moved = model.clone();
                moved.actuator.kd *= delta.exp();
                moved
            }
        }
    }
}

/// `dm-synth`'s track noise (its `SensorNoise`): 1.5 mm per axis and
/// frame, and a 1 mm constant bias per track and axis; the defaults of
/// `dm-fit --identifiability`.
pub const DEFAULT_TRACK_NOISE_MM: f64 = 1.5;
pub const DEFAULT_TRACK_OFFSET_MM: f64 = 1.0;

/// The track noise the bound assumes, metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrackNoise {
    /// Independent noise per axis and frame.
    pub sigma_m: f64,
    /// Constant offset per track and axis over the clip.
    pub offset_sigma_m: f64,
}

/// Sensitivities of the observed training positions: for every track, its
/// observed frames' ∂x/∂θ (one `[P][3]` block per frame).
#[derive(Clone, Debug, PartialEq)]
pub struct TrackJacobian {
    pub parameters: Vec<Parameter>,
    pub tracks: Vec<Vec<Vec<[f64; 3]>>>,
    /// Observed minus simulated position at the same frames, per track.
    pub residuals: Vec<Vec<[f64; 3]>>,
    /// Per parameter, ‖x(θ+h) + x(θ−h) − 2 x(θ)‖ / ‖x(θ+h) − x(θ−h)‖ over
    /// all observations: near 0 where the rollout is linear over ±h.
    pub curvature: Vec<f64>,
}

impl TrackJacobian {
    pub fn observation_count(&self) -> usize {
        self.tracks.iter().map(Vec::len).sum::<usize>() * 3
    }

    /// Σ over tracks and axes of the squared residuals about the track's
    /// mean (m²): the least-squares cost with every track's offset free.
    pub fn centred_cost(&self) -> f64 {
        self.residuals
            .iter()
            .filter(|r| !r.is_empty())
            .map(|r| {
                (0..3)
                    .map(|a| {
                        let mean = r.iter().map(|v| v[a]).sum::<f64>() / r.len() as f64;
                        r.iter().map(|v| (v[a] - mean).powi(2)).sum::<f64>()
                    })
                    .sum::<f64>()
            })
            .sum()
    }
}

/// Σ over tracks and axes of Σ_t j_t j_tᵀ − c(m) s sᵀ (s = Σ_t j_t, m the
/// track's observed frames) and of Σ_t j_t r_t − c(m) s Σ_t r_t: the
/// normal matrix and right-hand side of least squares whose inverse
/// covariance per track is I − c 1 1ᵀ (up to a scale).
fn offset_weighted_normal(
    jacobian: &TrackJacobian,
    c_of_frames: impl Fn(f64) -> f64,
) -> (DMatrix<f64>, DVector<f64>) {
    let p = jacobian.parameters.len();
    let mut normal = DMatrix::<f64>::zeros(p, p);
    let mut rhs = DVector::<f64>::zeros(p);
    for (frames, residuals) in jacobian.tracks.iter().zip(&jacobian.residuals) {
        if frames.is_empty() {
            continue;
        }
        let c = c_of_frames(frames.len() as f64);
        for axis in 0..3 {
            let mut sum = DVector::<f64>::zeros(p);
            let mut sum_r = 0.0;
            for (rows, r) in frames.iter().zip(residuals) {
                let j = DVector::from_fn(p, |i, _| rows[i][axis]);
                normal += &j * j.transpose();
                rhs += &j * r[axis];
                sum += j;
                sum_r += r[axis];
            }
            normal -= c * &sum * sum.transpose();
            rhs -= c * sum_r * sum;
        }
    }
    (normal, rhs)
}

/// Fisher information of the tracks about the parameters (P × P), under
/// `noise` (module docs).
pub fn fisher_information(jacobian: &TrackJacobian, noise: TrackNoise) -> DMatrix<f64> {
    let var = noise.sigma_m * noise.sigma_m;
    let offset_var = noise.offset_sigma_m * noise.offset_sigma_m;
    let (normal, _) = offset_weighted_normal(jacobian, |m| offset_var / (var + m * offset_var));
    normal / var
}

/// The bound on each parameter's standard deviation with the parameters
/// marked `estimated` unknown and the rest known; `None` for a known
/// parameter, infinity where the data cannot tell the estimated ones apart
/// (a singular block).
pub fn cramer_rao_std(fisher: &DMatrix<f64>, estimated: &[bool]) -> Vec<Option<f64>> {
    let free: Vec<usize> = (0..fisher.nrows()).filter(|&i| estimated[i]).collect();
    let block = DMatrix::from_fn(free.len(), free.len(), |a, b| fisher[(free[a], free[b])]);
    let inverse = block.clone().cholesky().map(|c| c.inverse());
    let mut out = vec![None; fisher.nrows()];
    for (a, &i) in free.iter().enumerate() {
        out[i] = Some(match &inverse {
            Some(inv) if inv[(a, a)] > 0.0 => inv[(a, a)].sqrt(),
            _ => f64::INFINITY,
        });
    }
    out
}

/// Correlation of the bound's covariance over the parameters marked
/// `estimated`; NaN rows for the others, and everywhere when that block of
/// the information is singular.
pub fn cramer_rao_correlation(fisher: &DMatrix<f64>, estimated: &[bool]) -> DMatrix<f64> {
    let p = fisher.nrows();
    let free: Vec<usize> = (0..p).filter(|&i| estimated[i]).collect();
    let block = DMatrix::from_fn(free.len(), free.len(), |a, b| fisher[(free[a], free[b])]);
    let mut out = DMatrix::from_element(p, p, f64::NAN);
    if let Some(cov) = block.cholesky().map(|c| c.inverse()) {
        for (a, &i) in free.iter().enumerate() {
            for (b, &j) in free.iter().enumerate() {
                out[(i, j)] = cov[(a, b)] / (cov[(a, a)] * cov[(b, b)]).sqrt();
            }
        }
    }
    out
}

/// Sensitivity of the observed training tracks to `parameters` at `model`:
/// one base rollout and two per parameter over the first `frames` frames.
/// Each track is followed on the particle nearest its frame-0 observation
/// (the protocol's Track matching); only frames ≥ 1 where the track is
/// visible and valid count, as in the fit's track loss.
pub fn track_jacobian(
    model: &WorldModel,
    bundle: &Bundle,
    frames: usize,
    parameters: &[(Parameter, f64)],
    on_rollout: &mut dyn FnMut(&str),
) -> Result<TrackJacobian, FitError> {
    let frames = frames.min(bundle.frame_count());
    // A diverging rollout is an error of the simulation (NaN or det F ≤ 0);
    // `on_rollout` has named the parameter it was run for.
    let rollout = |m: &WorldModel| m.rollout(bundle, frames, &mut |_| {});
    on_rollout("base");
    let base = rollout(model)?;
    let tracks = &bundle.tracks;
    // The fit's own matching (loss::TrackMatch): each tracked point on the
    // particle nearest its frame-0 observation.
    let matched = TrackMatch::new(
        &model.particles,
        &ObservedFrame::from_tracks(tracks, 0)?.points,
    )?;
    let matched = matched.particles();
    let track_count = matched.len();
    let observed =
        |t: usize, k: usize| tracks.object_visibility[[t, k]] && tracks.object_motion_valid[[t, k]];
    let residuals: Vec<Vec<[f64; 3]>> = matched
        .iter()
        .enumerate()
        .map(|(k, &i)| {
            (1..frames)
                .filter(|&t| observed(t, k))
                .map(|t| {
                    std::array::from_fn(|a| {
                        f64::from(tracks.object_points[[t, k, a]]) - f64::from(base[t][i][a])
                    })
                })
                .collect()
        })
        .collect();
    let mut columns: Vec<Vec<Vec<[f64; 3]>>> = Vec::with_capacity(parameters.len());
    let mut curvature = Vec::with_capacity(parameters.len());
    for &(parameter, step) in parameters {
        let label = format!("{} ± {step}", parameter.name());
        on_rollout(&label);
        let plus = rollout(&parameter.moved(model, step))?;
        let minus = rollout(&parameter.moved(model, -step))?;
        let (mut bend, mut slope) = (0.0f64, 0.0f64);
        let mut column = vec![Vec::new(); track_count];
        for (k, &i) in matched.iter().enumerate() {
            for t in 1..frames {
                if !observed(t, k) {
                    continue;
                }
                let d: [f64; 3] =
                    std::array::from_fn(|a| f64::from(plus[t][i][a]) - f64::from(minus[t][i][a]));
                let b: [f64; 3] = std::array::from_fn(|a| {
                    f64::from(plus[t][i][a]) + f64::from(minus[t][i][a])
                        - 2.0 * f64::from(base[t][i][a])
                });
                bend += b.iter().map(|c| c * c).sum::<f64>();
                slope += d.iter().map(|c| c * c).sum::<f64>();
                column[k].push(d.map(|c| c / (2.0 * step)));
            }
        }
        curvature.push(if slope > 0.0 {
            (bend / slope).sqrt()
        } else {
            f64::NAN
        });
        columns.push(column);
    }
    let tracks_out = (0..track_count)
        .map(|k| {
            let observed_frames = residuals[k].len();
            (0..observed_frames)
                .map(|f| columns.iter().map(|c| c[k][f]).collect())
                .collect()
        })
        .collect();
    Ok(TrackJacobian {
        parameters: parameters.iter().map(|p| p.0).collect(),
        tracks: tracks_out,
        residuals,
        curvature,
    })
}

/// A damped Gauss–Newton (Levenberg–Marquardt) step on the parameters:
/// the least-squares fit of the tracks with each track's constant offset
/// left free (the residuals and sensitivities are centred per track and
/// axis over its observed frames), solving (JᵀJ + λ diag JᵀJ) Δθ = Jᵀr.
/// Returns Δθ in the Jacobian's parameter order and the centred sum of
/// squared residuals it starts from (m²); `None` where the system is
/// singular.
pub fn gauss_newton_step(jacobian: &TrackJacobian, damping: f64) -> Option<(Vec<f64>, f64)> {
    // Free offsets: c = 1/m centres each track's sensitivities and residuals.
    let (mut normal, rhs) = offset_weighted_normal(jacobian, |m| 1.0 / m);
    for i in 0..normal.nrows() {
        normal[(i, i)] *= 1.0 + damping;
    }
    let step = normal.cholesky()?.solve(&rhs);
    Some((step.iter().copied().collect(), jacobian.centred_cost()))
}

/// The centred sum of squared track residuals at `model` (the quantity
/// [`gauss_newton_step`] lowers), from one rollout.
pub fn centred_track_cost(
    model: &WorldModel,
    bundle: &Bundle,
    frames: usize,
) -> Result<f64, FitError> {
    Ok(track_jacobian(model, bundle, frames, &[], &mut |_| {})?.centred_cost())
}

/// `model` with every parameter moved by its entry of `delta`.
pub fn moved_by(model: &WorldModel, parameters: &[Parameter], delta: &[f64]) -> WorldModel {
    parameters
        .iter()
        .zip(delta)
        .fold(model.clone(), |m, (p, &d)| p.moved(&m, d))
}

/// One parameter's row of the report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ParameterBound {
    pub name: String,
    /// Central-difference half step.
    pub step: f64,
    /// Bound on the standard deviation with every listed parameter estimated.
    pub std_all_estimated: f64,
    /// Bound with the actuator gains known (material parameters only).
    pub std_gains_known: Option<f64>,
    /// Curvature of the rollout over ±step (see [`TrackJacobian::curvature`]).
    pub curvature: f64,
}

/// The bound for a clip: what `identifiability` reports.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Identifiability {
    pub noise: TrackNoise,
    pub observations: usize,
    pub parameters: Vec<ParameterBound>,
    /// Correlations of the bound's covariance, in `parameters` order.
    pub correlation: Vec<Vec<f64>>,
}

/// Bounds and correlations from a Jacobian.
pub fn identifiability(
    jacobian: &TrackJacobian,
    steps: &[f64],
    noise: TrackNoise,
) -> Identifiability {
    let fisher = fisher_information(jacobian, noise);
    let p = jacobian.parameters.len();
    // A parameter that moves no track (the gains of rigid actuators) is not
    // part of the model's fit: leave it out rather than let it make the
    // whole information singular. Its bound reads as infinite (JSON null).
    let informative: Vec<bool> = (0..p).map(|i| fisher[(i, i)] > 0.0).collect();
    let all = cramer_rao_std(&fisher, &informative);
    let material_only: Vec<bool> = (0..p)
        .map(|i| informative[i] && !jacobian.parameters[i].is_gain())
        .collect();
    let known_gains = cramer_rao_std(&fisher, &material_only);
    let correlation = cramer_rao_correlation(&fisher, &informative);
    Identifiability {
        noise,
        observations: jacobian.observation_count(),
        parameters: (0..p)
            .map(|i| ParameterBound {
                name: jacobian.parameters[i].name().into(),
                step: steps[i],
                std_all_estimated: all[i].unwrap_or(f64::INFINITY),
                std_gains_known: if jacobian.parameters[i].is_gain() {
                    None
                } else {
                    Some(known_gains[i].unwrap_or(f64::INFINITY))
                },
                curvature: jacobian.curvature[i],
            })
            .collect(),
        correlation: (0..p)
            .map(|i| (0..p).map(|j| correlation[(i, j)]).collect())
            .collect(),
    }
}

/// The bound at `model` over every [`Parameter`] with its default step,
/// on the first `frames` frames.
pub fn identifiability_at(
    model: &WorldModel,
    bundle: &Bundle,
    frames: usize,
    noise: TrackNoise,
    on_rollout: &mut dyn FnMut(&str),
) -> Result<Identifiability, FitError> {
    let parameters: Vec<(Parameter, f64)> = Parameter::ALL
        .iter()
        .map(|&p| (p, p.default_step()))
        .collect();
    let jacobian = track_jacobian(model, bundle, frames, &parameters, on_rollout)?;
    let steps: Vec<f64> = parameters.iter().map(|p| p.1).collect();
    Ok(identifiability(&jacobian, &steps, noise))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Dense reference: Σ_k,a Jᵀ Σ⁻¹ J with Σ built and inverted explicitly.
    fn dense_fisher(jacobian: &TrackJacobian, noise: TrackNoise) -> DMatrix<f64> {
        let p = jacobian.parameters.len();
        let mut fisher = DMatrix::zeros(p, p);
        for frames in &jacobian.tracks {
            let m = frames.len();
            let sigma = DMatrix::from_fn(m, m, |i, j| {
                noise.offset_sigma_m.powi(2) + if i == j { noise.sigma_m.powi(2) } else { 0.0 }
            });
            let inverse = sigma
                .try_inverse()
                .expect("covariance is positive definite");
            for axis in 0..3 {
                let j = DMatrix::from_fn(m, p, |t, q| frames[t][q][axis]);
                fisher += j.transpose() * &inverse * j;
            }
        }
        fisher
    }

    fn jacobian(tracks: Vec<Vec<Vec<[f64; 3]>>>) -> TrackJacobian {
        TrackJacobian {
            parameters: vec![Parameter::LnYoungs, Parameter::LnKp],
            residuals: tracks.iter().map(|f| vec![[0.0; 3]; f.len()]).collect(),
            tracks,
            curvature: vec![0.0, 0.0],
        }
    }

    /// Deterministic, unequal sensitivities for tracks of different lengths.
    fn sample_tracks() -> Vec<Vec<Vec<[f64; 3]>>> {
        (0..4)
            .map(|k| {
                (0..(3 + k))
                    .map(|t| {
                        let s = (k * 7 + t) as f64;
                        vec![
                            [0.3 * s.sin(), 0.1 * t as f64, 0.02 * k as f64],
                            [0.5 * (0.7 * s).cos(), -0.05 * t as f64, 0.01],
                        ]
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn closed_form_matches_the_dense_inverse_of_noise_plus_offset() {
        let j = jacobian(sample_tracks());
        let noise = TrackNoise {
            sigma_m: 1.5e-3,
            offset_sigma_m: 1e-3,
        };
        let fast = fisher_information(&j, noise);
        let dense = dense_fisher(&j, noise);
        // Both sums are O(1e6); the Woodbury identity is exact, so only
        // rounding separates them.
        const RELATIVE_TOLERANCE: f64 = 1e-10;
        assert!(
            (&fast - &dense).norm() <= RELATIVE_TOLERANCE * dense.norm(),
            "{fast} vs {dense}"
        );
    }

    #[test]
    fn a_constant_shift_carries_no_information_when_offsets_are_free() {
        // A parameter that only shifts every track by a constant is
        // indistinguishable from the tracks' offsets once those are
        // unconstrained; with tight offsets it is measured.
        let shift: Vec<Vec<Vec<[f64; 3]>>> = (0..5)
            .map(|_| (0..10).map(|_| vec![[1.0, 0.0, 0.0]]).collect())
            .collect();
        let j = TrackJacobian {
            parameters: vec![Parameter::LnYoungs],
            residuals: vec![vec![[0.0; 3]; 10]; 5],
            tracks: shift,
            curvature: vec![0.0],
        };
        let loose = fisher_information(
            &j,
            TrackNoise {
                sigma_m: 1e-3,
                offset_sigma_m: 1e3,
            },
        );
        let tight = fisher_information(
            &j,
            TrackNoise {
                sigma_m: 1e-3,
                offset_sigma_m: 0.0,
            },
        );
        assert!(loose[(0, 0)] < 1e-3 * tight[(0, 0)], "{loose} vs {tight}");
        // No offset: 5 tracks × 10 frames of unit sensitivity over σ².
        assert!((tight[(0, 0)] - 50.0 / 1e-6).abs() < 1e-6 * tight[(0, 0)]);
    }

    #[test]
    fn a_compensating_gain_widens_the_bound() {
        // E and k_p move the tracks almost alike: estimated together their
        // bounds widen far beyond E's bound with the gain known.
        let tracks: Vec<Vec<Vec<[f64; 3]>>> = (0..6)
            .map(|k| {
                (0..8)
                    .map(|t| {
                        let s = 1e-2 * (1.0 + t as f64 + k as f64);
                        vec![[s, 0.0, 0.0], [0.98 * s, 1e-4 * t as f64, 0.0]]
                    })
                    .collect()
            })
            .collect();
        let j = jacobian(tracks);
        let noise = TrackNoise {
            sigma_m: 1.5e-3,
            offset_sigma_m: 0.0,
        };
        let fisher = fisher_information(&j, noise);
        let both = cramer_rao_std(&fisher, &[true, true]);
        let known = cramer_rao_std(&fisher, &[true, false]);
        let e_both = both[0].expect("estimated");
        let e_known = known[0].expect("estimated");
        assert!(known[1].is_none());
        assert!(e_both > 10.0 * e_known, "{e_both} vs {e_known}");
        // The known-gain bound is 1/√F_EE exactly.
        assert!((e_known - fisher[(0, 0)].sqrt().recip()).abs() < 1e-12 * e_known);
        let corr = cramer_rao_correlation(&fisher, &[true, true]);
        assert!(corr[(0, 1)] < -0.9, "E and k_p compensate: {corr}");
    }

    #[test]
    fn gauss_newton_recovers_a_linear_model_up_to_free_offsets() {
        // Residuals made by a known Δθ through the sample sensitivities,
        // plus a constant offset per track: the undamped step is Δθ
        // exactly, whatever the offsets.
        let tracks = sample_tracks();
        let truth = [0.3, -0.7];
        let residuals: Vec<Vec<[f64; 3]>> = tracks
            .iter()
            .enumerate()
            .map(|(k, frames)| {
                frames
                    .iter()
                    .map(|rows| {
                        std::array::from_fn(|a| {
                            truth[0] * rows[0][a] + truth[1] * rows[1][a] + 0.01 * (k + a) as f64
                        })
                    })
                    .collect()
            })
            .collect();
        let mut j = jacobian(tracks);
        j.residuals = residuals;
        let (step, cost) = gauss_newton_step(&j, 0.0).expect("regular system");
        // A direct solve of a well-conditioned 2×2 system: rounding only.
        const TOLERANCE: f64 = 1e-9;
        assert!((step[0] - truth[0]).abs() < TOLERANCE, "{step:?}");
        assert!((step[1] - truth[1]).abs() < TOLERANCE, "{step:?}");
        assert!(cost > 0.0);
        // Damping shortens the step.
        let (damped, _) = gauss_newton_step(&j, 1.0).expect("regular system");
        let norm = |v: &[f64]| v.iter().map(|c| c * c).sum::<f64>().sqrt();
        assert!(norm(&damped) < norm(&step));
    }

    #[test]
    fn a_parameter_that_moves_no_track_is_left_out() {
        // Rigid actuators: the gains' columns are zero. E keeps its bound.
        let tracks: Vec<Vec<Vec<[f64; 3]>>> = (0..3)
            .map(|k| {
                (0..5)
                    .map(|t| vec![[0.01 * (1 + t + k) as f64, 0.0, 0.0], [0.0; 3]])
                    .collect()
            })
            .collect();
        let j = jacobian(tracks);
        let noise = TrackNoise {
            sigma_m: 1e-3,
            offset_sigma_m: 0.0,
        };
        let bound = identifiability(&j, &[0.075, 0.075], noise);
        let e = &bound.parameters[0];
        assert!(
            e.std_all_estimated.is_finite() && e.std_all_estimated > 0.0,
            "{e:?}"
        );
        assert_eq!(e.std_gains_known, Some(e.std_all_estimated));
        assert_eq!(bound.parameters[1].std_all_estimated, f64::INFINITY);
        assert_eq!(bound.parameters[1].std_gains_known, None);
        // The left-out gain does not blank the others' correlations.
        assert_eq!(bound.correlation[0][0], 1.0);
        assert!(bound.correlation[1][1].is_nan());
    }

    #[test]
    fn singular_information_reads_as_an_infinite_bound() {
        let j = TrackJacobian {
            parameters: vec![Parameter::LnYoungs, Parameter::Poisson],
            tracks: vec![vec![vec![[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]; 4]],
            residuals: vec![vec![[0.0; 3]; 4]],
            curvature: vec![0.0, 0.0],
        };
        let fisher = fisher_information(
            &j,
            TrackNoise {
                sigma_m: 1e-3,
                offset_sigma_m: 0.0,
            },
        );
        let std = cramer_rao_std(&fisher, &[true, true]);
        assert_eq!(std[1], Some(f64::INFINITY));
    }
}
