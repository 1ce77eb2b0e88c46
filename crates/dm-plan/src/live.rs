//! A plan from a simulation's current state, for a caller's own control
//! loop (model-predictive control): the hands hold what they hold (the
//! simulation's couplings carried into the planning world), and the
//! search finds where they go over the next frames. The caller steps its
//! simulation (or its robot) along the returned anchors and plans again.

use std::time::Instant;

use dm_model::WorldModel;
use dm_mpm::actuators::Grip;
use dm_mpm::state::Particles;
use dm_play::PlayOptions;
use dm_play::session::MaterialControl;
use serde::Serialize;

use crate::actions::ActionPlan;
use crate::cost::Scores;
use crate::goal::Goal;
use crate::options::SearchOptions;
use crate::run::{History, PlanningWorldRecord, Progress, aimed_at_goal, workspace};
use crate::search::{Search, goal_cost};
use crate::world::{PlanningModel, rollout};
use crate::{PlanError, invalid};

/// Where a plan starts: a simulation of the model as it is now.
#[derive(Clone, Copy, Debug)]
pub struct LiveStart<'a> {
    /// Every model particle's state, in the model's order.
    pub state: &'a Particles<f32>,
    /// Hand anchors now.
    pub hands: &'a [[f64; 3]],
    /// What the hands hold, one entry per model particle
    /// (`dm_mpm::World::grip`); anchors it marks grasped take hold of
    /// nothing more, the others grasp at the plan's first frame.
    pub grip: &'a Grip,
    /// The simulation's material (scale on the fitted E, ν, damping).
    pub material: &'a MaterialControl,
    /// Anchors moved together as rigid hands: ranges `[start, end)` of
    /// `hands`, in order and covering every anchor (a gripper's fingers,
    /// a bundle's `hands`); none: every anchor moves on its own.
    pub rigid_hands: Option<&'a [[usize; 2]]>,
}

/// The record of a plan from a live state (keys documented in docs/python.md).
#[derive(Clone, Debug, Serialize)]
pub struct LiveRecord {
    pub options: SearchOptions,
    pub goal: LiveGoalRecord,
    /// The object as it is now, scored against the goal.
    pub start: Scores,
    /// The plan's last frame in the planning world.
    pub planned: Scores,
    pub rollouts: usize,
    pub seconds: f64,
    pub history: History,
    pub planning_world: PlanningWorldRecord,
    pub actions: ActionPlan,
}

#[derive(Clone, Debug, Serialize)]
pub struct LiveGoalRecord {
    pub points: usize,
    pub correspondences: bool,
}

/// What [`plan_from_state`] returns.
#[derive(Debug)]
pub struct LivePlan {
    pub record: LiveRecord,
    /// Hand anchors of every frame, frame 0 (now) first: `horizon + 1` rows.
    pub hands: Vec<Vec<[f64; 3]>>,
    /// Planning-world positions of every frame, frame 0 (now) first.
    pub planned: Vec<Vec<[f64; 3]>>,
    /// The model particle each planning-world particle stands for.
    pub planned_particles: Vec<usize>,
    /// Seconds per frame.
    pub frame_dt: f64,
}

/// The up vector and the floor's height along it (none: unbounded below).
fn up_and_floor(model: &WorldModel) -> ([f64; 3], f64) {
    match &model.physics.floor {
        Some(floor) => (floor.up, floor.height),
        None => {
            let g = model.physics.gravity;
            let norm = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt().max(1e-12);
            let up = g.map(|c| -c / norm);
            // The workspace caps the up axis at `floor` on its floor side.
            let below = if up.iter().sum::<f64>() < 0.0 {
                f64::INFINITY
            } else {
                f64::NEG_INFINITY
            };
            (up, below)
        }
    }
}

fn check_start(model: &WorldModel, start: &LiveStart<'_>, goal: &Goal) -> Result<(), PlanError> {
    let n = model.particles.len();
    if start.state.len() != n {
        return Err(invalid(
            "state",
            format!("{} particles given; the model has {n}", start.state.len()),
        ));
    }
    if start.grip.couplings.len() != n {
        return Err(invalid(
            "grip",
            format!(
                "{} particles' couplings given; the model has {n}",
                start.grip.couplings.len()
            ),
        ));
    }
    if start.hands.is_empty() {
        return Err(invalid("hands", "the simulation has no hands to plan for"));
    }
    if goal.points.is_empty() || goal.points.iter().flatten().any(|c| !c.is_finite()) {
        return Err(invalid("goal", "needs at least one point, all finite"));
    }
    if let Some(ids) = &goal.particles {
        if ids.len() != goal.points.len() {
            return Err(invalid(
                "particles",
                format!(
                    "{} particles for {} goal points",
                    ids.len(),
                    goal.points.len()
                ),
            ));
        }
        if let Some(bad) = ids.iter().find(|&&i| i >= n) {
            return Err(invalid(
                "particles",
                format!("particle {bad} does not exist; the model has {n}"),
            ));
        }
    }
    Ok(())
}

/// Searches where `start`'s hands should move over the next
/// `options.horizon` frames to bring the object to `goal` (its
/// correspondences, when given, are model particles), in the planning
/// world of `options` started from `start`'s state.
pub fn plan_from_state(
    model: &WorldModel,
    start: &LiveStart<'_>,
    goal: &Goal,
    options: &SearchOptions,
    progress: Progress<'_>,
) -> Result<LivePlan, PlanError> {
    options.validate()?;
    check_start(model, start, goal)?;
    let clock = Instant::now();
    let now: Vec<[f64; 3]> = start
        .state
        .x
        .iter()
        .map(|p| [0, 1, 2].map(|a| f64::from(p[a])))
        .collect();
    let play = if options.exact {
        PlayOptions::default()
    } else {
        PlayOptions::interactive()
    };
    let mut planning = PlanningModel::new(model, &play)?
        .with_material(start.material)
        .with_domain_containing(&[now.as_slice(), start.hands].concat())
        .on_device(options.device);
    if options.residual {
        planning = planning.with_residual(model, dm_residual::Precision::F32)?;
    }
    // The planning world's particles take the state and the couplings of
    // the model particles they stand for (their own mass and volume kept).
    let planned_particles = planning.model_index().to_vec();
    let planning = planning.with_grip(start.grip.subset(&planned_particles));
    let mut world = planning.world::<f32>()?;
    let mut state = world.state()?;
    for (p, &i) in planned_particles.iter().enumerate() {
        state.x[p] = start.state.x[i];
        state.v[p] = start.state.v[i];
        state.f[p] = start.state.f[i];
        state.c[p] = start.state.c[i];
    }
    let positions: Vec<[f64; 3]> = planned_particles.iter().map(|&i| now[i]).collect();
    let correspondences: Option<Vec<usize>> = goal.particles.as_ref().map(|ids| {
        let rest: Vec<[f64; 3]> = ids.iter().map(|&i| model.particles[i]).collect();
        planning.nearest_particles(&rest)
    });
    let (up, floor) = up_and_floor(model);
    let (lo, hi) = planning.interior();
    let workspace = workspace(&positions, options.workspace_margin_m, up, floor).within(lo, hi);
    let (weights, cost) = goal_cost(options, &planning, goal, correspondences.clone());
    let at_rest = match start.rigid_hands {
        Some(ranges) => {
            ActionPlan::rigid_at_rest(start.hands, ranges, options.knots, options.horizon)
                .map_err(|problem| invalid("rigid_hands", problem))?
        }
        None => ActionPlan::at_rest(start.hands, options.knots, options.horizon),
    };
    // Straight at the goal, or holding still where that ends nearer (an
    // object already close to the goal, a goal the straight path misses).
    let aimed = aimed_at_goal(
        at_rest.clone(),
        goal,
        correspondences.as_deref(),
        &positions,
    );
    let mut search = Search::new(options, &planning, &cost, weights, workspace)?;
    let first = search.best_start(vec![aimed, at_rest], Some(&state))?;
    let plan = search.search(
        &first,
        Some(&state),
        options.iterations,
        options.gradient_iters,
        options.seed,
        progress,
    )?;
    world.set_state(&state)?;
    let planned = rollout(&mut world, &plan, true)?;
    let record = LiveRecord {
        options: options.clone(),
        goal: LiveGoalRecord {
            points: goal.points.len(),
            correspondences: goal.particles.is_some(),
        },
        start: cost.scores(&positions),
        planned: cost.scores(planned.last().map(Vec::as_slice).unwrap_or(&[])),
        rollouts: search.rollouts,
        seconds: clock.elapsed().as_secs_f64(),
        history: search.history.clone(),
        planning_world: PlanningWorldRecord::of(&planning, &world),
        actions: plan.clone(),
    };
    Ok(LivePlan {
        hands: (0..=plan.horizon).map(|t| plan.anchors(t)).collect(),
        record,
        planned,
        planned_particles,
        frame_dt: planning.frame_dt(),
    })
}
