//! Model-predictive path integral (MPPI) over the knots: each iteration
//! samples perturbed plans around the current mean, rolls each out, and
//! moves the mean to their exponentially cost-weighted average. The
//! defaults are PhysTwin's planner's (20 samples, 10 iterations).

use std::ops::ControlFlow;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::{PlanError, keep_going};

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MppiOptions {
    pub samples: usize,
    pub iterations: usize,
    /// Standard deviation of the knot perturbations, metres.
    pub noise_m: f64,
    /// Temperature as a fraction of the spread of the samples' costs
    /// (cost − best over median − best): smaller is greedier.
    pub temperature: f64,
    pub seed: u64,
}

impl Default for MppiOptions {
    fn default() -> Self {
        Self {
            samples: 20,
            iterations: 10,
            noise_m: 0.02,
            temperature: 0.3,
            seed: 0,
        }
    }
}

/// What the search found.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SearchResult {
    /// The lowest-cost parameters evaluated.
    pub best: Vec<f64>,
    pub best_cost: f64,
    /// The best cost after each iteration.
    pub history: Vec<f64>,
    pub rollouts: usize,
}

/// Minimises `cost` from `start`. `project` keeps a sample feasible (e.g.
/// inside the workspace); `progress` is called with (iteration, best cost)
/// and stops the search with [`PlanError::Stopped`] when it breaks.
/// An iteration's samples are drawn in order, then costed in parallel
/// (on `threads` when given, else on the current rayon pool): the result
/// does not depend on the thread count.
pub fn mppi(
    cost: &(dyn Fn(&[f64]) -> Result<f64, PlanError> + Sync),
    start: &[f64],
    project: &dyn Fn(&mut Vec<f64>),
    options: &MppiOptions,
    threads: Option<&rayon::ThreadPool>,
    progress: &mut dyn FnMut(usize, f64) -> ControlFlow<()>,
) -> Result<SearchResult, PlanError> {
    let noise = Normal::new(0.0, options.noise_m).map_err(|e| PlanError::InvalidOption {
        option: "--mppi-noise".into(),
        problem: e.to_string(),
    })?;
    let mut rng = ChaCha8Rng::seed_from_u64(options.seed);
    let mut mean = start.to_vec();
    project(&mut mean);
    let mut best = mean.clone();
    let mut best_cost = cost(&mean)?;
    let mut rollouts = 1;
    let mut history = Vec::with_capacity(options.iterations);
    for iteration in 0..options.iterations {
        let mut samples = Vec::with_capacity(options.samples);
        for k in 0..options.samples {
            let mut sample = mean.clone();
            // The first sample is the mean itself, so the update never
            // loses it.
            if k > 0 {
                for v in &mut sample {
                    *v += noise.sample(&mut rng);
                }
            }
            project(&mut sample);
            samples.push(sample);
        }
        // All samples run to the end; a failure is reported as the first
        // failing sample's, whatever the thread count.
        let evaluate = || {
            samples
                .par_iter()
                .map(|sample| cost(sample))
                .collect::<Vec<_>>()
        };
        let costs = match threads {
            Some(pool) => pool.install(evaluate),
            None => evaluate(),
        };
        let costs = costs.into_iter().collect::<Result<Vec<f64>, PlanError>>()?;
        rollouts += samples.len();
        for (sample, &c) in samples.iter().zip(&costs) {
            if c < best_cost {
                best_cost = c;
                best = sample.clone();
            }
        }
        let lowest = costs.iter().copied().fold(f64::INFINITY, f64::min);
        if !lowest.is_finite() {
            // Every sample diverged: keep the mean, try again.
            history.push(best_cost);
            keep_going(progress(iteration + 1, best_cost), "MPPI")?;
            continue;
        }
        let mut sorted = costs.clone();
        sorted.sort_by(f64::total_cmp);
        let spread = (sorted[sorted.len() / 2] - lowest).max(1e-12);
        let weights: Vec<f64> = costs
            .iter()
            .map(|c| (-(c - lowest) / (options.temperature * spread)).exp())
            .collect();
        let total: f64 = weights.iter().sum();
        for (i, m) in mean.iter_mut().enumerate() {
            *m = samples
                .iter()
                .zip(&weights)
                .map(|(s, w)| w * s[i])
                .sum::<f64>()
                / total;
        }
        project(&mut mean);
        history.push(best_cost);
        keep_going(progress(iteration + 1, best_cost), "MPPI")?;
    }
    Ok(SearchResult {
        best,
        best_cost,
        history,
        rollouts,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mppi_finds_the_minimum_of_a_bowl_and_is_seeded() {
        let target = [0.05, -0.02, 0.03, 0.0];
        let run = |seed| {
            let cost = |x: &[f64]| -> Result<f64, PlanError> {
                Ok(x.iter().zip(&target).map(|(a, b)| (a - b).powi(2)).sum())
            };
            let options = MppiOptions {
                seed,
                iterations: 30,
                ..MppiOptions::default()
            };
            mppi(&cost, &[0.0; 4], &|_| {}, &options, None, &mut |_, _| {
                ControlFlow::Continue(())
            })
            .expect("search")
        };
        let result = run(1);
        assert!(result.best_cost < 1e-4, "best cost {}", result.best_cost);
        assert!(result.history.windows(2).all(|w| w[1] <= w[0]));
        assert_eq!(result.rollouts, 1 + 30 * 20);
        assert_eq!(run(1), result);
        assert_ne!(run(2).best, result.best);
    }

    #[test]
    fn mppi_does_not_depend_on_the_thread_count() {
        // A cost with many equal values: ties must resolve the same way
        // whichever sample finishes first.
        let cost = |x: &[f64]| -> Result<f64, PlanError> {
            Ok((x.iter().map(|v| v.abs()).sum::<f64>() * 50.0).round())
        };
        let options = MppiOptions {
            seed: 3,
            iterations: 8,
            ..MppiOptions::default()
        };
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("thread pool")
                .install(|| {
                    mppi(&cost, &[0.1; 6], &|_| {}, &options, None, &mut |_, _| {
                        ControlFlow::Continue(())
                    })
                })
                .expect("search")
        };
        let one = on(1);
        assert_eq!(on(2), one);
        assert_eq!(on(5), one);
    }
}
