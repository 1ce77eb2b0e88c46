//! Validation scenarios: whole simulations checked against analytical or
//! physical expectations (conservation, free fall, resting contact,
//! actuator tracking, divergence reporting, plasticity, viscosity).

mod common;

use common::{
    FLOOR_GRID, block_world, bounds, floor_config, free_space_config, jittered_lattice, lattice,
    mean, rng, uniform,
};
use dm_mpm::scenes::{BenchExperts, bench_block};
use dm_mpm::{
    ActuatorConfig, ActuatorMode, Effects, ParticleMaterial, PhysicsConfig, SimError, World,
};

// ---------------------------------------------------------------- tolerances

/// f64 momentum: round-off of ~1e4 particles x 200 substeps (measured 4e-16).
const F64_MOMENTUM_RTOL: f64 = 1e-12;
/// f32 momentum: single-precision P2G/G2P sums accumulate (measured 5e-8).
const F32_MOMENTUM_RTOL: f64 = 1e-6;
/// Momentum the default empty-node cut drops over the run (measured 4e-7).
const EMPTY_NODE_CUT_MOMENTUM_RTOL: f64 = 1e-5;
/// f64 rigid translation: P2G/G2P carry a uniform velocity exactly, so one
/// frame's velocity ratio is the damping product up to round-off.
const F64_TRANSLATION_TOL: f64 = 1e-12;
/// f64 free fall vs the closed-form symplectic Euler trajectory.
const FREE_FALL_TOL_M: f64 = 1e-10;
/// A resting cube keeps far less than this share of the energy it gained
/// falling (damping 5/s over ~1.8 s leaves ~1e-8).
const REST_ENERGY_RATIO: f64 = 1e-6;
/// Node-based floor contact: the bottom particles rest up to ~1.5 cells
/// above the plane (the floor node is in their stencil only below that).
const FLOOR_GAP_CELLS: f64 = 1.5;
/// An elastic block returns to its rest length up to this strain.
const ELASTIC_RECOVERY_RTOL: f64 = 0.01;
/// A resting cube's particles move slower than this, m/s.
const REST_SPEED: f64 = 0.01;
/// The cube's extents may change this much (sag, bulge) without failing.
const SHAPE_RTOL: f64 = 0.3;
/// Mean displacement error of grasped particles vs their anchor, m: the
/// springs (kp = 3000 /s²) sag ~g/kp = 3 mm under the block's weight.
const GRASP_TRACK_TOL_M: f64 = 0.01;
/// f64 round-off on positions of O(0.1) m.
const RIGID_TOL_M: f64 = 1e-12;
/// Sliding distances vs Coulomb/inertial closed forms: the landing bounce
/// and one-cell contact layer perturb them slightly (measured < 1 %).
const SLIDE_RTOL: f64 = 0.05;
/// Explicit Euler on v' = g - k v vs the exact exponential (k dt = 0.016;
/// the per-step errors cancel towards terminal velocity, measured 6e-5).
const DRAG_RTOL: f64 = 1e-3;

/// A spinning block's late peak kinetic energy is the same with or without
/// viscosity up to this share: strain-rate damping must not see rotation
/// (measured 0.5571 vs 0.5571 of the start, 2e-4 apart; the soft block
/// itself turns part of its spin into centrifugal stretch).
const SPIN_ENERGY_RTOL: f64 = 0.01;
/// A stretched block at η = 2000 Pa·s (50× the explicit limit) keeps less
/// than this share of the peak kinetic energy the elastic one keeps
/// (measured 7e-4 vs 0.32 of the start).
const VISCOUS_PEAK_ENERGY_RATIO: f64 = 0.05;

const SUBSTEPS_PER_FRAME: usize = 42;

fn dx() -> f64 {
    1.0 / FLOOR_GRID as f64
}

// ---------------------------------------------------------------- conservation

/// No gravity, walls out of reach, no damping: APIC transfers and internal
/// stress forces conserve linear momentum exactly (up to round-off).
fn momentum_drift<T: dm_mpm::Real>(empty_node_mass_ratio: f64) -> f64 {
    let mut config = free_space_config();
    config.gravity = [0.0; 3];
    config.substeps_per_frame = 20;
    config.empty_node_mass_ratio = empty_node_mass_ratio;
    let mut r = rng(21);
    let h = dx() / 2.0;
    let positions = jittered_lattice(&mut r, [0.4; 3], [0.6; 3], h, 0.3);
    // A common drift plus random per-particle velocities: |v| < 0.3 m/s moves
    // at most 5 cm in 0.16 s, far from the walls 0.3 m away.
    let velocities: Vec<[f64; 3]> = positions
        .iter()
        .map(|_| [0.05, -0.03, 0.02].map(|d| d + uniform(&mut r, -0.1, 0.1)))
        .collect();
    let n = positions.len();
    let (e, nu) = (1e5, 0.3);
    let weights: Vec<[f64; 3]> = (0..n)
        .map(|_| {
            let w = [0; 3].map(|_| uniform(&mut r, 0.0, 1.0));
            let s: f64 = w.iter().sum();
            w.map(|x| x / s)
        })
        .collect();
    let material = ParticleMaterial::from_fields(&vec![e; n], &vec![nu; n], &weights);
    let mut world = World::<T>::new(
        config,
        &positions,
        h * h * h,
        material,
        ActuatorConfig::default(),
    )
    .expect("valid world");
    world.set_velocities(&velocities).expect("sizes match");
    let p0 = world.total_momentum();
    let scale: f64 = world
        .velocities()
        .iter()
        .map(|v| v.iter().map(|c| c.abs()).sum::<f64>())
        .sum::<f64>()
        * h.powi(3)
        * 1000.0;
    for _ in 0..10 {
        world.step_frame_free().expect("stable");
    }
    let p1 = world.total_momentum();
    let drift = (0..3).map(|a| (p1[a] - p0[a]).abs()).fold(0.0, f64::max);
    // The particles stayed far from the walls (no boundary forces).
    let (lo, hi) = bounds(&world.positions());
    assert!(lo.iter().all(|&c| c > 0.3) && hi.iter().all(|&c| c < 0.7));
    drift / scale
}

#[test]
fn momentum_is_conserved_without_gravity_and_walls() {
    let d64 = momentum_drift::<f64>(0.0);
    assert!(d64 < F64_MOMENTUM_RTOL, "f64 relative drift {d64:e}");
    let d32 = momentum_drift::<f32>(0.0);
    assert!(d32 < F32_MOMENTUM_RTOL, "f32 relative drift {d32:e}");
    // The default light-node cut zeroes nodes below 1e-4 particle masses,
    // dropping their (tiny) momentum every substep.
    let default_ratio =
        PhysicsConfig::volumetric([0.0; 3], 1.0, [0.0, 0.0, 1.0]).empty_node_mass_ratio;
    let d_cut = momentum_drift::<f64>(default_ratio);
    assert!(
        d_cut < EMPTY_NODE_CUT_MOMENTUM_RTOL,
        "f64 drift with the cut {d_cut:e}"
    );
}

#[test]
fn free_fall_follows_symplectic_euler_exactly() {
    // Uniform velocity: C = 0, F = I, no stress; each substep is
    // v += g dt; x += v dt, so z_n = z_0 - g dt² n(n+1)/2.
    let mut config = free_space_config();
    // Light nodes are kept: the default cut drags surface particles (~1e-5 m here).
    config.empty_node_mass_ratio = 0.0;
    let g = 9.8;
    let dt = config.dt;
    let positions = lattice([0.4, 0.4, 0.6], [0.5, 0.5, 0.7], dx() / 2.0);
    let mut world: World<f64> = block_world(
        config,
        &positions,
        1e5,
        0.3,
        [0.4, 0.3, 0.3],
        ActuatorConfig::default(),
    );
    let frames = 5;
    for _ in 0..frames {
        world.step_frame_free().expect("stable");
    }
    let n = (frames * SUBSTEPS_PER_FRAME) as f64;
    let drop = g * dt * dt * n * (n + 1.0) / 2.0;
    for (p0, p) in positions.iter().zip(world.positions()) {
        assert!(
            (p[2] - (p0[2] - drop)).abs() < FREE_FALL_TOL_M,
            "{p:?} vs {p0:?}"
        );
        assert!((p[0] - p0[0]).abs() < FREE_FALL_TOL_M && (p[1] - p0[1]).abs() < FREE_FALL_TOL_M);
    }
    for v in world.velocities() {
        assert!((v[2] + g * dt * n).abs() < FREE_FALL_TOL_M, "{v:?}");
    }
}

// ---------------------------------------------------------------- resting contact

#[test]
fn elastic_cube_dropped_on_the_floor_comes_to_rest() {
    let config = floor_config();
    let dx = dx();
    let edge = 12.0 * dx / 2.0; // 12 particles per axis
    let z0 = 0.1;
    let positions = lattice(
        [-edge / 2.0, -edge / 2.0, z0],
        [edge / 2.0, edge / 2.0, z0 + edge],
        dx / 2.0,
    );
    let (e, nu, density) = (2e5, 0.3, config.density);
    let mass = density * edge.powi(3);
    let mut world: World<f32> = block_world(
        config,
        &positions,
        e,
        nu,
        [0.5, 0.3, 0.2],
        ActuatorConfig::default(),
    );
    let com0 = mean(&positions)[2];
    for frame in 0..60 {
        world
            .step_frame_free()
            .unwrap_or_else(|err| panic!("frame {frame}: {err}"));
    }
    let x = world.positions();
    let (lo, hi) = bounds(&x);
    let com = mean(&x)[2];
    let energy_gained = mass * 9.8 * (com0 - com);
    assert!(
        com0 - com > z0 - FLOOR_GAP_CELLS * dx,
        "the cube fell: COM {com0} -> {com}"
    );
    let ke = world.kinetic_energy();
    assert!(
        ke < REST_ENERGY_RATIO * energy_gained,
        "KE {ke:e} J of {energy_gained:e} J"
    );
    let max_speed = world
        .velocities()
        .iter()
        .map(|v| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt())
        .fold(0.0, f64::max);
    assert!(max_speed < REST_SPEED, "max speed {max_speed}");
    assert!(lo[2] > -dx, "a particle sank through the floor: {}", lo[2]);
    assert!(lo[2] < FLOOR_GAP_CELLS * dx, "the cube hovers at {}", lo[2]);
    for a in 0..3 {
        let extent = hi[a] - lo[a];
        let initial = edge - dx / 2.0;
        assert!(
            (extent / initial - 1.0).abs() < SHAPE_RTOL,
            "axis {a}: extent {extent} vs {initial}"
        );
    }
    // Resting on its bottom layer: centre of mass half the (sagged) height up.
    let rest_com = lo[2] + (edge - dx / 2.0) / 2.0;
    assert!(
        (com - rest_com).abs() < SHAPE_RTOL * edge / 2.0,
        "COM height {com}"
    );
}

/// Centre-of-mass x travel of a small block launched along the floor at
/// `v0` m/s, after `frames` frames (no damping).
fn slide_distance(friction: f64, v0: f64, frames: usize) -> f64 {
    let mut config = floor_config();
    config.particle_damping = 0.0;
    config.grid_damping = 1.0;
    config.effects.floor_friction = friction;
    let h = dx() / 2.0;
    let positions = lattice([-0.35, -0.05, 0.0], [-0.25, 0.05, 4.0 * h], h);
    let mut world: World<f32> = block_world(
        config,
        &positions,
        1e5,
        0.3,
        [1.0, 0.0, 0.0],
        ActuatorConfig::default(),
    );
    world
        .set_velocities(&vec![[v0, 0.0, 0.0]; positions.len()])
        .expect("sizes match");
    for _ in 0..frames {
        world.step_frame_free().expect("stable");
    }
    mean(&world.positions())[0] - mean(&positions)[0]
}

#[test]
fn floor_friction_stops_a_sliding_block_at_the_coulomb_distance() {
    let (v0, mu, g) = (1.0, 0.5, 9.8);
    let frames = 15; // 0.5 s: the block stops after v0 / (mu g) = 0.2 s
    let t = frames as f64 * SUBSTEPS_PER_FRAME as f64 * 8e-4;
    let free = slide_distance(0.0, v0, frames);
    let rough = slide_distance(mu, v0, frames);
    assert!(
        (free / (v0 * t) - 1.0).abs() < SLIDE_RTOL,
        "frictionless slide {free}"
    );
    let coulomb = v0 * v0 / (2.0 * mu * g);
    assert!(
        (rough / coulomb - 1.0).abs() < SLIDE_RTOL,
        "slide {rough} vs {coulomb}"
    );
}

#[test]
fn linear_air_drag_approaches_terminal_velocity() {
    let mut config = free_space_config();
    config.empty_node_mass_ratio = 0.0;
    let k = 20.0;
    config.effects.air_drag_linear = k;
    let positions = lattice([0.45, 0.45, 0.6], [0.55, 0.55, 0.7], dx() / 2.0);
    let mut world: World<f64> = block_world(
        config,
        &positions,
        1e5,
        0.3,
        [1.0, 0.0, 0.0],
        ActuatorConfig::default(),
    );
    let frames = 10;
    for _ in 0..frames {
        world.step_frame_free().expect("stable");
    }
    let t = frames as f64 * SUBSTEPS_PER_FRAME as f64 * 8e-4;
    let want = -(9.8 / k) * (1.0 - (-k * t).exp());
    let v = world.velocities();
    for vp in &v {
        assert!(
            (vp[2] / want - 1.0).abs() < DRAG_RTOL,
            "v_z {} vs {want}",
            vp[2]
        );
        assert!(vp[0].abs() < FREE_FALL_TOL_M && vp[1].abs() < FREE_FALL_TOL_M);
    }
}

// ---------------------------------------------------------------- actuators

/// A soft block lying on the floor, 16 x 8 x 4 particles (25 x 12.5 x 6 cm).
fn soft_block() -> Vec<[f64; 3]> {
    let h = dx() / 2.0;
    lattice([-8.0 * h, -4.0 * h, 0.0], [8.0 * h, 4.0 * h, 4.0 * h], h)
}

fn grasp_config(mode: ActuatorMode) -> ActuatorConfig {
    ActuatorConfig {
        mode,
        ..ActuatorConfig::default()
    }
}

/// Anchor positions of one frame of a linear lift by `lift` over `frames`.
fn lifted(anchors: &[[f64; 3]], lift: f64, frame: usize, frames: usize) -> Vec<[f64; 3]> {
    let t = (frame as f64 / frames as f64).min(1.0);
    anchors
        .iter()
        .map(|a| [a[0], a[1], a[2] + lift * t])
        .collect()
}

fn within(p: &[f64; 3], a: &[f64; 3], r: f64) -> bool {
    (0..3).map(|i| (p[i] - a[i]).powi(2)).sum::<f64>() <= r * r
}

#[test]
fn grasped_patch_follows_a_moving_anchor() {
    let positions = soft_block();
    let top = positions.iter().map(|p| p[2]).fold(f64::MIN, f64::max);
    let x_min = positions.iter().map(|p| p[0]).fold(f64::MAX, f64::min);
    // A "hand" of four anchors around one end of the block.
    let (cx, z) = (x_min + 0.035, top + 0.005);
    let anchors = vec![
        [cx - 0.015, -0.015, z],
        [cx + 0.015, -0.015, z],
        [cx - 0.015, 0.015, z],
        [cx + 0.015, 0.015, z],
    ];
    // Stiffer than the default gains: the grasped ~10 % of the block
    // carries a third of its weight, a lag of ~(1/3)/(10 %) g / kp = 3 mm.
    let config = ActuatorConfig {
        kp: 1e4,
        kd: 200.0,
        ..grasp_config(ActuatorMode::Distributed)
    };
    let mut world: World<f32> = block_world(
        floor_config(),
        &positions,
        5e4,
        0.3,
        [1.0, 0.0, 0.0],
        config,
    );
    let (lift, frames) = (0.05, 30);
    for f in 0..frames {
        let from = lifted(&anchors, lift, f, frames);
        let to = lifted(&anchors, lift, f + 1, frames);
        world
            .step_frame(&from, &to, &[true; 4])
            .unwrap_or_else(|err| panic!("frame {f}: {err}"));
    }
    // Hold still for a few frames so the springs settle.
    let end = lifted(&anchors, lift, frames, frames);
    for _ in 0..5 {
        world.step_frame(&end, &end, &[true; 4]).expect("stable");
    }
    let grasped: Vec<usize> = (0..positions.len())
        .filter(|&i| {
            anchors
                .iter()
                .any(|a| within(&positions[i], a, config.grasp_radius))
        })
        .collect();
    assert!(
        grasped.len() >= 5,
        "only {} particles grasped",
        grasped.len()
    );
    assert_eq!(world.actuators().coupled_particle_count(), grasped.len());
    let x = world.positions();
    let mean_disp = |ids: &[usize], a: usize| {
        ids.iter().map(|&i| x[i][a] - positions[i][a]).sum::<f64>() / ids.len() as f64
    };
    for a in 0..3 {
        let want = if a == 2 { lift } else { 0.0 };
        let got = mean_disp(&grasped, a);
        assert!(
            (got - want).abs() < GRASP_TRACK_TOL_M,
            "axis {a}: {got} vs {want}"
        );
    }
    // The far end of the block lifts much less (it bends and pivots).
    let far: Vec<usize> = (0..positions.len())
        .filter(|&i| positions[i][0] > -x_min - 0.04)
        .collect();
    let far_lift = mean_disp(&far, 2);
    assert!(far_lift < 0.2 * lift, "far side lifted {far_lift}");
}

#[test]
fn rigid_actuators_pin_particles_to_their_anchors() {
    let positions = soft_block();
    let top = positions.iter().map(|p| p[2]).fold(f64::MIN, f64::max);
    let anchors = vec![[-0.05, 0.0, top + 0.005]];
    let config = grasp_config(ActuatorMode::Rigid);
    let mut world: World<f64> = block_world(
        floor_config(),
        &positions,
        5e4,
        0.3,
        [1.0, 0.0, 0.0],
        config,
    );
    let grasped: Vec<usize> = (0..positions.len())
        .filter(|&i| within(&positions[i], &anchors[0], config.grasp_radius))
        .collect();
    assert!(!grasped.is_empty());
    let (lift, frames) = (0.05, 6);
    for f in 0..frames {
        let from = lifted(&anchors, lift, f, frames);
        let to = lifted(&anchors, lift, f + 1, frames);
        world.step_frame(&from, &to, &[true]).expect("stable");
        // x_p = anchor - o_p, o_p = anchor_0 - x_p^0 captured at grasp.
        let x = world.positions();
        let v = world.velocities();
        let shift = to[0][2] - anchors[0][2];
        for &i in &grasped {
            let want = [positions[i][0], positions[i][1], positions[i][2] + shift];
            for a in 0..3 {
                assert!(
                    (x[i][a] - want[a]).abs() < RIGID_TOL_M,
                    "frame {f}: {:?} vs {want:?}",
                    x[i]
                );
            }
            let speed = lift / frames as f64 / (SUBSTEPS_PER_FRAME as f64 * 8e-4);
            assert!((v[i][2] - speed).abs() < RIGID_TOL_M && v[i][0] == 0.0);
        }
    }
}

#[test]
fn single_mode_keeps_one_anchor_per_particle() {
    let positions = soft_block();
    let top = positions.iter().map(|p| p[2]).fold(f64::MIN, f64::max);
    // Two anchors 2 cm apart with 3 cm grasp balls: their patches overlap.
    let anchors = vec![[-0.02, 0.0, top + 0.005], [0.0, 0.0, top + 0.005]];
    let couplings_per_particle = |mode| {
        let mut world: World<f32> = block_world(
            floor_config(),
            &positions,
            5e4,
            0.3,
            [1.0, 0.0, 0.0],
            grasp_config(mode),
        );
        for f in 0..2 {
            let from = lifted(&anchors, 0.01, f, 2);
            let to = lifted(&anchors, 0.01, f + 1, 2);
            world.step_frame(&from, &to, &[true, true]).expect("stable");
        }
        let act = world.actuators();
        let counts: Vec<usize> = (0..positions.len())
            .map(|p| act.couplings_of(p).count())
            .collect();
        // Single keeps the nearest anchor: |offset| is the capture distance.
        if mode == ActuatorMode::Single {
            for p in 0..positions.len() {
                for (a, o) in act.couplings_of(p) {
                    let x0 = [0, 1, 2].map(|i| anchors[a][i] - f64::from(o[i]));
                    let d = |b: usize| (0..3).map(|i| (x0[i] - anchors[b][i]).powi(2)).sum::<f64>();
                    assert!(
                        d(a) <= d(1 - a) + 1e-9,
                        "particle {p} kept the farther anchor"
                    );
                }
            }
        }
        counts
    };
    let single = couplings_per_particle(ActuatorMode::Single);
    let distributed = couplings_per_particle(ActuatorMode::Distributed);
    assert!(single.iter().all(|&c| c <= 1));
    assert!(distributed.contains(&2), "anchors must share particles");
    // Both modes tie the same particles.
    for (s, d) in single.iter().zip(&distributed) {
        assert_eq!(*s == 1, *d >= 1);
    }
}

#[test]
fn dropping_a_grasping_anchor_is_an_error_not_a_panic() {
    let positions = soft_block();
    let top = positions.iter().map(|p| p[2]).fold(f64::MIN, f64::max);
    let anchors = vec![[0.0, 0.0, top + 0.005]];
    let mut world: World<f32> = block_world(
        floor_config(),
        &positions,
        5e4,
        0.3,
        [1.0, 0.0, 0.0],
        ActuatorConfig::default(),
    );
    world
        .step_frame(&anchors, &anchors, &[true])
        .expect("stable");
    assert!(world.actuators().coupling_count() > 0);
    assert!(matches!(
        world.step_frame_free(),
        Err(SimError::InvalidInput(_))
    ));
    // Inactive anchors still count: they keep their particles.
    world
        .step_frame(&anchors, &anchors, &[false])
        .expect("anchor present");
}

// ---------------------------------------------------------------- divergence

#[test]
fn a_diverging_configuration_reports_an_error() {
    let mut config = floor_config();
    config.dt = 1e-2;
    config.substeps_per_frame = 4;
    config.particle_damping = 0.0;
    // A fixed, far too long step: what divergence detection is for.
    config.cfl = None;
    let positions = soft_block();
    let mut world: World<f32> = block_world(
        config,
        &positions,
        1e12,
        0.3,
        [0.5, 0.3, 0.2],
        ActuatorConfig::default(),
    );
    let mut r = rng(22);
    let v: Vec<[f64; 3]> = positions
        .iter()
        .map(|_| [0; 3].map(|_| uniform(&mut r, -0.5, 0.5)))
        .collect();
    world.set_velocities(&v).expect("sizes match");
    let mut outcome = Ok(());
    for _ in 0..50 {
        outcome = world.step_frame_free();
        if outcome.is_err() {
            break;
        }
    }
    match outcome {
        Err(SimError::Diverged {
            frame,
            substep,
            particle,
            ..
        }) => {
            assert!(frame < 50 && substep < 4 && particle < positions.len());
        }
        other => panic!("expected Diverged, got {other:?}"),
    }
}

// ---------------------------------------------------------------- plasticity

/// A soft 0.2 × 0.1 × 0.1 m block (E = 5 kPa) centred in the unit cube,
/// started with the velocity field `v0`: the world, its particles'
/// positions and initial velocities.
fn soft_block_in_motion<T: dm_mpm::Real>(
    config: PhysicsConfig,
    v0: impl Fn(&[f64; 3]) -> [f64; 3],
) -> (World<T>, Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let h = dx() / 2.0;
    let positions = lattice([0.4, 0.45, 0.45], [0.6, 0.55, 0.55], h);
    let mut world: World<T> = block_world(
        config,
        &positions,
        5e3,
        0.3,
        [1.0, 0.0, 0.0],
        ActuatorConfig::default(),
    );
    let v: Vec<[f64; 3]> = positions.iter().map(v0).collect();
    world.set_velocities(&v).expect("sizes match");
    (world, positions, v)
}

/// x-extent of a free block stretched by an initial velocity field, after
/// it settled (relative to its initial extent).
fn extent_after_stretch(plastic_yield: Option<f64>) -> f64 {
    let mut config = free_space_config();
    config.gravity = [0.0; 3];
    config.grid_damping = 0.999; // as before: only particle damping was set here
    config.particle_damping = 10.0;
    config.effects = Effects {
        plastic_yield,
        ..Effects::default()
    };
    // v_x = 5 (x - 0.5): a fast stretch along x.
    let (mut world, positions, _) =
        soft_block_in_motion::<f32>(config, |p| [5.0 * (p[0] - 0.5), 0.0, 0.0]);
    let initial = {
        let (lo, hi) = bounds(&positions);
        hi[0] - lo[0]
    };
    for _ in 0..30 {
        world.step_frame_free().expect("stable");
    }
    let (lo, hi) = bounds(&world.positions());
    (hi[0] - lo[0]) / initial
}

#[test]
fn plasticity_keeps_deformation_that_elasticity_recovers() {
    // The stretch peaks at roughly 20 % strain; yield y keeps about
    // (peak - y) of it, so a lower yield keeps more.
    let elastic = extent_after_stretch(None);
    let soft_yield = extent_after_stretch(Some(0.02));
    let hard_yield = extent_after_stretch(Some(0.05));
    assert!(
        (elastic - 1.0).abs() < ELASTIC_RECOVERY_RTOL,
        "elastic block ends at {elastic}"
    );
    assert!(
        hard_yield > elastic + 0.03,
        "yield 0.05 block ends at {hard_yield}"
    );
    assert!(
        soft_yield > hard_yield + 0.03,
        "yield 0.02 block ends at {soft_yield}"
    );
}

// ---------------------------------------------------------------- viscosity

/// A free block (no gravity, no damping) started with the velocity field
/// `v0`: its peak kinetic energy over frames 15–30, relative to the start.
fn late_peak_kinetic_energy(viscosity: f64, v0: impl Fn(&[f64; 3]) -> [f64; 3]) -> f64 {
    let mut config = free_space_config();
    config.gravity = [0.0; 3];
    config.effects.viscosity = viscosity;
    let (mut world, _, v) = soft_block_in_motion::<f64>(config, v0);
    // Equal particle masses: Σ|v|² is the kinetic energy up to a factor.
    let energy = |v: &[[f64; 3]]| {
        v.iter()
            .map(|v| v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
            .sum::<f64>()
    };
    let initial = energy(&v);
    let mut peak = 0.0_f64;
    for frame in 0..30 {
        world.step_frame_free().expect("stable");
        if frame >= 15 {
            peak = peak.max(energy(&world.velocities()));
        }
    }
    peak / initial
}

#[test]
fn implicit_viscosity_damps_deformation_but_not_rigid_spin() {
    // The elastic block's stretch oscillates (period ≈ 2L/c ≈ 6 frames);
    // at η = 2000 Pa·s (dt η/(ρ dx²) ≈ 0.3 per substep, 50× what explicit
    // viscous stress could take) the motion is overdamped within a frame.
    let stretch = |p: &[f64; 3]| [5.0 * (p[0] - 0.5), 0.0, 0.0];
    let elastic = late_peak_kinetic_energy(0.0, stretch);
    let viscous = late_peak_kinetic_energy(2000.0, stretch);
    assert!(
        viscous < VISCOUS_PEAK_ENERGY_RATIO * elastic,
        "stretch: peak kinetic energy {viscous} (viscous) vs {elastic} (elastic)"
    );
    // A rigid spin about x through the block's centre has no strain rate.
    let spin = |p: &[f64; 3]| [0.0, -2.0 * (p[2] - 0.5), 2.0 * (p[1] - 0.5)];
    let elastic = late_peak_kinetic_energy(0.0, spin);
    let viscous = late_peak_kinetic_energy(2000.0, spin);
    assert!(
        (viscous - elastic).abs() < SPIN_ENERGY_RTOL * elastic,
        "spin: peak kinetic energy {viscous} (viscous) vs {elastic} (elastic)"
    );
}

// ---------------------------------------------------------------- scenes

#[test]
fn bench_block_runs() {
    for experts in [BenchExperts::NeoHookean, BenchExperts::Mixture] {
        let mut world = bench_block::<f32>(5000, 32, experts, 7).expect("valid scene");
        assert_eq!(world.particle_count(), 5000);
        for _ in 0..50 {
            world.substep().expect("stable");
        }
        assert!(world.positions().iter().flatten().all(|c| c.is_finite()));
    }
}

#[test]
fn a_material_too_stiff_for_the_grid_is_refused_not_run_forever() {
    let config = floor_config();
    let positions = soft_block();
    let material = ParticleMaterial::<f32>::uniform(positions.len(), 1e14, 0.3, [1.0, 0.0, 0.0]);
    let result = World::new(
        config,
        &positions,
        1e-6,
        material,
        ActuatorConfig::default(),
    );
    assert!(
        matches!(&result, Err(SimError::InvalidConfig { field, .. }) if field == "dt"),
        "{result:?}"
    );
}

/// Grid damping keeps its rate per second when the CFL bound refines the
/// substep (regression: 0.999 per refined substep
/// damped the toy's model at its true E at 4.3 /s instead of 1.25 /s, so
/// changing E changed the damping).
/// A rigid translation carries no stress, so after one frame its velocity
/// is v₀ times the frame's damping alone, whatever the material.
#[test]
fn grid_damping_per_second_does_not_depend_on_stiffness() {
    let mut config = free_space_config();
    config.gravity = [0.0; 3];
    config.grid_damping = 0.999;
    let nominal_substeps = config.substeps_per_frame;
    let frame_damping = |youngs: f64| -> (usize, f64) {
        let h = dx() / 2.0;
        let positions = lattice([0.4, 0.45, 0.45], [0.6, 0.55, 0.55], h);
        let mut world: World<f64> = block_world(
            config.clone(),
            &positions,
            youngs,
            0.3,
            [1.0, 0.0, 0.0],
            ActuatorConfig::default(),
        );
        world
            .set_velocities(&vec![[0.2, 0.0, 0.0]; positions.len()])
            .expect("sizes match");
        world.step_frame_free().expect("stable");
        let vx = mean(&world.velocities())[0];
        (world.config().substeps_per_frame, vx / 0.2)
    };
    let expected = 0.999f64.powi(nominal_substeps as i32);
    let (soft_substeps, soft) = frame_damping(5e3);
    let (stiff_substeps, stiff) = frame_damping(5e7);
    assert_eq!(
        soft_substeps, nominal_substeps,
        "the soft block is not refined"
    );
    assert!(
        stiff_substeps > 2 * nominal_substeps,
        "the stiff block must be refined for this test ({stiff_substeps} substeps)"
    );
    for (name, got) in [("soft", soft), ("stiff", stiff)] {
        assert!(
            (got - expected).abs() < F64_TRANSLATION_TOL,
            "{name}: one frame kept {got} of the velocity, expected {expected}"
        );
    }
}
