//! One planning run: options (the command line and the run record), the
//! plan searched in the planning world, carried out in the plant open loop
//! or re-planned from observations, and everything written to the output
//! directory.

use std::ops::ControlFlow;
use std::path::Path;
use std::time::Instant;

use dm_bundle::Bundle;
use dm_model::metrics::match_tracks;
use dm_model::{ModelOptions, WorldModel};
use dm_mpm::state::Particles;
use dm_play::PlayOptions;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::Serialize;

use crate::actions::{ActionPlan, Workspace};
use crate::cost::{Scores, scores};
use crate::goal::Goal;
pub use crate::options::{Optimizer, PlanOptions, SearchOptions};
pub use crate::output::write_outputs;
use crate::plant::Plant;
use crate::search::{Search, goal_cost, shifted};
use crate::world::{PlanningModel, PlanningWorld, rollout};
use crate::{PlanError, invalid, keep_going};

/// `plan.json` (keys documented in docs/plan.md).
#[derive(Clone, Debug, Serialize)]
pub struct PlanRecord {
    pub options: PlanOptions,
    pub goal: GoalRecord,
    /// The plan's last frame in the planning world.
    pub planned: Scores,
    /// The last frame carried out in the plant.
    pub executed: Scores,
    pub plant: String,
    /// The untouched object's distance to the goal (nothing done).
    pub start: Scores,
    pub rollouts: usize,
    pub seconds: f64,
    /// Where `seconds` went.
    pub seconds_by_stage: StageSeconds,
    pub replans: usize,
    pub history: History,
    pub planning_world: PlanningWorldRecord,
    pub actions: ActionPlan,
}

#[derive(Clone, Debug, Serialize)]
pub struct GoalRecord {
    pub name: String,
    pub points: usize,
    pub correspondences: bool,
}

#[derive(Clone, Debug, Default, Serialize)]
pub struct History {
    pub mppi: Vec<f64>,
    pub gradient: Vec<f64>,
}

/// Seconds spent in MPPI's rollouts, in the gradient refinement, and
/// carrying the plan out (the plant's frames, the planning world's account
/// of them, the observations), re-plans included.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct StageSeconds {
    pub mppi: f64,
    pub gradient: f64,
    pub execute: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct PlanningWorldRecord {
    pub particles: usize,
    pub grid: usize,
    pub substeps_per_frame: usize,
    pub grasp_radius_m: f64,
}

impl PlanningWorldRecord {
    pub(crate) fn of(planning: &PlanningModel, world: &PlanningWorld<f32>) -> Self {
        Self {
            particles: planning.particles().len(),
            grid: world.config().grid_res,
            substeps_per_frame: world.config().substeps_per_frame,
            grasp_radius_m: planning.grasp_radius(),
        }
    }
}

/// Progress: (stage, done, total); `Break` stops the run with
/// [`PlanError::Stopped`].
pub type Progress<'a> = &'a mut dyn FnMut(&str, usize, usize) -> ControlFlow<()>;

/// The scene's up axis and floor height.
fn up_and_floor(bundle: &Bundle) -> ([f64; 3], f64) {
    (
        bundle.meta.up_axis.unit_vector(),
        bundle.meta.floor_height_m,
    )
}

/// The goal the options name, with correspondences in model particles.
fn read_goal(
    options: &PlanOptions,
    bundle: &Bundle,
    model: &WorldModel,
) -> Result<Goal, PlanError> {
    if let Some(frame) = options.goal.strip_prefix("frame:") {
        let frame = frame.parse().map_err(|_| {
            invalid(
                "--goal",
                format!("`{}`: frame:T needs a frame number", options.goal),
            )
        })?;
        let matched = match_tracks(&model.particles, &bundle.tracks);
        return Goal::from_bundle_frame(bundle, frame, &matched);
    }
    if options.goal.ends_with(".ply") {
        return Goal::from_ply(Path::new(&options.goal));
    }
    let (up, floor) = up_and_floor(bundle);
    Goal::named(
        &options.goal,
        bundle.meta.category,
        &model.particles,
        model.surface_count,
        up,
        floor,
    )
}

/// Grasp points: where the goal moves the surface most, the next hand
/// where it moves it much (half the most or more) and farthest from the
/// hands chosen; without correspondences, the bundle's first-frame hands.
fn grasp_points(
    options: &PlanOptions,
    bundle: &Bundle,
    particles: &[[f64; 3]],
    goal: &Goal,
    correspondences: Option<&[usize]>,
) -> Vec<[f64; 3]> {
    let Some(ids) = correspondences else {
        let anchors = dm_model::hand_anchors(bundle, 0);
        return bundle
            .meta
            .hands
            .iter()
            .take(options.hands)
            .map(|h| {
                let range = &anchors[h.anchor_range[0]..h.anchor_range[1]];
                let n = range.len().max(1) as f64;
                std::array::from_fn(|a| range.iter().map(|p| p[a]).sum::<f64>() / n)
            })
            .collect();
    };
    let moved: Vec<(usize, f64)> = ids
        .iter()
        .zip(&goal.points)
        .map(|(&p, g)| {
            let d = (0..3)
                .map(|a| (g[a] - particles[p][a]).powi(2))
                .sum::<f64>()
                .sqrt();
            (p, d)
        })
        .collect();
    let most = moved.iter().map(|m| m.1).fold(0.0, f64::max);
    let mut chosen: Vec<usize> = Vec::new();
    if let Some(&(first, _)) = moved.iter().max_by(|a, b| a.1.total_cmp(&b.1)) {
        chosen.push(first);
    }
    while chosen.len() < options.hands {
        let far = moved
            .iter()
            .filter(|m| m.1 >= 0.5 * most)
            .map(|m| {
                let gap = chosen
                    .iter()
                    .map(|&c| {
                        (0..3)
                            .map(|a| (particles[m.0][a] - particles[c][a]).powi(2))
                            .sum::<f64>()
                    })
                    .fold(f64::INFINITY, f64::min);
                (m.0, gap)
            })
            .max_by(|a, b| a.1.total_cmp(&b.1));
        match far {
            Some((p, gap)) if gap > 0.0 => chosen.push(p),
            _ => break,
        }
    }
    chosen.iter().map(|&p| particles[p]).collect()
}

/// The box the hands stay in: the object's box at the start grown by the
/// margin (upwards by twice it), never below the floor.
pub(crate) fn workspace(
    particles: &[[f64; 3]],
    margin: f64,
    up: [f64; 3],
    floor: f64,
) -> Workspace {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in particles {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a] - margin);
            hi[a] = hi[a].max(p[a] + margin);
        }
    }
    for a in 0..3 {
        if up[a] > 0.5 {
            lo[a] = lo[a].max(floor + 0.005);
            hi[a] += margin;
        } else if up[a] < -0.5 {
            hi[a] = hi[a].min(floor - 0.005);
            lo[a] -= margin;
        }
    }
    Workspace { lo, hi }
}

/// A first guess: each hand moves its grasp point straight towards where
/// the goal puts it, knot by knot.
pub(crate) fn initial_plan(
    grasps: &[[f64; 3]],
    goal: &Goal,
    correspondences: Option<&[usize]>,
    particles: &[[f64; 3]],
    knots: usize,
    horizon: usize,
) -> ActionPlan {
    aimed_at_goal(
        ActionPlan::at_rest(grasps, knots, horizon),
        goal,
        correspondences,
        particles,
    )
}

/// `plan` (hands at rest) with each hand's knots moving it in a straight
/// line to the goal point of the particle nearest its grasp, where the
/// goal has correspondences.
pub(crate) fn aimed_at_goal(
    mut plan: ActionPlan,
    goal: &Goal,
    correspondences: Option<&[usize]>,
    particles: &[[f64; 3]],
) -> ActionPlan {
    let knots = plan.knot_count();
    if let Some(ids) = correspondences {
        for hand in &mut plan.hands {
            // The goal point of the grasped particle (nearest to the grasp).
            let target = ids
                .iter()
                .zip(&goal.points)
                .min_by(|a, b| {
                    let d = |p: usize| {
                        (0..3)
                            .map(|c| (particles[p][c] - hand.grasp[c]).powi(2))
                            .sum::<f64>()
                    };
                    d(*a.0).total_cmp(&d(*b.0))
                })
                .map(|(_, g)| *g);
            if let Some(g) = target {
                for (j, knot) in hand.knots.iter_mut().enumerate() {
                    let s = (j + 1) as f64 / knots as f64;
                    *knot = std::array::from_fn(|a| s * (g[a] - hand.grasp[a]));
                }
            }
        }
    }
    plan
}

/// The smallest box holding `points`.
fn bounds(points: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    points.iter().fold(
        ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]),
        |(lo, hi), p| {
            (
                std::array::from_fn(|a| lo[a].min(p[a])),
                std::array::from_fn(|a| hi[a].max(p[a])),
            )
        },
    )
}

/// The planning world's state observed in the plant: the plant's
/// positions with noise and its velocities; the deformation as the
/// planning world (`tracker`) accounts for it.
fn observe(
    plant: &mut Plant,
    tracker: &mut PlanningWorld<f32>,
    observed_of: &[usize],
    noise: &Normal<f64>,
    rng: &mut ChaCha8Rng,
) -> Result<Particles<f32>, PlanError> {
    let truth = plant.state()?;
    let mut state = tracker.state()?;
    for (p, &q) in observed_of.iter().enumerate() {
        for a in 0..3 {
            state.x[p][a] = truth.x[q][a] + noise.sample(rng) as f32;
            state.v[p][a] = truth.v[q][a];
        }
    }
    Ok(state)
}

/// Brings the plant and the planning world (`tracker`) to where the clip
/// leaves the object at `--start-frame`: the clip's hands play up to it
/// (the plant's own, the recorded ones in the planning world), let go, and
/// the object settles for `--settle-frames`; returns the state observed
/// then.
#[allow(clippy::too_many_arguments)]
fn start_from_clip(
    options: &PlanOptions,
    plant: &mut Plant,
    tracker: &mut PlanningWorld<f32>,
    clip_hands: &[Vec<[f64; 3]>],
    observed_of: &[usize],
    noise: &Normal<f64>,
    rng: &mut ChaCha8Rng,
    progress: Progress<'_>,
) -> Result<Particles<f32>, PlanError> {
    let last = clip_hands.len().min(plant.clip_frames());
    if options.start_frame >= last {
        return Err(invalid(
            "--start-frame",
            format!(
                "frame {} is past the clip, which has {last} frames",
                options.start_frame
            ),
        ));
    }
    let total = options.start_frame + options.settle_frames;
    for t in 0..options.start_frame {
        plant.replay(t)?;
        let grasp = vec![true; clip_hands[t].len()];
        tracker.step_frame(&clip_hands[t], &clip_hands[t + 1], &grasp)?;
        keep_going(progress("start", t + 1, total), "start")?;
    }
    plant.release()?;
    tracker.release_grasps()?;
    for s in 0..options.settle_frames {
        plant.step_free()?;
        tracker.step_frame_free()?;
        keep_going(
            progress("start", options.start_frame + s + 1, total),
            "start",
        )?;
    }
    observe(plant, tracker, observed_of, noise, rng)
}

/// What `run` returns besides the files.
#[derive(Debug)]
pub struct RunResult {
    pub record: PlanRecord,
    pub planned: Vec<Vec<[f64; 3]>>,
    pub executed: Vec<Vec<[f64; 3]>>,
    /// Anchors carried out per frame (the plant's hands).
    pub hands: Vec<Vec<[f64; 3]>>,
    pub goal: Goal,
    /// Radius the model's particles are drawn with.
    pub splat_radius: f32,
    /// Seconds per frame.
    pub frame_dt: f64,
    /// The scene's bundle (cameras and floor of the video).
    pub bundle: Bundle,
}

/// Plans, carries the plan out and returns everything (`write_outputs`
/// writes it).
pub fn plan(options: &PlanOptions, progress: Progress<'_>) -> Result<RunResult, PlanError> {
    options.validate()?;
    let clock = Instant::now();
    let bundle = Bundle::open(&options.bundle)?;
    if !options.no_video && options.camera >= bundle.meta.cameras.len() {
        return Err(invalid(
            "--camera",
            format!(
                "camera {} does not exist; the bundle has {}",
                options.camera,
                bundle.meta.cameras.len()
            ),
        ));
    }
    let model: WorldModel = if options.untrained {
        WorldModel::from_bundle(
            &bundle,
            &ModelOptions {
                residual: dm_model::ResidualKind::None,
                ..ModelOptions::default()
            },
        )?
    } else {
        WorldModel::load(&options.model_dir.join("model.json"))?
    };
    let play = if options.search.exact {
        PlayOptions::default()
    } else {
        PlayOptions::interactive()
    };
    let mut planning = PlanningModel::new(&model, &play)?.on_device(options.search.device);
    if options.search.residual {
        planning = planning.with_residual(&model, dm_residual::Precision::F32)?;
    }
    let rest_goal = read_goal(options, &bundle, &model)?;
    let correspondences: Option<Vec<usize>> = rest_goal.particles.as_ref().map(|ids| {
        let points: Vec<[f64; 3]> = ids.iter().map(|&i| model.particles[i]).collect();
        planning.nearest_particles(&points)
    });
    let (up, floor) = up_and_floor(&bundle);
    let clip_hands: Vec<Vec<[f64; 3]>> = (0..bundle.frame_count())
        .map(|t| dm_model::hand_anchors(&bundle, t))
        .collect();
    // The plant (built first: a plant that cannot be built should stop the
    // run before the search). Its domain holds the hands' reach from the
    // first frame and, for a later start, the clip's hands too.
    let rest_workspace = workspace(
        planning.particles(),
        options.search.workspace_margin_m,
        up,
        floor,
    );
    let mut reach = vec![rest_workspace.lo, rest_workspace.hi];
    if options.start_frame > 0 {
        reach.extend(clip_hands.iter().take(options.start_frame + 1).flatten());
    }
    let (mut plant, plant_name) = match &options.plant {
        Some(path) => {
            let truth = dm_synth::TruthFile::load(path)?;
            let clip = dm_synth::clip_hand_anchors(&truth);
            let plant = if truth.engine.is_some() {
                let foreign = dm_synth::foreign_plant::MujocoPlant::start(&truth, options.hands)?;
                Plant::foreign(foreign, clip)
            } else {
                let (world, surface) = dm_synth::plant_world(&truth, &reach)?;
                Plant::truth(world, surface, clip, options.search.device)?
            };
            (plant, format!("truth:{}", path.display()))
        }
        None => (
            Plant::model(
                &model.with_domain_containing(&reach),
                clip_hands.clone(),
                options.search.device,
            )?,
            "model".to_string(),
        ),
    };
    // Which plant particle each planning particle and goal point is
    // observed as: the nearest at the first frame.
    let plant_index = dm_mpm::neighbors::PointIndex::new(&plant.positions()?);
    let nearest_in_plant = |p: &[f64; 3]| plant_index.nearest(p, 1).first().map_or(0, |n| n.0);
    let observed_of: Vec<usize> = planning.particles().iter().map(nearest_in_plant).collect();
    let plant_correspondences: Option<Vec<usize>> = rest_goal.particles.as_ref().map(|ids| {
        ids.iter()
            .map(|&i| nearest_in_plant(&model.particles[i]))
            .collect()
    });
    let noise = Normal::new(0.0, options.observation_noise_mm * 1e-3)
        .map_err(|e| invalid("--observation-noise-mm", e.to_string()))?;
    let mut rng = ChaCha8Rng::seed_from_u64(options.search.seed ^ 0x5eed);
    // The planning world's own account of the plant (its deformation);
    // positions and velocities are observed from the plant.
    let mut tracker = planning.world::<f32>()?;
    let start_state = if options.start_frame > 0 {
        let state = start_from_clip(
            options,
            &mut plant,
            &mut tracker,
            &clip_hands,
            &observed_of,
            &noise,
            &mut rng,
            progress,
        )?;
        tracker.set_state(&state)?;
        Some(state)
    } else {
        None
    };
    let start_positions: Vec<[f64; 3]> = match &start_state {
        Some(state) => state
            .x
            .iter()
            .map(|p| [0, 1, 2].map(|a| f64::from(p[a])))
            .collect(),
        None => planning.particles().to_vec(),
    };
    // A named goal is the first frame's shape changed as it says; from a
    // later start, that shape where the object now lies.
    let goal = match (&start_state, &correspondences, &rest_goal.particles) {
        (Some(_), Some(ids), Some(model_ids)) if crate::goal::is_named(&options.goal) => {
            let now: Vec<[f64; 3]> = ids.iter().map(|&i| start_positions[i]).collect();
            let rest: Vec<[f64; 3]> = model_ids.iter().map(|&i| model.particles[i]).collect();
            rest_goal.placed_as_moved(&rest, &now, up)
        }
        _ => rest_goal,
    };
    // Never beyond the plant's domain.
    let (lo, hi) = bounds(&reach);
    let workspace = workspace(
        &start_positions,
        options.search.workspace_margin_m,
        up,
        floor,
    )
    .within(lo, hi);
    let grasps = grasp_points(
        options,
        &bundle,
        &start_positions,
        &goal,
        correspondences.as_deref(),
    );
    if grasps.is_empty() {
        return Err(invalid(
            "--goal",
            "no grasp point found: the goal has no correspondences and the bundle no hands",
        ));
    }
    let (weights, cost) = goal_cost(&options.search, &planning, &goal, correspondences.clone());
    let mut search = Search::new(&options.search, &planning, &cost, weights, workspace)?;
    let first = initial_plan(
        &grasps,
        &goal,
        correspondences.as_deref(),
        &start_positions,
        options.search.knots,
        options.search.horizon,
    );
    let mut plan = search.search(
        &first,
        start_state.as_ref(),
        options.search.iterations,
        options.search.gradient_iters,
        options.search.seed,
        progress,
    )?;
    let initial_plan_record = plan.clone();

    let mut planning_world = planning.world::<f32>()?;
    if let Some(state) = &start_state {
        planning_world.set_state(state)?;
    }
    let planned = rollout(&mut planning_world, &plan, true)?;
    let planned_outcome = cost.scores(planned.last().map(Vec::as_slice).unwrap_or(&[]));

    let plant_scores = |plant: &mut Plant| -> Result<_, PlanError> {
        Ok(scores(
            &goal.points,
            &plant.outline()?,
            &plant.positions()?,
            plant_correspondences.as_deref(),
        ))
    };
    let start_outcome = plant_scores(&mut plant)?;
    let mut executed = vec![plant.positions()?];
    let mut hands = vec![plan.anchors(0)];
    let mut replans = 0;
    let mut t = 0;
    // `plan` runs from frame `offset` of the whole motion.
    let mut offset = 0;
    while t < options.search.horizon {
        let segment = if options.replan_every == 0 {
            options.search.horizon - t
        } else {
            options.replan_every.min(options.search.horizon - t)
        };
        let segment_clock = Instant::now();
        for s in 0..segment {
            let (from, to) = (
                plan.anchors(t - offset + s),
                plan.anchors(t - offset + s + 1),
            );
            plant.step(&from, &to, t + s == 0)?;
            tracker.step_frame(&from, &to, &vec![t - offset + s == 0; from.len()])?;
            executed.push(plant.positions()?);
            hands.push(to);
            keep_going(
                progress("execute", t + s + 1, options.search.horizon),
                "execute",
            )?;
        }
        t += segment;
        if options.replan_every > 0 && t < options.search.horizon {
            // Observed: the plant's positions with noise, its velocities;
            // the deformation as the model predicts it.
            let state = observe(&mut plant, &mut tracker, &observed_of, &noise, &mut rng)?;
            search.seconds.execute += segment_clock.elapsed().as_secs_f64();
            let rest = shifted(&plan, t - offset);
            plan = search.search(
                &rest,
                Some(&state),
                options.replan_iterations,
                options.replan_iterations,
                options.search.seed + replans as u64 + 1,
                progress,
            )?;
            offset = t;
            tracker = planning.world::<f32>()?;
            tracker.set_state(&state)?;
            replans += 1;
        } else {
            search.seconds.execute += segment_clock.elapsed().as_secs_f64();
        }
    }
    let executed_outcome = plant_scores(&mut plant)?;
    let record = PlanRecord {
        options: options.clone(),
        goal: GoalRecord {
            name: goal.name.clone(),
            points: goal.points.len(),
            correspondences: goal.particles.is_some(),
        },
        planned: planned_outcome,
        executed: executed_outcome,
        plant: plant_name,
        start: start_outcome,
        rollouts: search.rollouts,
        seconds: clock.elapsed().as_secs_f64(),
        seconds_by_stage: search.seconds,
        replans,
        history: search.history.clone(),
        planning_world: PlanningWorldRecord::of(&planning, &planning_world),
        actions: initial_plan_record,
    };
    Ok(RunResult {
        record,
        planned,
        executed,
        hands,
        goal,
        splat_radius: model.splat_radius(),
        frame_dt: planning.frame_dt(),
        bundle,
    })
}
