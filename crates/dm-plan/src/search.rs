//! The search of one plan: MPPI and the gradient refinement in turn, as
//! the options ask, from the first frame or from an observed state.

use dm_model::device::Device;
use dm_mpm::state::Particles;

use crate::PlanError;
use crate::actions::{ActionPlan, Workspace};
use crate::cost::{CostWeights, TerminalCost};
use crate::goal::Goal;
use crate::gradient::{GradientOptions, refine};
use crate::mppi::{MppiOptions, mppi};
use crate::options::{Optimizer, SearchOptions};
use crate::run::{History, Progress, StageSeconds};
use crate::world::{PlanningModel, WorldPool, rollout_last};

/// Most host threads MPPI's samples get on the GPU (each holds a world
/// and waits on its stream).
const GPU_SAMPLE_THREADS: usize = 64;

/// The rollouts and cost histories of a run's searches.
pub(crate) struct Search<'a> {
    pub(crate) options: &'a SearchOptions,
    pub(crate) planning: &'a PlanningModel,
    /// The worlds the rollouts and the refinement's iterates run in.
    worlds: WorldPool<'a>,
    pub(crate) cost: &'a TerminalCost,
    pub(crate) weights: CostWeights,
    pub(crate) workspace: Workspace,
    pub(crate) rollouts: usize,
    pub(crate) history: History,
    pub(crate) seconds: StageSeconds,
}

impl<'a> Search<'a> {
    pub(crate) fn new(
        options: &'a SearchOptions,
        planning: &'a PlanningModel,
        cost: &'a TerminalCost,
        weights: CostWeights,
        workspace: Workspace,
    ) -> Result<Self, PlanError> {
        Ok(Self {
            options,
            planning,
            worlds: WorldPool::new(planning)?,
            cost,
            weights,
            workspace,
            rollouts: 0,
            history: History::default(),
            seconds: StageSeconds::default(),
        })
    }

    /// The cost of a plan rolled out from `start` (the first frame when None).
    fn evaluate(
        &self,
        plan: &ActionPlan,
        start: Option<&Particles<f32>>,
    ) -> Result<f64, PlanError> {
        let last = self.worlds.with_world(|world| {
            if let Some(state) = start {
                world.set_state(state)?;
            }
            rollout_last(world, plan, true)
        });
        match last {
            Ok(last) => {
                let (value, _) = self.cost.value_and_gradient(&last);
                let (penalty, _) =
                    crate::cost::plan_penalty(plan, self.planning.frame_dt(), &self.weights);
                Ok(value + penalty)
            }
            // A sample that diverges is a bad sample, not a failed search.
            Err(e) if e.is_simulation() => Ok(f64::INFINITY),
            Err(other) => Err(other),
        }
    }

    /// The lowest-cost plan of `candidates` (each kept inside the
    /// workspace; the first on a tie) rolled out from `start`: a search
    /// then starts from it.
    pub(crate) fn best_start(
        &mut self,
        candidates: Vec<ActionPlan>,
        start: Option<&Particles<f32>>,
    ) -> Result<ActionPlan, PlanError> {
        let mut best: Option<(f64, ActionPlan)> = None;
        for mut plan in candidates {
            plan.project(&self.workspace);
            let cost = self.evaluate(&plan, start)?;
            self.rollouts += 1;
            if best.as_ref().is_none_or(|(lowest, _)| cost < *lowest) {
                best = Some((cost, plan));
            }
        }
        best.map(|(_, plan)| plan)
            .ok_or_else(|| crate::invalid("plan", "no candidate plan to start from"))
    }

    /// Searches from `plan` with `iterations` MPPI iterations and
    /// `gradient_iters` refinement steps (as the optimiser allows).
    pub(crate) fn search(
        &mut self,
        plan: &ActionPlan,
        start: Option<&Particles<f32>>,
        iterations: usize,
        gradient_iters: usize,
        seed: u64,
        progress: Progress<'_>,
    ) -> Result<ActionPlan, PlanError> {
        let mut best = plan.clone();
        best.project(&self.workspace);
        let o = self.options;
        if o.optimizer != Optimizer::Gradient && iterations > 0 {
            let mppi_options = MppiOptions {
                samples: o.samples,
                iterations,
                noise_m: o.noise_m,
                seed,
                ..MppiOptions::default()
            };
            let template = best.clone();
            let workspace = self.workspace;
            let project = move |params: &mut Vec<f64>| {
                let mut p = template.with_params(params);
                p.project(&workspace);
                *params = p.params();
            };
            let template = best.clone();
            let clock = std::time::Instant::now();
            // A GPU rollout's thread mostly waits on its stream: a thread
            // per sample (up to GPU_SAMPLE_THREADS) keeps every sample's
            // stream busy at once, more than the host has cores.
            let wanted = o.samples.min(GPU_SAMPLE_THREADS);
            let threads = match self.planning.device() {
                Device::Cuda if wanted > rayon::current_num_threads() => Some(
                    rayon::ThreadPoolBuilder::new()
                        .num_threads(wanted)
                        .build()
                        .map_err(|e| crate::invalid("--samples", e.to_string()))?,
                ),
                _ => None,
            };
            let result = mppi(
                &|params| self.evaluate(&template.with_params(params), start),
                &best.params(),
                &project,
                &mppi_options,
                threads.as_ref(),
                &mut |i, _| progress("MPPI", i, iterations),
            )?;
            self.seconds.mppi += clock.elapsed().as_secs_f64();
            self.rollouts += result.rollouts;
            self.history.mppi.extend(&result.history);
            best = best.with_params(&result.best);
        }
        if o.optimizer != Optimizer::Mppi && gradient_iters > 0 {
            let gradient_options = GradientOptions {
                iterations: gradient_iters,
                learning_rate_m: o.learning_rate_m,
                window: o.window,
            };
            let clock = std::time::Instant::now();
            let refined = refine(
                &self.worlds,
                start,
                &best,
                self.cost,
                &self.weights,
                &self.workspace,
                &gradient_options,
                &mut |i, _| progress("gradient", i, gradient_iters),
            )?;
            self.seconds.gradient += clock.elapsed().as_secs_f64();
            self.rollouts += refined.rollouts;
            self.history.gradient.extend(&refined.history);
            best = best.with_params(&refined.best);
        }
        Ok(best)
    }
}

/// The cost a search minimises: distance to `goal` (with its
/// correspondences in planning-world particles) and the plan's penalties.
pub(crate) fn goal_cost(
    options: &SearchOptions,
    planning: &PlanningModel,
    goal: &Goal,
    correspondences: Option<Vec<usize>>,
) -> (CostWeights, TerminalCost) {
    let weights = CostWeights {
        max_speed_m_s: options.max_speed,
        ..CostWeights::default()
    };
    let cost = TerminalCost::new(
        goal.points.clone(),
        correspondences,
        planning.surface_count(),
        weights,
    );
    (weights, cost)
}

/// The rest of `plan` from frame `t`, with the hands where they are then
/// and its knots where the plan had them (as many, spread over what is left).
pub(crate) fn shifted(plan: &ActionPlan, t: usize) -> ActionPlan {
    let remaining = plan.horizon - t;
    let now = plan.hand_points(t);
    let k = plan.knot_count();
    let mut out = ActionPlan::at_rest(&now, k, remaining);
    for (hand, planned) in out.hands.iter_mut().zip(&plan.hands) {
        hand.offsets.clone_from(&planned.offsets);
    }
    for (h, hand) in out.hands.iter_mut().enumerate() {
        for (j, knot) in hand.knots.iter_mut().enumerate() {
            let frame = t as f64 + remaining as f64 * (j + 1) as f64 / k as f64;
            let weights = plan.knot_weights(frame);
            let mut p = plan.hands[h].grasp;
            for &(i, w) in &weights {
                for a in 0..3 {
                    p[a] += w * plan.hands[h].knots[i][a];
                }
            }
            *knot = std::array::from_fn(|a| p[a] - now[h][a]);
        }
    }
    out
}
