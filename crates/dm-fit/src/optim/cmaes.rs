//! A compact (μ/μ_w, λ)-CMA-ES following N. Hansen, "The CMA Evolution
//! Strategy: A Tutorial" (arXiv:1604.00772), Table 1 defaults with positive
//! recombination weights only (no active CMA).
//!
//! Used to select the actuator gains (k_p, k_d) gradient-free
//! (method.md §4, §7 step 2). The gains span decades, so the fit searches
//! **log-gains**: x = (ln k_p, ln k_d) (or log10), with box bounds on the
//! logs, e.g. k_p ∈ [1, 1e5], k_d ∈ [0.1, 1e3]; one σ then means the same
//! relative change for both gains.
//!
//! # Interface
//!
//! [`Cmaes::ask`] returns one generation of λ candidates, the caller evaluates
//! them however it likes (in parallel: each is an independent rollout) and
//! hands the fitness values back **in the same order** with [`Cmaes::tell`].
//! [`minimize`] wraps the loop and evaluates a generation with rayon; results
//! do not depend on the thread count because every candidate is evaluated
//! and only then told, in index order.
//!
//! # Determinism
//!
//! Generation g draws its normal samples from `ChaCha8Rng::seed_from_u64(seed)`
//! on stream g, so the sample stream is a pure function of (seed, g) and the
//! whole state — including the pending population between `ask` and `tell` —
//! is serde serialisable for checkpoints without serialising an RNG.
//!
//! # Bounds: mirroring
//!
//! Candidates outside the box are **mirrored** (reflected) back into it,
//! periodically, so any point maps inside. Mirroring keeps the sampling
//! density smooth near a bound (clamping would pile probability mass onto the
//! faces). The update is Lamarckian: the mirrored point is both what the
//! caller evaluates and what the strategy learns from, so the mean (a convex
//! combination of in-box points) stays in the box and every `ask` result
//! respects the bounds.
//!
//! # Fitness values
//!
//! Lower is better. Non-finite values (a diverged rollout, a failed
//! simulation mapped to `f64::INFINITY`) rank worst; a generation where every
//! value is non-finite is an error.

use std::collections::VecDeque;

use nalgebra::{DMatrix, DVector, SymmetricEigen};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::OptimError;

/// Box bounds `lower[i] <= x[i] <= upper[i]`; either side may be infinite.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Bounds {
    lower: Vec<f64>,
    upper: Vec<f64>,
}

impl Bounds {
    /// Requires equal lengths, no NaN and `lower < upper` strictly (a fixed
    /// coordinate would make the covariance singular; leave it out instead).
    pub fn new(lower: Vec<f64>, upper: Vec<f64>) -> Result<Self, OptimError> {
        if lower.len() != upper.len() {
            return Err(OptimError::InvalidOption {
                option: "bounds",
                problem: format!("{} lower but {} upper bounds", lower.len(), upper.len()),
            });
        }
        for (i, (&lo, &hi)) in lower.iter().zip(&upper).enumerate() {
            if lo.is_nan() || hi.is_nan() || lo >= hi {
                return Err(OptimError::InvalidOption {
                    option: "bounds",
                    problem: format!("coordinate {i}: need lower < upper, got [{lo}, {hi}]"),
                });
            }
        }
        Ok(Self { lower, upper })
    }

    pub fn lower(&self) -> &[f64] {
        &self.lower
    }

    pub fn upper(&self) -> &[f64] {
        &self.upper
    }

    pub fn dim(&self) -> usize {
        self.lower.len()
    }

    /// Whether `x` lies inside (bounds inclusive).
    pub fn contains(&self, x: &[f64]) -> bool {
        x.len() == self.dim()
            && x.iter()
                .zip(self.lower.iter().zip(&self.upper))
                .all(|(&v, (&lo, &hi))| lo <= v && v <= hi)
    }

    /// Reflects every coordinate into its interval (periodically, so points
    /// several widths away still land inside).
    pub fn mirror(&self, x: &mut [f64]) {
        for ((v, &lo), &hi) in x.iter_mut().zip(&self.lower).zip(&self.upper) {
            *v = mirror_into(*v, lo, hi);
        }
    }
}

fn mirror_into(value: f64, lower: f64, upper: f64) -> f64 {
    match (lower.is_finite(), upper.is_finite()) {
        (true, true) => {
            let width = upper - lower;
            let mut offset = (value - lower).rem_euclid(2.0 * width);
            if offset > width {
                offset = 2.0 * width - offset;
            }
            // Rounding in rem_euclid can land a hair outside.
            (lower + offset).clamp(lower, upper)
        }
        (true, false) if value < lower => 2.0 * lower - value,
        (false, true) if value > upper => 2.0 * upper - value,
        _ => value,
    }
}

/// Run settings; `CmaesOptions::default()` gives the tutorial defaults.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CmaesOptions {
    /// Seed of the sample stream.
    pub seed: u64,
    /// λ; default 4 + ⌊3 ln n⌋.
    pub population_size: Option<usize>,
    /// Evaluation budget; a generation that would exceed it is not started.
    /// Default (pycma's) 100 + 150 (n + 3)² √λ.
    pub max_evaluations: Option<u64>,
    pub max_generations: Option<u64>,
    /// Stop once the best fitness seen is ≤ this.
    pub target_fitness: Option<f64>,
    /// Stop when the best values of the last 10 + ⌈30 n / λ⌉ generations and
    /// all values of the latest generation span less than this.
    pub tol_fun: f64,
    /// Stop when σ · max(|p_c,i|, √C_ii) < tol_x for every coordinate.
    pub tol_x: f64,
    /// Stop when the condition number of C exceeds this.
    pub max_condition: f64,
    /// Generations between eigendecompositions of C; default
    /// max(1, ⌊1 / (10 n (c_1 + c_μ))⌋) (tutorial's lazy update).
    pub eigen_interval: Option<u64>,
}

impl Default for CmaesOptions {
    fn default() -> Self {
        Self {
            seed: 0,
            population_size: None,
            max_evaluations: None,
            max_generations: None,
            target_fitness: None,
            tol_fun: 1e-12,
            tol_x: 1e-12,
            max_condition: 1e14,
            eigen_interval: None,
        }
    }
}

/// Why a run stopped (or should stop).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum StopReason {
    TargetFitness,
    TolFun,
    TolX,
    ConditionCov,
    MaxEvaluations,
    MaxGenerations,
}

/// Outcome of a run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CmaesResult {
    /// Best point evaluated (inside the bounds).
    pub best_x: Vec<f64>,
    pub best_fitness: f64,
    /// Final distribution mean (often better than `best_x` on noisy fitness).
    pub mean: Vec<f64>,
    pub sigma: f64,
    pub evaluations: u64,
    pub generations: u64,
    pub stop_reason: StopReason,
}

/// Strategy constants derived from n and λ (tutorial Table 1).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct Strategy {
    lambda: usize,
    mu: usize,
    weights: Vec<f64>,
    mu_eff: f64,
    c_sigma: f64,
    d_sigma: f64,
    c_c: f64,
    c_1: f64,
    c_mu: f64,
    /// E‖N(0, I)‖.
    chi_n: f64,
    eigen_interval: u64,
    /// Length of the best-fitness history used by TolFun.
    history_len: usize,
    max_evaluations: u64,
}

impl Strategy {
    fn new(n: usize, options: &CmaesOptions) -> Result<Self, OptimError> {
        let nf = n as f64;
        let lambda = options
            .population_size
            .unwrap_or(4 + (3.0 * nf.ln()).floor() as usize);
        if lambda < 2 {
            return Err(OptimError::InvalidOption {
                option: "population_size",
                problem: format!("need at least 2, got {lambda}"),
            });
        }
        let mu = lambda / 2;
        let raw: Vec<f64> = (1..=mu)
            .map(|i| ((lambda as f64 + 1.0) / 2.0).ln() - (i as f64).ln())
            .collect();
        let raw_sum: f64 = raw.iter().sum();
        let weights: Vec<f64> = raw.iter().map(|w| w / raw_sum).collect();
        let mu_eff = 1.0 / weights.iter().map(|w| w * w).sum::<f64>();

        let c_sigma = (mu_eff + 2.0) / (nf + mu_eff + 5.0);
        let d_sigma = 1.0 + 2.0 * (((mu_eff - 1.0) / (nf + 1.0)).sqrt() - 1.0).max(0.0) + c_sigma;
        let c_c = (4.0 + mu_eff / nf) / (nf + 4.0 + 2.0 * mu_eff / nf);
        let c_1 = 2.0 / ((nf + 1.3).powi(2) + mu_eff);
        let c_mu =
            (1.0 - c_1).min(2.0 * (mu_eff - 2.0 + 1.0 / mu_eff) / ((nf + 2.0).powi(2) + mu_eff));
        let chi_n = nf.sqrt() * (1.0 - 1.0 / (4.0 * nf) + 1.0 / (21.0 * nf * nf));
        let eigen_interval = options
            .eigen_interval
            .unwrap_or_else(|| ((1.0 / (10.0 * nf * (c_1 + c_mu))).floor() as u64).max(1));
        if eigen_interval == 0 {
            return Err(OptimError::InvalidOption {
                option: "eigen_interval",
                problem: "must be at least 1".into(),
            });
        }
        let history_len = 10 + (30.0 * nf / lambda as f64).ceil() as usize;
        let max_evaluations = options.max_evaluations.unwrap_or_else(|| {
            (100.0 + 150.0 * (nf + 3.0).powi(2) * (lambda as f64).sqrt()) as u64
        });
        if max_evaluations < lambda as u64 {
            return Err(OptimError::InvalidOption {
                option: "max_evaluations",
                problem: format!("{max_evaluations} is less than one generation (λ = {lambda})"),
            });
        }
        Ok(Self {
            lambda,
            mu,
            weights,
            mu_eff,
            c_sigma,
            d_sigma,
            c_c,
            c_1,
            c_mu,
            chi_n,
            eigen_interval,
            history_len,
            max_evaluations,
        })
    }
}

/// CMA-ES state (serialisable, including a pending population).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Cmaes {
    options: CmaesOptions,
    strategy: Strategy,
    bounds: Option<Bounds>,
    mean: DVector<f64>,
    sigma: f64,
    /// Covariance C.
    cov: DMatrix<f64>,
    /// Eigenvectors of C (columns), B in C = B D² Bᵀ.
    basis: DMatrix<f64>,
    /// Square roots of the eigenvalues of C, D.
    scales: DVector<f64>,
    path_sigma: DVector<f64>,
    path_c: DVector<f64>,
    generation: u64,
    evaluations: u64,
    /// Generation at which `basis`/`scales` were last computed.
    eigen_generation: u64,
    /// Candidates handed out by `ask`, awaiting `tell`.
    pending: Option<Vec<Vec<f64>>>,
    best_x: Option<Vec<f64>>,
    best_fitness: f64,
    /// Best fitness of each recent generation (TolFun).
    best_history: VecDeque<f64>,
    /// Spread (max − min) of the latest generation's fitness values.
    last_generation_range: f64,
}

impl Cmaes {
    /// Starts from mean `x0` with step size `sigma0` and C = I. With bounds,
    /// `x0` must lie inside them; choose σ0 about a quarter to a third of the
    /// box width so that the initial samples cover it without mostly being
    /// mirrored.
    pub fn new(
        x0: &[f64],
        sigma0: f64,
        bounds: Option<Bounds>,
        options: CmaesOptions,
    ) -> Result<Self, OptimError> {
        let n = x0.len();
        if n == 0 {
            return Err(OptimError::InvalidOption {
                option: "x0",
                problem: "needs at least one coordinate".into(),
            });
        }
        if let Some(i) = x0.iter().position(|v| !v.is_finite()) {
            return Err(OptimError::InvalidOption {
                option: "x0",
                problem: format!("coordinate {i} is {}", x0[i]),
            });
        }
        if !(sigma0.is_finite() && sigma0 > 0.0) {
            return Err(OptimError::InvalidOption {
                option: "sigma0",
                problem: format!("must be finite and positive, got {sigma0}"),
            });
        }
        if let Some(bounds) = &bounds {
            if bounds.dim() != n {
                return Err(OptimError::InvalidOption {
                    option: "bounds",
                    problem: format!("{} bounds for {n} coordinates", bounds.dim()),
                });
            }
            for (index, &value) in x0.iter().enumerate() {
                let (lower, upper) = (bounds.lower[index], bounds.upper[index]);
                if !(lower <= value && value <= upper) {
                    return Err(OptimError::StartOutsideBounds {
                        index,
                        value,
                        lower,
                        upper,
                    });
                }
            }
        }
        for (option, value) in [
            ("tol_fun", options.tol_fun),
            ("tol_x", options.tol_x),
            ("max_condition", options.max_condition),
        ] {
            if value.is_nan() || value < 0.0 {
                return Err(OptimError::InvalidOption {
                    option,
                    problem: format!("must be non-negative, got {value}"),
                });
            }
        }
        if options.max_generations == Some(0) {
            return Err(OptimError::InvalidOption {
                option: "max_generations",
                problem: "must be at least 1".into(),
            });
        }
        let strategy = Strategy::new(n, &options)?;
        Ok(Self {
            options,
            strategy,
            bounds,
            mean: DVector::from_column_slice(x0),
            sigma: sigma0,
            cov: DMatrix::identity(n, n),
            basis: DMatrix::identity(n, n),
            scales: DVector::from_element(n, 1.0),
            path_sigma: DVector::zeros(n),
            path_c: DVector::zeros(n),
            generation: 0,
            evaluations: 0,
            eigen_generation: 0,
            pending: None,
            best_x: None,
            best_fitness: f64::INFINITY,
            best_history: VecDeque::new(),
            last_generation_range: f64::INFINITY,
        })
    }

    pub fn dim(&self) -> usize {
        self.mean.len()
    }

    /// λ.
    pub fn population_size(&self) -> usize {
        self.strategy.lambda
    }

    pub fn mean(&self) -> &[f64] {
        self.mean.as_slice()
    }

    pub fn sigma(&self) -> f64 {
        self.sigma
    }

    /// Completed generations (calls of `tell`).
    pub fn generation(&self) -> u64 {
        self.generation
    }

    pub fn evaluations(&self) -> u64 {
        self.evaluations
    }

    /// Best point and fitness told so far.
    pub fn best(&self) -> Option<(&[f64], f64)> {
        self.best_x.as_deref().map(|x| (x, self.best_fitness))
    }

    /// The next generation's λ candidates (inside the bounds). Calling it
    /// again before `tell` returns the same candidates, so a run restored
    /// from a checkpoint taken between `ask` and `tell` re-evaluates them.
    pub fn ask(&mut self) -> Vec<Vec<f64>> {
        if let Some(pending) = &self.pending {
            return pending.clone();
        }
        let n = self.dim();
        let mut rng = ChaCha8Rng::seed_from_u64(self.options.seed);
        rng.set_stream(self.generation);
        let population: Vec<Vec<f64>> = (0..self.strategy.lambda)
            .map(|_| {
                let z = DVector::from_fn(n, |_, _| rng.sample::<f64, _>(StandardNormal));
                // x = m + σ B D z, i.e. x ~ N(m, σ² C).
                let y = &self.basis * z.component_mul(&self.scales);
                let mut x: Vec<f64> = (&self.mean + self.sigma * y).as_slice().to_vec();
                if let Some(bounds) = &self.bounds {
                    bounds.mirror(&mut x);
                }
                x
            })
            .collect();
        self.pending = Some(population.clone());
        population
    }

    /// Updates the distribution from the fitness of the candidates of the
    /// last `ask`, in the same order. On error the state is unchanged.
    pub fn tell(&mut self, fitness: &[f64]) -> Result<(), OptimError> {
        let population = self.pending.as_ref().ok_or(OptimError::TellWithoutAsk)?;
        let lambda = self.strategy.lambda;
        if fitness.len() != lambda {
            return Err(OptimError::FitnessCountMismatch {
                expected: lambda,
                got: fitness.len(),
            });
        }
        if fitness.iter().all(|f| !f.is_finite()) {
            return Err(OptimError::AllFitnessNonFinite {
                generation: self.generation,
            });
        }
        // Non-finite ranks worst; ties keep index order (stable sort).
        let rank_value = |f: f64| if f.is_finite() { f } else { f64::INFINITY };
        let mut order: Vec<usize> = (0..lambda).collect();
        order.sort_by(|&a, &b| rank_value(fitness[a]).total_cmp(&rank_value(fitness[b])));

        let n = self.dim();
        let s = &self.strategy;
        // Selected steps y_i = (x_i:λ − m) / σ, best first.
        let steps: Vec<DVector<f64>> = order[..s.mu]
            .iter()
            .map(|&i| (DVector::from_column_slice(&population[i]) - &self.mean) / self.sigma)
            .collect();
        let mut weighted_step = DVector::zeros(n);
        for (w, y) in s.weights.iter().zip(&steps) {
            weighted_step += *w * y;
        }

        // All fallible work is done on copies; commit at the end.
        let mean = &self.mean + self.sigma * &weighted_step;

        // C^{-1/2} y_w = B D⁻¹ Bᵀ y_w.
        let whitened =
            &self.basis * (self.basis.transpose() * &weighted_step).component_div(&self.scales);
        let path_sigma = (1.0 - s.c_sigma) * &self.path_sigma
            + (s.c_sigma * (2.0 - s.c_sigma) * s.mu_eff).sqrt() * whitened;

        let generation = self.generation + 1;
        let norm_ps = path_sigma.norm();
        // h_σ stalls the p_c update while ‖p_σ‖ is large (σ increasing fast).
        let h_sigma = norm_ps / (1.0 - (1.0 - s.c_sigma).powf(2.0 * generation as f64)).sqrt()
            < (1.4 + 2.0 / (n as f64 + 1.0)) * s.chi_n;
        let h = if h_sigma { 1.0 } else { 0.0 };
        let path_c = (1.0 - s.c_c) * &self.path_c
            + h * (s.c_c * (2.0 - s.c_c) * s.mu_eff).sqrt() * &weighted_step;

        // Rank-one + rank-μ update; δ(h_σ) compensates the stalled p_c.
        let delta_h = (1.0 - h) * s.c_c * (2.0 - s.c_c);
        let mut cov = (1.0 + s.c_1 * delta_h - s.c_1 - s.c_mu) * &self.cov
            + s.c_1 * &path_c * path_c.transpose();
        for (w, y) in s.weights.iter().zip(&steps) {
            cov += (s.c_mu * w) * y * y.transpose();
        }

        let sigma = self.sigma * ((s.c_sigma / s.d_sigma) * (norm_ps / s.chi_n - 1.0)).exp();
        if !(sigma.is_finite() && sigma > 0.0) {
            return Err(OptimError::NumericalBreakdown {
                detail: format!("step size became {sigma} in generation {generation}"),
            });
        }

        let (basis, scales, eigen_generation) =
            if generation - self.eigen_generation >= s.eigen_interval {
                let (basis, scales) = decompose(&mut cov, generation)?;
                (basis, scales, generation)
            } else {
                (
                    self.basis.clone(),
                    self.scales.clone(),
                    self.eigen_generation,
                )
            };

        // Commit.
        let best_index = order[0];
        let generation_best = rank_value(fitness[best_index]);
        if generation_best < self.best_fitness || self.best_x.is_none() {
            self.best_fitness = generation_best;
            self.best_x = Some(population[best_index].clone());
        }
        self.last_generation_range = rank_value(fitness[order[lambda - 1]]) - generation_best;
        self.best_history.push_back(generation_best);
        if self.best_history.len() > s.history_len {
            self.best_history.pop_front();
        }
        self.mean = mean;
        self.path_sigma = path_sigma;
        self.path_c = path_c;
        self.cov = cov;
        self.sigma = sigma;
        self.basis = basis;
        self.scales = scales;
        self.eigen_generation = eigen_generation;
        self.generation = generation;
        self.evaluations += lambda as u64;
        self.pending = None;
        Ok(())
    }

    /// The first termination criterion met, if any (checked in the order of
    /// [`StopReason`]'s variants).
    pub fn should_stop(&self) -> Option<StopReason> {
        let s = &self.strategy;
        if let Some(target) = self.options.target_fitness
            && self.best_x.is_some()
            && self.best_fitness <= target
        {
            return Some(StopReason::TargetFitness);
        }
        if self.best_history.len() >= s.history_len {
            let (lo, hi) = self
                .best_history
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &f| {
                    (lo.min(f), hi.max(f))
                });
            if hi - lo < self.options.tol_fun && self.last_generation_range < self.options.tol_fun {
                return Some(StopReason::TolFun);
            }
        }
        if self.generation > 0
            && (0..self.dim()).all(|i| {
                self.sigma * self.path_c[i].abs().max(self.cov[(i, i)].sqrt()) < self.options.tol_x
            })
        {
            return Some(StopReason::TolX);
        }
        let (min_scale, max_scale) = self
            .scales
            .iter()
            .fold((f64::INFINITY, 0.0_f64), |(lo, hi), &d| {
                (lo.min(d), hi.max(d))
            });
        if (max_scale / min_scale).powi(2) > self.options.max_condition {
            return Some(StopReason::ConditionCov);
        }
        if self.evaluations + s.lambda as u64 > s.max_evaluations {
            return Some(StopReason::MaxEvaluations);
        }
        if let Some(max_generations) = self.options.max_generations
            && self.generation >= max_generations
        {
            return Some(StopReason::MaxGenerations);
        }
        None
    }

    /// Summary of the run so far, `None` before the first `tell`.
    pub fn result(&self, stop_reason: StopReason) -> Option<CmaesResult> {
        let best_x = self.best_x.clone()?;
        Some(CmaesResult {
            best_x,
            best_fitness: self.best_fitness,
            mean: self.mean.as_slice().to_vec(),
            sigma: self.sigma,
            evaluations: self.evaluations,
            generations: self.generation,
            stop_reason,
        })
    }
}

/// Symmetrises `cov` in place and returns (B, D) with C = B diag(D²) Bᵀ.
fn decompose(
    cov: &mut DMatrix<f64>,
    generation: u64,
) -> Result<(DMatrix<f64>, DVector<f64>), OptimError> {
    // Rounding makes the updated C slightly asymmetric.
    let symmetric = (&*cov + cov.transpose()) * 0.5;
    *cov = symmetric;
    if cov.iter().any(|v| !v.is_finite()) {
        return Err(OptimError::NumericalBreakdown {
            detail: format!("covariance has non-finite entries in generation {generation}"),
        });
    }
    let eigen = SymmetricEigen::new(cov.clone());
    let largest = eigen.eigenvalues.max();
    if largest.is_nan() || largest <= 0.0 {
        return Err(OptimError::NumericalBreakdown {
            detail: format!("covariance lost positive definiteness in generation {generation}"),
        });
    }
    // Round-off can push tiny eigenvalues to ≤ 0; floor them so D⁻¹ exists
    // (ConditionCov stops the run long before this matters).
    let floor = largest * 1e-20;
    let scales = eigen.eigenvalues.map(|value| value.max(floor).sqrt());
    Ok((eigen.eigenvectors, scales))
}

/// Minimises `objective` from `x0` with step size `sigma0`, evaluating each
/// generation in parallel with rayon (the result does not depend on the
/// number of threads). Runs at least one generation, then until a
/// [`StopReason`] holds.
pub fn minimize<F>(
    objective: F,
    x0: &[f64],
    sigma0: f64,
    bounds: Option<Bounds>,
    options: CmaesOptions,
) -> Result<CmaesResult, OptimError>
where
    F: Fn(&[f64]) -> f64 + Sync,
{
    let mut es = Cmaes::new(x0, sigma0, bounds, options)?;
    loop {
        let population = es.ask();
        // `collect` keeps index order whatever the scheduling.
        let fitness: Vec<f64> = population.par_iter().map(|x| objective(x)).collect();
        es.tell(&fitness)?;
        if let Some(reason) = es.should_stop() {
            return es
                .result(reason)
                .ok_or_else(|| OptimError::NumericalBreakdown {
                    detail: "no candidate was evaluated".into(),
                });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_constants_match_the_tutorial_for_n_10() {
        let s = Strategy::new(10, &CmaesOptions::default()).expect("strategy");
        assert_eq!((s.lambda, s.mu), (10, 5));
        assert!((s.weights.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        assert!(s.weights.windows(2).all(|w| w[0] > w[1]));
        assert!((s.mu_eff - 3.1672).abs() < 1e-3, "{}", s.mu_eff);
        assert!(s.c_1 > 0.0 && s.c_mu > 0.0 && s.c_1 + s.c_mu <= 1.0);
        assert!((s.chi_n - 3.0847).abs() < 1e-3, "{}", s.chi_n);
    }

    #[test]
    fn mirroring_reflects_into_the_box() {
        assert_eq!(mirror_into(1.5, 0.0, 1.0), 0.5);
        assert_eq!(mirror_into(-0.25, 0.0, 1.0), 0.25);
        assert_eq!(mirror_into(2.25, 0.0, 1.0), 0.25);
        assert_eq!(mirror_into(0.5, 0.0, 1.0), 0.5);
        assert_eq!(mirror_into(-3.0, 0.0, f64::INFINITY), 3.0);
        assert_eq!(mirror_into(5.0, f64::NEG_INFINITY, 1.0), -3.0);
        assert_eq!(mirror_into(-7.0, f64::NEG_INFINITY, f64::INFINITY), -7.0);
    }

    #[test]
    fn tell_checks_its_input_and_leaves_state_on_error() {
        let mut es = Cmaes::new(&[0.0, 0.0], 1.0, None, CmaesOptions::default()).expect("new");
        assert_eq!(es.tell(&[0.0; 6]), Err(OptimError::TellWithoutAsk));
        let population = es.ask();
        assert_eq!(es.ask(), population, "ask before tell repeats");
        let snapshot = es.clone();
        assert!(matches!(
            es.tell(&[0.0; 3]),
            Err(OptimError::FitnessCountMismatch {
                expected: 6,
                got: 3
            })
        ));
        assert!(matches!(
            es.tell(&[f64::NAN; 6]),
            Err(OptimError::AllFitnessNonFinite { generation: 0 })
        ));
        assert_eq!(es, snapshot);
        // Partly non-finite is fine: those candidates rank last.
        let mut fitness = vec![1.0; 6];
        fitness[0] = f64::NAN;
        es.tell(&fitness).expect("tell");
        assert_eq!(es.evaluations(), 6);
        assert_eq!(es.best().map(|(_, f)| f), Some(1.0));
    }

    #[test]
    fn invalid_setups_are_refused() {
        let bounds = Bounds::new(vec![0.0], vec![1.0]).expect("bounds");
        assert!(matches!(
            Cmaes::new(&[2.0], 0.1, Some(bounds), CmaesOptions::default()),
            Err(OptimError::StartOutsideBounds { index: 0, .. })
        ));
        assert!(Cmaes::new(&[], 0.1, None, CmaesOptions::default()).is_err());
        assert!(Cmaes::new(&[0.0], 0.0, None, CmaesOptions::default()).is_err());
        assert!(Bounds::new(vec![1.0], vec![1.0]).is_err());
        assert!(Bounds::new(vec![f64::NAN], vec![1.0]).is_err());
        let tiny_budget = CmaesOptions {
            max_evaluations: Some(2),
            ..CmaesOptions::default()
        };
        assert!(Cmaes::new(&[0.0, 0.0], 1.0, None, tiny_budget).is_err());
    }
}
