//! Issue 3: the adjoint of a whole video frame (every substep, actuators
//! coupled) against central finite differences in f64, through
//! `World::step_frame_taped` / `World::backward_frame`.

use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::real::{Mat3, Vec3};
use dm_mpm::state::Particles;
use dm_mpm::tape::FrameGrads;
use dm_mpm::{ActuatorConfig, ParticleMaterial, PhysicsConfig, World};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A frame composes 8 substeps, so round-off grows a little over the
/// single-substep check; 1e-5 (the bound) still holds with margin.
const FD_RTOL: f64 = 1e-5;
const FD_STEP: f64 = 1e-6;

fn rand_vec(rng: &mut ChaCha8Rng, s: f64) -> Vec3<f64> {
    Vec3::new(0.0, 0.0, 0.0).map(|_| s * (2.0 * rng.random::<f64>() - 1.0))
}

// 2 cm apart with a 3 cm grasp radius: some particles hang on both (n = 2).
const FROM: [[f64; 3]; 2] = [[-0.01, 0.0, 0.125], [0.01, 0.0, 0.125]];

fn anchors_to() -> Vec<[f64; 3]> {
    FROM.iter()
        .map(|a| [a[0] + 0.003, a[1], a[2] + 0.01])
        .collect()
}

fn world() -> World<f64> {
    world_with(|_| {})
}

/// The test world with its physics settings adjusted before it is built.
fn world_with(adjust: impl FnOnce(&mut PhysicsConfig)) -> World<f64> {
    let mut config = PhysicsConfig::volumetric([-0.25, -0.25, -0.1], 0.5, [0.0, 0.0, 1.0]);
    config.grid_res = 16;
    config.dt = 1e-3;
    config.substeps_per_frame = 8;
    config.position_clip = [0.1, 0.9]; // 1.5 cells at 16³
    config.empty_node_mass_ratio = 0.0;
    config.effects.air_drag_linear = 0.5;
    adjust(&mut config);
    let mut positions = Vec::new();
    for i in 0..5 {
        for j in 0..4 {
            for k in 0..4 {
                positions.push([
                    -0.04 + 0.02 * i as f64,
                    -0.03 + 0.02 * j as f64,
                    0.06 + 0.02 * k as f64,
                ]);
            }
        }
    }
    let n = positions.len();
    let weights = vec![[0.5, 0.3, 0.2]; n];
    let youngs: Vec<f64> = (0..n).map(|i| 2e3 + 50.0 * (i % 7) as f64).collect();
    let poisson = vec![0.3; n];
    let material = ParticleMaterial::from_fields(&youngs, &poisson, &weights);
    let actuators = ActuatorConfig {
        kp: 800.0,
        kd: 20.0,
        grasp_radius: 0.03,
        ..ActuatorConfig::default()
    };
    let mut w = World::new(config, &positions, 8e-6, material, actuators).expect("world");
    // Grasp and set things moving in a first, untaped frame.
    w.step_frame(&FROM, &FROM, &[true, true])
        .expect("first frame");
    w
}

/// A random loss direction on positions and velocities only.
fn position_velocity_probe(rng: &mut ChaCha8Rng, n: usize) -> ParticleGrads<f64> {
    ParticleGrads {
        x: (0..n).map(|_| rand_vec(rng, 1.0)).collect(),
        v: (0..n).map(|_| rand_vec(rng, 1.0)).collect(),
        f: vec![Mat3::zeros(); n],
        c: vec![Mat3::zeros(); n],
    }
}

/// Steps `w` one taped frame (FROM → `anchors_to()`, every substep
/// recorded) and runs its backward pass for a random position/velocity
/// probe drawn from `rng`.
fn probed_frame(w: &mut World<f64>, rng: &mut ChaCha8Rng) -> (ParticleGrads<f64>, FrameGrads<f64>) {
    let probe = position_velocity_probe(rng, w.particle_count());
    let tape = w
        .step_frame_taped(&FROM, &anchors_to(), &[true, true], usize::MAX)
        .expect("taped frame");
    let grads = w.backward_frame(&tape, &probe).expect("backward");
    (probe, grads)
}

fn loss(state: &Particles<f64>, probe: &ParticleGrads<f64>) -> f64 {
    (0..state.len())
        .map(|p| {
            probe.x[p].dot(&state.x[p])
                + probe.v[p].dot(&state.v[p])
                + probe.f[p].component_mul(&state.f[p]).sum()
                + probe.c[p].component_mul(&state.c[p]).sum()
        })
        .sum()
}

fn check(name: &str, analytic: f64, eval: &mut dyn FnMut(f64) -> f64) {
    let numeric = (eval(FD_STEP) - eval(-FD_STEP)) / (2.0 * FD_STEP);
    let rel = (analytic - numeric).abs() / analytic.abs().max(numeric.abs()).max(1e-8);
    assert!(
        rel <= FD_RTOL,
        "{name}: adjoint {analytic:.10e} vs finite differences {numeric:.10e} (relative error {rel:.2e})"
    );
}

#[test]
fn frame_adjoint_with_actuators_matches_finite_differences() {
    let mut w = world();
    let n = w.particle_count();
    assert!(
        w.actuators().coupling_count() > 0,
        "the hand must hold particles"
    );
    let start = w.state();
    let to = anchors_to();
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let probe = ParticleGrads {
        x: (0..n).map(|_| rand_vec(&mut rng, 1.0)).collect(),
        v: (0..n).map(|_| rand_vec(&mut rng, 1.0)).collect(),
        f: (0..n)
            .map(|_| Mat3::from_fn(|_, _| 2.0 * rng.random::<f64>() - 1.0))
            .collect(),
        c: (0..n)
            .map(|_| Mat3::from_fn(|_, _| 0.01 * (2.0 * rng.random::<f64>() - 1.0)))
            .collect(),
    };
    let tape = w
        .step_frame_taped(&FROM, &to, &[true, true], usize::MAX)
        .expect("taped frame");
    assert_eq!(tape.len(), w.config().substeps_per_frame, "full window");
    let grads = w.backward_frame(&tape, &probe).expect("backward");

    let run = |w: &mut World<f64>, state: &Particles<f64>| {
        w.set_state(state).expect("state");
        w.step_frame(&FROM, &to, &[true, true]).expect("frame");
        loss(&w.state(), &probe)
    };
    let dx: Vec<Vec3<f64>> = (0..n).map(|_| rand_vec(&mut rng, 1.0)).collect();
    let dv: Vec<Vec3<f64>> = (0..n).map(|_| rand_vec(&mut rng, 1.0)).collect();
    let analytic_x: f64 = grads.state.x.iter().zip(&dx).map(|(g, d)| g.dot(d)).sum();
    check("x", analytic_x, &mut |h| {
        let mut s = start.clone();
        s.x.iter_mut().zip(&dx).for_each(|(x, d)| *x += d * h);
        run(&mut w, &s)
    });
    let analytic_v: f64 = grads.state.v.iter().zip(&dv).map(|(g, d)| g.dot(d)).sum();
    check("v", analytic_v, &mut |h| {
        let mut s = start.clone();
        s.v.iter_mut().zip(&dv).for_each(|(v, d)| *v += d * h);
        run(&mut w, &s)
    });
    let base_material = {
        let e: Vec<f64> = (0..n).map(|i| 2e3 + 50.0 * (i % 7) as f64).collect();
        ParticleMaterial::<f64>::from_fields(&e, &vec![0.3; n], &vec![[0.5, 0.3, 0.2]; n])
    };
    // μ ≈ 800 Pa and the loss is weakly sensitive to it: a direction of
    // 1e4 Pa keeps the finite difference above round-off (step 0.01 Pa).
    let dmu: Vec<f64> = (0..n)
        .map(|_| 1e4 * (2.0 * rng.random::<f64>() - 1.0))
        .collect();
    let analytic_mu: f64 = grads.mu.iter().zip(&dmu).map(|(g, d)| g * d).sum();
    check("mu", analytic_mu, &mut |h| {
        let mut m = base_material.clone();
        m.mu.iter_mut().zip(&dmu).for_each(|(mu, d)| *mu += d * h);
        w.set_material(m).expect("material");
        let l = run(&mut w, &start);
        w.set_material(base_material.clone()).expect("material");
        l
    });
    check("kp", grads.gains.kp * 100.0, &mut |h| {
        w.set_gains(800.0 + 100.0 * h, 20.0);
        let l = run(&mut w, &start);
        w.set_gains(800.0, 20.0);
        l
    });
    check("kd", grads.gains.kd, &mut |h| {
        w.set_gains(800.0, 20.0 + h);
        let l = run(&mut w, &start);
        w.set_gains(800.0, 20.0);
        l
    });
    check_gravity(&mut w, &start, &to, &probe, grads.effects.gravity);
    check_mass(&mut w, &start, &to, &probe, &grads.mass, &mut rng);
}

/// ∂L/∂m (each particle's mass, a density gradient's parameter) along a
/// relative direction: each mass moves by up to its own size times the
/// step, like the other checks' steps against their scale.
fn check_mass(
    w: &mut World<f64>,
    start: &Particles<f64>,
    to: &[[f64; 3]],
    probe: &ParticleGrads<f64>,
    analytic: &[f64],
    rng: &mut ChaCha8Rng,
) {
    let direction: Vec<f64> = start
        .mass
        .iter()
        .map(|m| m * (2.0 * rng.random::<f64>() - 1.0))
        .collect();
    let along: f64 = analytic.iter().zip(&direction).map(|(g, d)| g * d).sum();
    check("mass", along, &mut |h| {
        let mut s = start.clone();
        s.mass
            .iter_mut()
            .zip(&direction)
            .for_each(|(m, d)| *m += d * h);
        w.set_state(&s).expect("state");
        w.step_frame(&FROM, to, &[true, true]).expect("frame");
        loss(&w.state(), probe)
    });
}

/// ∂L/∂g along a tilt-like direction: gravity turned a little sideways
/// (a direction of 10 m/s², so the loss moves well above round-off).
fn check_gravity(
    w: &mut World<f64>,
    start: &Particles<f64>,
    to: &[[f64; 3]],
    probe: &ParticleGrads<f64>,
    analytic: [f64; 3],
) {
    let base = w.config().gravity;
    let direction = [6.0, -8.0, 0.5];
    let along: f64 = (0..3).map(|a| analytic[a] * direction[a]).sum();
    check("gravity", along, &mut |h| {
        let mut config = w.config().clone();
        config.gravity = std::array::from_fn(|a| base[a] + direction[a] * h);
        w.set_gravity(config.gravity).expect("gravity");
        w.set_state(start).expect("state");
        w.step_frame(&FROM, to, &[true, true]).expect("frame");
        let l = loss(&w.state(), probe);
        w.set_gravity(base).expect("gravity");
        l
    });
}

#[test]
fn truncated_window_records_only_the_last_substeps() {
    let mut w = world();
    let tape = w
        .step_frame_taped(&FROM, &anchors_to(), &[true, true], 3)
        .expect("taped frame");
    assert_eq!(tape.len(), 3);
    let n = w.particle_count();
    let probe = ParticleGrads::zeros(n);
    let grads = w.backward_frame(&tape, &probe).expect("backward");
    assert!(
        grads.state.x.iter().all(|g| g.norm() == 0.0),
        "zero upstream gives zero gradient"
    );
}

/// The residual's hook: a frame followed by a velocity
/// correction, differentiated with respect to the correction and the
/// frame's start state, one particle pushed against the position clip so
/// that the clipped branch is exercised too.
#[test]
fn velocity_correction_after_a_frame_matches_finite_differences() {
    let mut w = world();
    let n = w.particle_count();
    let start = w.state();
    let to = anchors_to();
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let probe = position_velocity_probe(&mut rng, n);
    let mut correction: Vec<[f64; 3]> = (0..n).map(|_| rand_vec(&mut rng, 0.05).into()).collect();
    // Far enough down to leave the domain: the clip must hold it.
    correction[0][2] = -20.0;
    let direction: Vec<Vec3<f64>> = (0..n).map(|_| rand_vec(&mut rng, 1.0)).collect();

    let tape = w
        .step_frame_taped(&FROM, &to, &[true, true], usize::MAX)
        .expect("taped frame");
    let correction_tape = w
        .apply_velocity_correction(&correction)
        .expect("correction");
    assert!(
        correction_tape.clipped[0][2],
        "particle 0 must hit the clip"
    );
    let mut grads = probe.clone();
    let grad_dv = correction_tape.backward(&mut grads);
    let frame_grads = w.backward_frame(&tape, &grads).expect("backward");

    let mut run = |state: &Particles<f64>, dv: &[[f64; 3]]| {
        w.set_state(state).expect("state");
        w.step_frame(&FROM, &to, &[true, true]).expect("frame");
        w.apply_velocity_correction(dv).expect("correction");
        loss(&w.state(), &probe)
    };
    let analytic_dv: f64 = grad_dv.iter().zip(&direction).map(|(g, d)| g.dot(d)).sum();
    check("dv", analytic_dv, &mut |h| {
        let dv: Vec<[f64; 3]> = correction
            .iter()
            .zip(&direction)
            .map(|(c, d)| [0, 1, 2].map(|a| c[a] + h * d[a]))
            .collect();
        run(&start, &dv)
    });
    let analytic_x: f64 = frame_grads
        .state
        .x
        .iter()
        .zip(&direction)
        .map(|(g, d)| g.dot(d))
        .sum();
    check("x through frame and correction", analytic_x, &mut |h| {
        let mut s = start.clone();
        s.x.iter_mut()
            .zip(&direction)
            .for_each(|(x, d)| *x += d * h);
        run(&s, &correction)
    });
}

#[test]
fn non_finite_velocity_correction_is_refused() {
    let mut w = world();
    let mut dv = vec![[0.0; 3]; w.particle_count()];
    dv[3][1] = f64::NAN;
    let err = w
        .apply_velocity_correction(&dv)
        .expect_err("NaN must be refused");
    assert!(err.to_string().contains("particle 3"), "{err}");
    assert!(
        w.apply_velocity_correction(&dv[1..]).is_err(),
        "wrong length"
    );
}

/// Issue 6: the effect coefficients a fit learns (drag k₁, k₂ and the
/// viscosity η) through a whole frame, actuators coupled.
#[test]
fn frame_adjoint_of_effect_coefficients_matches_finite_differences() {
    let mut w = world();
    // dt η / (ρ dx²) ≈ 3 at 16³ (dx 3.1 cm, ρ 1000): the implicit viscous
    // solve dominates the nodes' inertia, as on the truth scenes.
    let base = dm_mpm::Effects {
        air_drag_linear: 0.5,
        air_drag_quadratic: 2.0,
        viscosity: 3000.0,
        ..dm_mpm::Effects::default()
    };
    w.set_effects(base.clone()).expect("effects");
    let start = w.state();
    let to = anchors_to();
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (probe, grads) = probed_frame(&mut w, &mut rng);
    // Each coefficient is probed along a direction as large as itself: the
    // loss moves ∝ dt |v| per unit of drag, so an absolute FD_STEP would sit
    // at the round-off floor of the O(1) loss; a relative step of 1e-6
    // keeps the truncation error O(h²) far below FD_RTOL.
    type Set = fn(&mut dm_mpm::Effects, f64);
    let coefficients: [(&str, f64, f64, Set); 3] = [
        (
            "air_drag_linear",
            grads.effects.air_drag_linear,
            base.air_drag_linear,
            |e, v| e.air_drag_linear = v,
        ),
        (
            "air_drag_quadratic",
            grads.effects.air_drag_quadratic,
            base.air_drag_quadratic,
            |e, v| e.air_drag_quadratic = v,
        ),
        (
            "viscosity",
            grads.effects.viscosity,
            base.viscosity,
            |e, v| e.viscosity = v,
        ),
    ];
    check_gravity(&mut w, &start, &to, &probe, grads.effects.gravity);
    // Through the viscous solve too: node masses set its cell volumes.
    check_mass(&mut w, &start, &to, &probe, &grads.mass, &mut rng);
    w.set_effects(base.clone()).expect("effects");
    for (name, analytic, value, set) in coefficients {
        assert!(analytic != 0.0, "{name}: the frame must depend on it");
        check(name, analytic * value, &mut |h| {
            let mut effects = base.clone();
            set(&mut effects, value * (1.0 + h));
            w.set_effects(effects).expect("effects");
            w.set_state(&start).expect("state");
            w.step_frame(&FROM, &to, &[true, true]).expect("frame");
            loss(&w.state(), &probe)
        });
    }
}

/// The particle damping rate through a whole frame: every substep scales
/// the gathered velocities by e^(−c dt), actuators coupled.
#[test]
fn frame_adjoint_of_the_particle_damping_rate_matches_finite_differences() {
    let rate = 20.0;
    let mut w = world_with(|config| config.particle_damping = rate);
    let start = w.state();
    let to = anchors_to();
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let (probe, grads) = probed_frame(&mut w, &mut rng);
    let analytic = grads.effects.particle_damping;
    assert!(analytic != 0.0, "the frame must depend on the damping");
    // A relative step, as for the effect coefficients above.
    check("particle_damping", analytic * rate, &mut |h| {
        w.set_particle_damping(rate * (1.0 + h)).expect("damping");
        w.set_state(&start).expect("state");
        w.step_frame(&FROM, &to, &[true, true]).expect("frame");
        loss(&w.state(), &probe)
    });
}

/// The floor plane of the friction frame: grid nodes at z ≤ 0.03 (row 4 of
/// 16, z = 0.025, inside the support of the lowest particles at z = 0.06)
/// are floor nodes.
const FRICTION_FLOOR_HEIGHT: f64 = 0.03;

/// Friction coefficient of the frame check: with the drift below most floor
/// nodes slide (|v_t| ≈ 0.45 m/s against μ |v_n| ≈ 0.1 m/s).
const FRICTION: f64 = 0.3;

/// Every particle's velocity at the taped frame's start gets this drift
/// (m/s): sideways and down, into the floor.
const FRICTION_DRIFT: [f64; 3] = [0.4, 0.2, -0.3];

/// Issue 6: floor friction μ through a whole frame (the substep checks in
/// `gradients_substep.rs` cover one grid update; this one covers the
/// frame's sum of μ̄ over its substeps, actuators coupled), and the state
/// adjoint through the sliding floor.
#[test]
fn frame_adjoint_of_floor_friction_matches_finite_differences() {
    let mut w = world_with(|config| {
        config.floor = Some(dm_mpm::FloorConfig {
            up: [0.0, 0.0, 1.0],
            height: FRICTION_FLOOR_HEIGHT,
            margin: 0.0,
        });
        config.effects.floor_friction = FRICTION;
    });
    let n = w.particle_count();
    let mut start = w.state();
    for v in &mut start.v {
        *v += Vec3::from(FRICTION_DRIFT);
    }
    w.set_state(&start).expect("state");
    let to = anchors_to();
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let (probe, grads) = probed_frame(&mut w, &mut rng);
    let analytic = grads.effects.floor_friction;
    assert!(
        analytic != 0.0,
        "floor nodes must slide for the frame to depend on μ"
    );
    let base = w.config().effects.clone();
    // A relative step, as for the other coefficients: μ = 0.3 moved by
    // 3e-7 keeps the O(1) loss's difference above round-off.
    check("floor_friction", analytic * FRICTION, &mut |h| {
        let mut effects = base.clone();
        effects.floor_friction = FRICTION * (1.0 + h);
        w.set_effects(effects).expect("effects");
        w.set_state(&start).expect("state");
        w.step_frame(&FROM, &to, &[true, true]).expect("frame");
        loss(&w.state(), &probe)
    });
    w.set_effects(base).expect("effects");
    let dv: Vec<Vec3<f64>> = (0..n).map(|_| rand_vec(&mut rng, 1.0)).collect();
    let analytic_v: f64 = grads.state.v.iter().zip(&dv).map(|(g, d)| g.dot(d)).sum();
    check("v through the floor", analytic_v, &mut |h| {
        let mut s = start.clone();
        s.v.iter_mut().zip(&dv).for_each(|(v, d)| *v += d * h);
        w.set_state(&s).expect("state");
        w.step_frame(&FROM, &to, &[true, true]).expect("frame");
        loss(&w.state(), &probe)
    });
}

/// ∂L/∂(anchor positions at the frame's start and end): through every
/// substep's interpolated anchor (spring) and the frame's anchor velocity
/// (damper), the full window. Directions of 1 cm per coordinate.
#[test]
fn frame_adjoint_of_the_hand_anchors_matches_finite_differences() {
    let mut w = world();
    let start = w.state();
    let to = anchors_to();
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (probe, grads) = probed_frame(&mut w, &mut rng);
    assert_eq!(grads.anchors_from.len(), 2);
    let direction: Vec<[f64; 3]> = (0..2)
        .map(|_| [0, 1, 2].map(|_| 0.01 * (2.0 * rng.random::<f64>() - 1.0)))
        .collect();
    let moved = |base: &[[f64; 3]], h: f64| -> Vec<[f64; 3]> {
        base.iter()
            .zip(&direction)
            .map(|(p, d)| [0, 1, 2].map(|a| p[a] + h * d[a]))
            .collect()
    };
    let along = |g: &[[f64; 3]]| -> f64 {
        g.iter()
            .zip(&direction)
            .map(|(g, d)| (0..3).map(|a| g[a] * d[a]).sum::<f64>())
            .sum()
    };
    let mut run = |from: &[[f64; 3]], to: &[[f64; 3]]| {
        w.set_state(&start).expect("state");
        w.step_frame(from, to, &[true, true]).expect("frame");
        loss(&w.state(), &probe)
    };
    check("anchors_to", along(&grads.anchors_to), &mut |h| {
        run(&FROM, &moved(&to, h))
    });
    check("anchors_from", along(&grads.anchors_from), &mut |h| {
        run(&moved(&FROM, h), &to)
    });
    assert!(
        along(&grads.anchors_to).abs() > 1e-6,
        "the hands must move the loss"
    );
}

/// The grid's body force a = a₀ − D v − κ (x − p) through a whole frame,
/// actuators coupled, without and with the viscous solve (its adjoint
/// takes the other path through the grid update's backward pass). Each
/// parameter group is probed along a direction as large as itself (the
/// uniform push and the point along fixed directions of their own scale),
/// as for the effect coefficients above.
#[test]
fn frame_adjoint_of_the_body_force_matches_finite_differences() {
    for viscosity in [0.0, 3000.0] {
        let field = dm_mpm::ForceField {
            uniform: [0.5, -0.3, 0.2],
            axis_drag: [2.0, 0.5, 4.0],
            attractor_stiffness: 50.0,
            attractor_point: [0.02, 0.01, 0.15],
        };
        let base = dm_mpm::Effects {
            air_drag_linear: 0.5,
            viscosity,
            force_field: field,
            ..dm_mpm::Effects::default()
        };
        let mut w = world();
        w.set_effects(base.clone()).expect("effects");
        let start = w.state();
        let to = anchors_to();
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        let (probe, grads) = probed_frame(&mut w, &mut rng);
        let g = grads.effects.force_field;
        assert_eq!(
            g.uniform, grads.effects.gravity,
            "a uniform push acts as gravity does"
        );
        let uniform_direction = [0.6, -0.8, 0.3];
        let point_direction = [0.03, -0.02, 0.04];
        type Perturb = fn(&mut dm_mpm::ForceField, &dm_mpm::ForceField, f64);
        let dot = |a: [f64; 3], b: [f64; 3]| (0..3).map(|i| a[i] * b[i]).sum::<f64>();
        let groups: [(&str, f64, Perturb); 4] = [
            ("uniform", dot(g.uniform, uniform_direction), |f, b, h| {
                f.uniform = std::array::from_fn(|a| b.uniform[a] + h * [0.6, -0.8, 0.3][a]);
            }),
            ("axis_drag", dot(g.axis_drag, field.axis_drag), |f, b, h| {
                f.axis_drag = b.axis_drag.map(|d| d * (1.0 + h));
            }),
            (
                "attractor_stiffness",
                g.attractor_stiffness * field.attractor_stiffness,
                |f, b, h| f.attractor_stiffness = b.attractor_stiffness * (1.0 + h),
            ),
            (
                "attractor_point",
                dot(g.attractor_point, point_direction),
                |f, b, h| {
                    f.attractor_point =
                        std::array::from_fn(|a| b.attractor_point[a] + h * [0.03, -0.02, 0.04][a]);
                },
            ),
        ];
        for (name, analytic, perturb) in groups {
            assert!(analytic != 0.0, "{name}: the frame must depend on it");
            check(&format!("{name} (η = {viscosity})"), analytic, &mut |h| {
                let mut effects = base.clone();
                perturb(&mut effects.force_field, &field, h);
                w.set_effects(effects).expect("effects");
                w.set_state(&start).expect("state");
                w.step_frame(&FROM, &to, &[true, true]).expect("frame");
                loss(&w.state(), &probe)
            });
        }
    }
}

/// A frame's last substeps taped from the state kept at their start
/// (`step_frame_keeping`, then `step_frame_rest_taped`, as a fit's
/// backward pass runs them) are the whole frame taped: the same state
/// after it and the same gradients, bit for bit, for a truncated window,
/// one as long as the frame, and one longer.
#[test]
fn the_rest_of_a_frame_taped_from_its_kept_state_is_the_whole_frame_taped() {
    let to = anchors_to();
    let substeps = world().config().substeps_per_frame;
    for window in [3, substeps, usize::MAX] {
        let mut whole = world();
        let tape = whole
            .step_frame_taped(&FROM, &to, &[true, true], window)
            .expect("taped frame");
        let after = whole.state();

        let mut rest = world();
        let kept = rest
            .step_frame_keeping(&FROM, &to, &[true, true], substeps - window.min(substeps))
            .expect("frame keeping a state");
        assert_eq!(
            rest.state(),
            after,
            "window {window}: keeping changed the frame"
        );
        rest.set_state(&kept).expect("state");
        let rest_tape = rest
            .step_frame_rest_taped(&FROM, &to, window)
            .expect("rest of the frame");
        assert_eq!(
            rest.state(),
            after,
            "window {window}: the rest ends elsewhere"
        );
        assert_eq!(rest_tape.len(), tape.len());

        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let probe = position_velocity_probe(&mut rng, whole.particle_count());
        let grads = whole.backward_frame(&tape, &probe).expect("backward");
        let rest_grads = rest.backward_frame(&rest_tape, &probe).expect("backward");
        assert_eq!(rest_grads, grads, "window {window}: gradients differ");
    }
}
