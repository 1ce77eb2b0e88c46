//! dm-plan on tiny dm-synth scenes: the plan's gradient through the
//! simulator against finite differences, and a search that brings the
//! object closer to its goal in the model and in the truth world.

use std::ops::ControlFlow;

use dm_bundle::Bundle;
use dm_model::{ModelOptions, ResidualKind, WorldModel};
use dm_plan::actions::ActionPlan;
use dm_plan::cost::{CostWeights, TerminalCost};
use dm_plan::goal::Goal;
use dm_plan::gradient::cost_and_gradient;
use dm_plan::world::{PlanningModel, WorldPool};
use dm_play::PlayOptions;
use dm_synth::{Preset, SynthConfig};

fn tiny(
    dir: &std::path::Path,
    preset: Preset,
    seed: u64,
    residual: ResidualKind,
) -> (Bundle, WorldModel) {
    let scene = dir.join("scene");
    dm_synth::generate(
        &SynthConfig::tiny(preset, seed),
        &scene,
        &dir.join("truth.json"),
        &mut |_, _, _| {},
    )
    .expect("scene");
    let bundle = Bundle::open(&scene).expect("bundle");
    let options = ModelOptions {
        residual,
        ..ModelOptions::default()
    };
    let model = WorldModel::from_bundle(&bundle, &options).expect("model");
    (bundle, model)
}

/// The knots' gradient (actuator adjoint → per-frame anchors → knots,
/// plus the penalty) against central differences through the whole f64
/// rollout, every substep differentiated. Tolerance 1e-4 relative: three
/// frames of 10–20 substeps compose, and the Chamfer term's nearest
/// neighbours stay put within the ±1e-6 m steps.
#[test]
fn knot_gradient_through_the_simulator_matches_finite_differences() {
    knot_gradient_matches_finite_differences(false, 1e-4);
}

/// As above with a residual network (non-zero weights) correcting every
/// frame: its adjoint, including the earlier frame starts it sees as
/// history, joins the physics adjoint. Tolerance 1e-5 relative: here the
/// history's share of the gradient is about 1e-4 of it (dropping it gives
/// 9e-5), the exact adjoint agrees to 2e-6.
#[test]
fn knot_gradient_through_the_residual_matches_finite_differences() {
    knot_gradient_matches_finite_differences(true, 1e-5);
}

fn knot_gradient_matches_finite_differences(residual: bool, tolerance: f64) {
    let dir = tempfile::tempdir().expect("temp dir");
    let kind = if residual {
        ResidualKind::Pgnd
    } else {
        ResidualKind::None
    };
    let (bundle, mut model) = tiny(dir.path(), Preset::Rope, 3, kind);
    let mut planning =
        PlanningModel::new(&model, &PlayOptions::interactive()).expect("planning model");
    if let Some(state) = model.residual.as_mut() {
        // The fresh network's last layer is zero: give every weight a value.
        state.parameters = (0..state.parameters.len())
            .map(|i| 0.3 * ((i as f64) * 0.37 + 0.1).sin())
            .collect();
        planning = planning
            .with_residual(&model, dm_residual::Precision::F64)
            .expect("residual");
    }
    let up = bundle.meta.up_axis.unit_vector();
    let goal = Goal::named(
        "move",
        bundle.meta.category,
        &model.particles,
        model.surface_count,
        up,
        0.0,
    )
    .expect("goal");
    let ids: Vec<[f64; 3]> = goal
        .particles
        .as_ref()
        .expect("correspondences")
        .iter()
        .map(|&i| model.particles[i])
        .collect();
    let correspondences = planning.nearest_particles(&ids);
    let weights = CostWeights {
        max_speed_m_s: 0.05,
        ..CostWeights::default()
    };
    let cost = TerminalCost::new(
        goal.points.clone(),
        Some(correspondences),
        planning.surface_count(),
        weights,
    );
    let particles = planning.particles();
    let grasps = [particles[0], particles[planning.surface_count() / 2]];
    let mut plan = ActionPlan::at_rest(&grasps, 2, 3);
    let params: Vec<f64> = (0..plan.params().len())
        .map(|i| 0.01 * ((i as f64) * 0.9 + 0.3).sin())
        .collect();
    plan = plan.with_params(&params);
    // Every substep differentiated, each time in a new f64 world.
    let exact = |planning: &PlanningModel, plan: &ActionPlan| {
        let mut world = planning.world::<f64>().expect("world");
        cost_and_gradient(
            &mut world,
            planning,
            None,
            plan,
            &cost,
            &weights,
            usize::MAX,
        )
        .expect("cost and gradient")
    };
    let (_, grad) = exact(&planning, &plan);
    let value = |p: &[f64]| exact(&planning, &plan.with_params(p)).0;
    let h = 1e-6;
    let mut largest: f64 = 0.0;
    for i in 0..params.len() {
        let mut up = params.clone();
        up[i] += h;
        let mut down = params.clone();
        down[i] -= h;
        let fd = (value(&up) - value(&down)) / (2.0 * h);
        largest = largest.max(fd.abs());
        let error = (fd - grad[i]).abs() / fd.abs().max(grad[i].abs()).max(1e-9);
        assert!(
            error < tolerance,
            "knot parameter {i}: adjoint {:.8e}, finite differences {fd:.8e}",
            grad[i]
        );
    }
    assert!(largest > 1e-6, "the knots must move the cost");
    if residual {
        // The residual must matter: the same plan without it costs differently.
        let physics_only =
            PlanningModel::new(&model, &PlayOptions::interactive()).expect("planning model");
        let (without, _) = exact(&physics_only, &plan);
        let (with, _) = exact(&planning, &plan);
        assert!(
            (with - without).abs() > 1e-2 * without.abs(),
            "residual on {with:e}, off {without:e}"
        );
        // A model without a network refuses `--residual`, naming it.
        let mut bare = model.clone();
        bare.residual = None;
        let refused = PlanningModel::new(&bare, &PlayOptions::interactive())
            .expect("planning model")
            .with_residual(&bare, dm_residual::Precision::F32)
            .expect_err("no network");
        assert!(refused.to_string().contains("--residual"), "{refused}");
    }
}

/// A small search with the untrained model, one hand, re-planned once,
/// carried out in the scene's truth world.
fn small_plan(
    dir: &std::path::Path,
    scene: &std::path::Path,
    truth: &std::path::Path,
    goal: &str,
) -> dm_plan::run::PlanOptions {
    dm_plan::run::PlanOptions {
        model_dir: dir.join("no-model"),
        bundle: scene.to_path_buf(),
        goal: goal.into(),
        out: dir.join("plan"),
        plant: Some(truth.to_path_buf()),
        start_frame: 0,
        settle_frames: 30,
        hands: 1,
        search: small_search(),
        replan_every: 6,
        replan_iterations: 1,
        observation_noise_mm: 1.5,
        untrained: true,
        camera: 0,
        no_video: true,
    }
}

/// A few samples and steps over a short horizon.
fn small_search() -> dm_plan::run::SearchOptions {
    dm_plan::run::SearchOptions {
        optimizer: dm_plan::run::Optimizer::MppiGradient,
        horizon: 12,
        knots: 2,
        samples: 6,
        iterations: 3,
        noise_m: 0.02,
        gradient_iters: 3,
        learning_rate_m: 0.004,
        window: 4,
        max_speed: 0.5,
        workspace_margin_m: 0.2,
        exact: false,
        residual: false,
        seed: 1,
        device: dm_model::device::Device::Cpu,
    }
}

#[test]
fn a_planned_motion_brings_the_object_closer_to_its_goal_in_the_truth_world() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = dir.path().join("scene");
    let truth = dir.path().join("truth.json");
    dm_synth::generate(
        &SynthConfig::tiny(Preset::Toy, 5),
        &scene,
        &truth,
        &mut |_, _, _| {},
    )
    .expect("scene");
    let options = small_plan(dir.path(), &scene, &truth, "place");
    let result =
        dm_plan::run::plan(&options, &mut |_, _, _| ControlFlow::Continue(())).expect("plan");
    let r = &result.record;
    assert_eq!(r.replans, 1);
    assert_eq!(result.executed.len(), 13);
    assert!(
        r.planned.final_chamfer_m < r.start.final_chamfer_m,
        "planned {:.4} m vs start {:.4} m",
        r.planned.final_chamfer_m,
        r.start.final_chamfer_m
    );
    assert!(
        r.executed.final_chamfer_m < r.start.final_chamfer_m,
        "executed {:.4} m vs start {:.4} m",
        r.executed.final_chamfer_m,
        r.start.final_chamfer_m
    );
    // Seeded: the same options give the same plan and the same execution.
    let again =
        dm_plan::run::plan(&options, &mut |_, _, _| ControlFlow::Continue(())).expect("plan");
    assert_eq!(again.executed, result.executed);
    // A callback that breaks stops the run where it is.
    let mut stages = Vec::new();
    let stopped = dm_plan::run::plan(&options, &mut |stage, _, _| {
        stages.push(stage.to_owned());
        if stage == "MPPI" {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    });
    match stopped {
        Err(dm_plan::PlanError::Stopped { stage }) => assert_eq!(stage, "MPPI"),
        other => panic!(
            "the run did not stop: {:?}",
            other.map(|r| r.record.rollouts)
        ),
    }
    assert_eq!(stages.last().map(String::as_str), Some("MPPI"));
    assert_eq!(
        stages.iter().filter(|s| *s == "MPPI").count(),
        1,
        "called after the stop"
    );
}

/// From a later start the plant and the planning world first play the
/// clip's hands, let go and settle; the plan starts from there, and a
/// named goal is asked for where the object then lies.
#[test]
fn a_plan_from_a_later_start_begins_where_the_clip_leaves_the_object() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = dir.path().join("scene");
    let truth = dir.path().join("truth.json");
    let config = SynthConfig::tiny(Preset::Rope, 4);
    dm_synth::generate(&config, &scene, &truth, &mut |_, _, _| {}).expect("scene");
    let options = |start_frame: usize| dm_plan::run::PlanOptions {
        start_frame,
        settle_frames: 4,
        search: dm_plan::run::SearchOptions {
            horizon: 10,
            samples: 4,
            iterations: 2,
            gradient_iters: 2,
            ..small_search()
        },
        replan_every: 0,
        ..small_plan(dir.path(), &scene, &truth, "move")
    };
    let at_rest =
        dm_plan::run::plan(&options(0), &mut |_, _, _| ControlFlow::Continue(())).expect("plan");
    let later = dm_plan::run::plan(&options(config.frames - 1), &mut |_, _, _| {
        ControlFlow::Continue(())
    })
    .expect("plan");
    let centre = |points: &[[f64; 3]]| -> [f64; 3] {
        let n = points.len() as f64;
        std::array::from_fn(|a| points.iter().map(|p| p[a]).sum::<f64>() / n)
    };
    let distance =
        |a: [f64; 3], b: [f64; 3]| (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt();
    let (rest_start, later_start) = (centre(&at_rest.executed[0]), centre(&later.executed[0]));
    let moved = distance(rest_start, later_start);
    assert!(moved > 0.005, "the clip moved the object by {moved} m only");
    // `move` asks for the object 0.15 m sideways of where it starts.
    let up = Bundle::open(&scene)
        .expect("bundle")
        .meta
        .up_axis
        .unit_vector();
    for run in [&at_rest, &later] {
        let (goal, start) = (centre(&run.goal.points), centre(&run.executed[0]));
        let d: [f64; 3] = std::array::from_fn(|a| goal[a] - start[a]);
        let h = (0..3).map(|a| d[a] * up[a]).sum::<f64>();
        let sideways = distance(d, std::array::from_fn(|a| h * up[a]));
        assert!(
            (sideways - 0.15).abs() < 0.02,
            "goal {sideways} m from the start"
        );
    }
    assert!(
        later.record.executed.final_chamfer_m < later.record.start.final_chamfer_m,
        "executed {:.4} m vs start {:.4} m",
        later.record.executed.final_chamfer_m,
        later.record.start.final_chamfer_m
    );
}

/// A simulation of `model` stepped `steps` frames along the clip, and what
/// a plan from there starts with.
struct Stepped {
    simulation: dm_model::Simulation,
    state: dm_mpm::state::Particles<f32>,
    hands: Vec<[f64; 3]>,
    grip: dm_mpm::actuators::Grip,
    material: dm_play::MaterialControl,
}

impl Stepped {
    fn start(&self) -> dm_plan::live::LiveStart<'_> {
        dm_plan::live::LiveStart {
            state: &self.state,
            hands: &self.hands,
            grip: &self.grip,
            material: &self.material,
            rigid_hands: None,
        }
    }
}

fn stepped(model: &WorldModel, bundle: &Bundle, steps: usize) -> Stepped {
    let mut simulation = model.simulation().expect("simulation");
    for t in 0..steps {
        let (from, to, grasp) = dm_model::hand_step(bundle, t);
        simulation.step(&from, &to, &grasp).expect("step");
    }
    let world = simulation.world().expect("world");
    let all: Vec<usize> = (0..model.particles.len()).collect();
    let (state, grip) = (world.state(), world.grip(&all).expect("grip"));
    Stepped {
        simulation,
        state,
        hands: dm_model::hand_anchors(bundle, steps),
        grip,
        material: dm_play::MaterialControl {
            e_scale: 1.0,
            nu: None,
            damping: model.physics.particle_damping,
        },
    }
}

/// The goal `name` made from the model's first frame in the bundle's scene.
fn named_goal(name: &str, bundle: &Bundle, model: &WorldModel) -> Goal {
    let meta = &bundle.meta;
    Goal::named(
        name,
        meta.category,
        &model.particles,
        model.surface_count,
        meta.up_axis.unit_vector(),
        meta.floor_height_m,
    )
    .expect("goal")
}

/// A plan from a simulation stepped part way through its clip starts
/// exactly where the simulation is (its hands, its particles' state), and
/// stepping the simulation along the planned anchors brings the object
/// closer to the goal than it was.
#[test]
fn a_plan_from_a_live_state_starts_there_and_moves_the_simulation_towards_the_goal() {
    live_plan_moves_the_simulation_towards_the_goal(false);
}

/// The same with each of the bundle's hands moved as one rigid hand: its
/// anchors keep their offsets at every frame of the plan.
#[test]
fn a_live_plan_with_rigid_hands_keeps_each_hand_rigid() {
    live_plan_moves_the_simulation_towards_the_goal(true);
}

fn live_plan_moves_the_simulation_towards_the_goal(rigid: bool) {
    let dir = tempfile::tempdir().expect("temp dir");
    let (bundle, model) = tiny(dir.path(), Preset::Rope, 5, ResidualKind::None);
    let mut live = stepped(&model, &bundle, 4);
    let goal = named_goal("move", &bundle, &model);
    let options = dm_plan::run::SearchOptions {
        horizon: 10,
        samples: 4,
        iterations: 2,
        gradient_iters: 2,
        ..small_search()
    };
    let ranges: Vec<[usize; 2]> = bundle.meta.hands.iter().map(|h| h.anchor_range).collect();
    let start = dm_plan::live::LiveStart {
        rigid_hands: rigid.then_some(ranges.as_slice()),
        ..live.start()
    };
    let plan = dm_plan::live::plan_from_state(&model, &start, &goal, &options, &mut |_, _, _| {
        ControlFlow::Continue(())
    })
    .expect("plan");
    assert_eq!(plan.hands.len(), options.horizon + 1);
    if rigid {
        assert!(
            ranges.iter().any(|[start, end]| end - start > 1),
            "the scene's hands are single anchors: {ranges:?}"
        );
        for (t, anchors) in plan.hands.iter().enumerate() {
            for &[start, end] in &ranges {
                let shift = |i: usize| [0, 1, 2].map(|a| anchors[i][a] - plan.hands[0][i][a]);
                for i in start + 1..end {
                    let (first, this) = (shift(start), shift(i));
                    assert!(
                        (0..3).all(|a| (first[a] - this[a]).abs() < 1e-12),
                        "frame {t}: anchor {i} moved {this:?}, its hand's first {first:?}"
                    );
                }
            }
        }
        assert!(
            plan.hands.last() != plan.hands.first(),
            "the hands did not move"
        );
    }
    assert_eq!(
        plan.hands[0], live.hands,
        "the plan starts where the hands are"
    );
    for (p, &i) in plan.planned_particles.iter().enumerate() {
        let now = [0, 1, 2].map(|a| f64::from(live.state.x[i][a]));
        assert_eq!(plan.planned[0][p], now, "planning particle {p} (model {i})");
    }
    let surface_scores = |positions: &[[f32; 3]]| {
        let positions: Vec<[f64; 3]> = positions.iter().map(|p| p.map(f64::from)).collect();
        dm_plan::cost::scores(
            &goal.points,
            &positions[..model.surface_count],
            &positions,
            goal.particles.as_deref(),
        )
    };
    let before = surface_scores(&live.simulation.positions_f32().expect("positions"));
    for t in 0..options.horizon {
        let grasp = vec![false; live.hands.len()];
        live.simulation
            .step(&plan.hands[t], &plan.hands[t + 1], &grasp)
            .expect("step");
    }
    let after = surface_scores(&live.simulation.positions_f32().expect("positions"));
    assert!(
        after.final_chamfer_m < 0.8 * before.final_chamfer_m,
        "Chamfer to the goal {:.4} m before, {:.4} m after the plan",
        before.final_chamfer_m,
        after.final_chamfer_m
    );
    assert!(
        plan.record.planned.final_chamfer_m < plan.record.start.final_chamfer_m,
        "planned {:?} against the start {:?}",
        plan.record.planned,
        plan.record.start
    );
}

/// The planning world takes a simulation's changed material: the same
/// hand motion bends a stiffer object less.
#[test]
fn the_planning_world_steps_in_the_material_it_is_given() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (bundle, model) = tiny(dir.path(), Preset::Rope, 6, ResidualKind::None);
    let hands = dm_model::hand_anchors(&bundle, 0);
    let mut plan = ActionPlan::at_rest(&hands[..1], 2, 6);
    plan.hands[0].knots = vec![[0.0, 0.0, 0.05], [0.05, 0.0, 0.1]];
    let last_frame = |e_scale: f64| {
        let material = dm_play::MaterialControl {
            e_scale,
            nu: None,
            damping: model.physics.particle_damping,
        };
        let planning = PlanningModel::new(&model, &PlayOptions::interactive())
            .expect("planning model")
            .with_material(&material);
        let mut world = planning.world::<f64>().expect("world");
        let frames = dm_plan::world::rollout(&mut world, &plan, true).expect("rollout");
        frames.last().cloned().expect("frames")
    };
    let (fitted, stiffer) = (last_frame(1.0), last_frame(8.0));
    let moved = fitted
        .iter()
        .zip(&stiffer)
        .map(|(a, b)| (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt())
        .fold(0.0, f64::max);
    assert!(
        moved > 1e-3,
        "8× the stiffness moved no particle by more than {moved} m"
    );
}

/// A world kept between rollouts and started again gives the rollout a
/// new world would, bit for bit: after a rollout whose hands grasped and
/// pulled, a different plan from the first frame and one from a later
/// state (the hands grasping there again).
#[test]
fn a_kept_world_started_again_rolls_out_as_a_new_one() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (bundle, model) = tiny(dir.path(), Preset::Rope, 6, ResidualKind::None);
    let planning = PlanningModel::new(&model, &PlayOptions::interactive()).expect("planning");
    let hands = dm_model::hand_anchors(&bundle, 0);
    let mut pulled = ActionPlan::at_rest(&hands, 2, 4);
    pulled.hands[0].knots = vec![[0.0, 0.04, 0.02], [0.03, 0.06, 0.05]];
    let mut lifted = ActionPlan::at_rest(&hands, 2, 4);
    lifted.hands[0].knots = vec![[0.0, 0.05, 0.0], [0.0, 0.08, 0.0]];
    let mut fresh = planning.world::<f32>().expect("world");
    dm_plan::world::rollout(&mut fresh, &pulled, true).expect("rollout");
    let later = fresh.state().expect("state");
    let pool = WorldPool::<f32>::new(&planning).expect("pool");
    let mut kept = pool.take().expect("world");
    dm_plan::world::rollout(&mut kept, &pulled, true).expect("rollout");
    pool.give_back(kept);
    for start in [None, Some(&later)] {
        let mut kept = pool.take().expect("kept world");
        let mut fresh = planning.world::<f32>().expect("world");
        if let Some(state) = start {
            kept.set_state(state).expect("state");
            fresh.set_state(state).expect("state");
        }
        let want = dm_plan::world::rollout(&mut fresh, &lifted, true).expect("rollout");
        let got = dm_plan::world::rollout(&mut kept, &lifted, true).expect("rollout");
        assert_eq!(
            got,
            want,
            "a kept world rolled out otherwise (start {:?})",
            start.is_some()
        );
        pool.give_back(kept);
    }
}

/// With `exact`, the planning world is the model's own world: a
/// simulation part way through its clip, stepped along the plan's anchors,
/// does what was planned, bit for bit — positions, velocities,
/// deformation, affine velocity and the hands' hold all carried over, and
/// the physics a diagnosis added (a stiff ball, a density gradient).
#[test]
fn an_exact_plan_is_what_the_simulation_then_does() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (bundle, mut model) = tiny(dir.path(), Preset::Rope, 7, ResidualKind::None);
    let centre = model.particles[model.particles.len() / 2];
    model.extension = dm_model::ModelExtension {
        stiff_ball: Some(dm_model::extension::StiffBall {
            centre,
            radius: 0.05,
            factor: 6.0,
        }),
        density: Some(dm_model::extension::DensityGradient {
            axis: [1.0, 0.0, 0.0],
            excess: 0.8,
        }),
        ..Default::default()
    };
    let mut live = stepped(&model, &bundle, 3);
    let goal = named_goal("u-shape", &bundle, &model);
    let options = dm_plan::run::SearchOptions {
        horizon: 5,
        samples: 2,
        iterations: 1,
        gradient_iters: 1,
        exact: true,
        ..small_search()
    };
    let plan =
        dm_plan::live::plan_from_state(&model, &live.start(), &goal, &options, &mut |_, _, _| {
            ControlFlow::Continue(())
        })
        .expect("plan");
    assert_eq!(plan.planned_particles.len(), model.particles.len());
    for t in 0..options.horizon {
        let grasp = vec![false; live.hands.len()];
        live.simulation
            .step(&plan.hands[t], &plan.hands[t + 1], &grasp)
            .expect("step");
        let done: Vec<[f64; 3]> = live
            .simulation
            .positions_f32()
            .expect("positions")
            .iter()
            .map(|p| p.map(f64::from))
            .collect();
        let apart = done
            .iter()
            .zip(&plan.planned[t + 1])
            .map(|(a, b)| (0..3).map(|k| (a[k] - b[k]).abs()).fold(0.0, f64::max))
            .fold(0.0, f64::max);
        assert!(apart == 0.0, "frame {}: {apart:e} m apart", t + 1);
    }
}

/// A live plan starts from the better of moving each hand straight to its
/// grasped particles' goal points and holding still: with the grasped
/// particles' goal points far off (the rest where the object lies), holding
/// still wins and, with no search after it, the hands stay; with the goal
/// the whole object moved, the straight path wins and they move.
#[test]
fn a_live_plan_starts_from_holding_still_where_that_ends_nearer() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (bundle, model) = tiny(dir.path(), Preset::Rope, 5, ResidualKind::None);
    let live = stepped(&model, &bundle, 4);
    let up = bundle.meta.up_axis.unit_vector();
    let now: Vec<[f64; 3]> = live.state.x[..model.surface_count]
        .iter()
        .map(|p| [0, 1, 2].map(|a| f64::from(p[a])))
        .collect();
    let near_a_hand = |p: &[f64; 3]| {
        live.hands
            .iter()
            .any(|h| (0..3).map(|a| (p[a] - h[a]).powi(2)).sum::<f64>() < 0.03f64.powi(2))
    };
    assert!(now.iter().any(near_a_hand), "no particle near the hands");
    let goal_with = |shift: &dyn Fn(&[f64; 3]) -> [f64; 3]| Goal {
        name: "points".into(),
        points: now
            .iter()
            .map(|p| {
                let d = shift(p);
                [0, 1, 2].map(|a| p[a] + d[a])
            })
            .collect(),
        particles: Some((0..model.surface_count).collect()),
    };
    let options = dm_plan::run::SearchOptions {
        horizon: 6,
        samples: 2,
        iterations: 0,
        gradient_iters: 0,
        ..small_search()
    };
    let plan = |goal: &Goal| {
        dm_plan::live::plan_from_state(&model, &live.start(), goal, &options, &mut |_, _, _| {
            ControlFlow::Continue(())
        })
        .expect("plan")
    };
    let held_far = goal_with(&|p| {
        if near_a_hand(p) {
            up.map(|u| 0.3 * u)
        } else {
            [0.0; 3]
        }
    });
    let still = plan(&held_far);
    assert!(
        still.hands.iter().all(|frame| frame == &still.hands[0]),
        "the hands moved though holding still ends nearer"
    );
    assert_eq!(still.record.rollouts, 2, "both candidates are costed");
    let moved = plan(&goal_with(&|_| [0.05, 0.0, 0.0]));
    assert!(
        moved.hands.last() != moved.hands.first(),
        "the hands held still though the straight path ends nearer"
    );
}
