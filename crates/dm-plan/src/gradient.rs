//! Gradient refinement of a plan through the simulator: the rollout is
//! recorded frame by frame (the last `window` substeps of each, as the
//! fit's truncated backpropagation), the cost's gradient at the last frame
//! is carried back through every frame by dm-mpm's adjoint, which also
//! gives each frame's hand-anchor gradients; those map onto the knots
//! through the plan's interpolation weights. With the residual network,
//! each frame's correction is differentiated too, back to the frame starts
//! its network saw. Adam on the knots.

use std::ops::ControlFlow;

use dm_model::device::DeviceReal;
use dm_mpm::Real;
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::real::Vec3;
use dm_mpm::state::Particles;
use serde::{Deserialize, Serialize};

use crate::actions::{ActionPlan, Workspace};
use crate::cost::{CostWeights, TerminalCost, plan_penalty};
use crate::world::{PlanningModel, PlanningWorld, WorldPool};
use crate::{PlanError, keep_going};

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GradientOptions {
    pub iterations: usize,
    /// Adam's step, metres.
    pub learning_rate_m: f64,
    /// Substeps of each frame differentiated exactly (the rest pass the
    /// adjoint through unchanged; their anchor gradients are taken as the
    /// window's, scaled to the frame).
    pub window: usize,
}

impl Default for GradientOptions {
    fn default() -> Self {
        Self {
            iterations: 20,
            learning_rate_m: 0.004,
            window: 8,
        }
    }
}

/// The plan's cost from `start` (the planning model's first frame when
/// `None`) and its gradient with respect to the knots, in `world`: a world
/// of `model` at its first frame (new, or kept and started again).
pub fn cost_and_gradient<T: DeviceReal>(
    world: &mut PlanningWorld<T>,
    model: &PlanningModel,
    start: Option<&Particles<T>>,
    plan: &ActionPlan,
    cost: &TerminalCost,
    weights: &CostWeights,
    window: usize,
) -> Result<(f64, Vec<f64>), PlanError> {
    if let Some(state) = start {
        world.set_state(state)?;
    }
    let path = plan.path();
    let hands = plan.anchor_count();
    let mut tapes = Vec::with_capacity(plan.horizon);
    for t in 0..plan.horizon {
        let grasp = vec![t == 0; hands];
        tapes.push(world.step_frame_taped(&path[t], &path[t + 1], &grasp, window)?);
    }
    let (terminal, position_grad) = cost.value_and_gradient(&world.positions()?);
    let (penalty, penalty_grad) = plan_penalty(plan, model.frame_dt(), weights);
    let mut carried = ParticleGrads::<T>::zeros(position_grad.len());
    for (c, g) in carried.x.iter_mut().zip(&position_grad) {
        *c = Vec3::new(T::lit(g[0]), T::lit(g[1]), T::lit(g[2]));
    }
    let steps = world.config().substeps_per_frame;
    let mut per_frame = vec![vec![[0.0; 3]; hands]; plan.horizon + 1];
    // Adjoints of frame starts the residual saw as history, added once the
    // backward pass reaches them.
    let mut from_history: Vec<Option<ParticleGrads<T>>> = vec![None; plan.horizon];
    for t in (0..plan.horizon).rev() {
        let adjoint = world.backward_frame(&tapes[t], &carried)?;
        let grads = adjoint.frame;
        let scale = steps as f64 / tapes[t].taped_substeps().max(1) as f64;
        for h in 0..hands {
            for a in 0..3 {
                per_frame[t][h][a] += scale * grads.anchors_from[h][a];
                per_frame[t + 1][h][a] += scale * grads.anchors_to[h][a];
            }
        }
        carried = grads.state;
        for (frame, (x, v)) in adjoint.history {
            let slot = from_history[frame]
                .get_or_insert_with(|| ParticleGrads::<T>::zeros(position_grad.len()));
            add_into(&mut slot.x, &x);
            add_into(&mut slot.v, &v);
        }
        if let Some(earlier) = from_history[t].take() {
            for (c, e) in carried.x.iter_mut().zip(&earlier.x) {
                *c += *e;
            }
            for (c, e) in carried.v.iter_mut().zip(&earlier.v) {
                *c += *e;
            }
        }
    }
    let mut grad = plan.knot_gradient(&per_frame);
    for (g, p) in grad.iter_mut().zip(&penalty_grad) {
        *g += p;
    }
    Ok((terminal + penalty, grad))
}

fn add_into<T: Real>(sum: &mut [Vec3<T>], add: &[[f64; 3]]) {
    for (s, a) in sum.iter_mut().zip(add) {
        *s += Vec3::new(T::lit(a[0]), T::lit(a[1]), T::lit(a[2]));
    }
}

/// What the refinement reached.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Refined {
    pub best: Vec<f64>,
    pub best_cost: f64,
    /// Cost at each iterate.
    pub history: Vec<f64>,
    /// Rollouts run (each forward and backward counts one).
    pub rollouts: usize,
}

/// Adam on the knots of `plan`, kept inside `workspace`; the best iterate
/// wins. Each iterate runs in a world of `worlds` (on the GPU, one whose
/// graphs are already captured).
pub fn refine(
    worlds: &WorldPool<'_, f32>,
    start: Option<&Particles<f32>>,
    plan: &ActionPlan,
    cost: &TerminalCost,
    weights: &CostWeights,
    workspace: &Workspace,
    options: &GradientOptions,
    progress: &mut dyn FnMut(usize, f64) -> ControlFlow<()>,
) -> Result<Refined, PlanError> {
    let (beta1, beta2, epsilon) = (0.9, 0.999, 1e-12);
    let mut params = plan.params();
    let mut m = vec![0.0; params.len()];
    let mut v = vec![0.0; params.len()];
    let mut best = (f64::INFINITY, params.clone());
    let mut history = Vec::with_capacity(options.iterations + 1);
    let model = worlds.planning();
    for iteration in 0..=options.iterations {
        let current = plan.with_params(&params);
        let outcome = worlds.with_world(|world| {
            cost_and_gradient(world, model, start, &current, cost, weights, options.window)
        });
        let (value, grad) = match outcome {
            Ok(result) => result,
            // A step into a diverging plan ends the refinement; the best
            // iterate so far stands.
            Err(e) if e.is_simulation() && iteration > 0 => break,
            Err(other) => return Err(other),
        };
        history.push(value);
        if value < best.0 {
            best = (value, params.clone());
        }
        keep_going(progress(iteration, best.0), "gradient")?;
        if iteration == options.iterations {
            break;
        }
        let step = iteration as i32 + 1;
        for i in 0..params.len() {
            m[i] = beta1 * m[i] + (1.0 - beta1) * grad[i];
            v[i] = beta2 * v[i] + (1.0 - beta2) * grad[i] * grad[i];
            let m_hat = m[i] / (1.0 - beta1.powi(step));
            let v_hat = v[i] / (1.0 - beta2.powi(step));
            params[i] -= options.learning_rate_m * m_hat / (v_hat.sqrt() + epsilon);
        }
        let mut projected = plan.with_params(&params);
        projected.project(workspace);
        params = projected.params();
    }
    Ok(Refined {
        best: best.1,
        best_cost: best.0,
        rollouts: history.len(),
        history,
    })
}
