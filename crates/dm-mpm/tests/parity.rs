//! Determinism and parity: bitwise-identical results for any thread count,
//! f32 against f64, and the caller's particle order behind the internal
//! spatial sort.

mod common;

use common::{block_world, floor_config, jittered_lattice, rng, uniform};
use dm_mpm::real::{Mat3, Real};
use dm_mpm::{ActuatorConfig, MaterialBounds, MaterialPatches, PatchParams, World};

/// f32 vs f64 positions after a short rollout, m: f32 round-off on O(0.1) m
/// positions accumulated over 210 substeps (measured 3e-7).
const F32_F64_POSITION_TOL_M: f64 = 1e-5;
/// Same rollout, velocities in m/s (measured 3e-6 at ~1 m/s).
const F32_F64_VELOCITY_TOL: f64 = 1e-4;
/// f64 round-off from summing P2G contributions in another order.
const REORDER_POSITION_TOL_M: f64 = 1e-12;

/// Everything a frame can depend on: a MoCE material from patches with
/// random logits and E, random initial velocities, four anchors moving;
/// with `viscosity` > 0 the grid's implicit viscous solve too.
fn rich_scene<T: Real>(viscosity: f64) -> World<T> {
    let mut r = rng(31);
    let mut config = floor_config();
    config.effects.viscosity = viscosity;
    let h = config.dx() / 2.0;
    let positions = jittered_lattice(&mut r, [-0.1, -0.06, 0.0], [0.1, 0.06, 0.08], h, 0.25);
    let patches = MaterialPatches::build(&positions, 12);
    let bounds = MaterialBounds::VOLUMETRIC;
    let params = PatchParams {
        youngs_raw: (0..12).map(|_| uniform(&mut r, -4.0, 0.0)).collect(),
        poisson_raw: (0..12).map(|_| uniform(&mut r, -2.0, 2.0)).collect(),
        logits: (0..12)
            .map(|_| [0; 3].map(|_| uniform(&mut r, -2.0, 2.0)))
            .collect(),
    };
    let material = patches.particle_material::<T>(&params, &bounds);
    let mut world = World::new(
        config,
        &positions,
        h * h * h,
        material,
        ActuatorConfig::default(),
    )
    .expect("valid world");
    let v: Vec<[f64; 3]> = positions
        .iter()
        .map(|_| [0; 3].map(|_| uniform(&mut r, -0.3, 0.3)))
        .collect();
    world.set_velocities(&v).expect("sizes match");
    world
}

fn run_rich_scene<T: Real>(world: &mut World<T>, frames: usize) {
    let anchors = [
        [-0.08, 0.0, 0.09],
        [-0.06, 0.02, 0.09],
        [0.07, 0.0, 0.09],
        [0.05, -0.02, 0.09],
    ];
    for f in 0..frames {
        let at = |k: usize| -> Vec<[f64; 3]> {
            anchors
                .iter()
                .enumerate()
                .map(|(i, a)| {
                    let s = if i < 2 { -1.0 } else { 1.0 };
                    [a[0] + s * 0.004 * k as f64, a[1], a[2] + 0.006 * k as f64]
                })
                .collect()
        };
        world
            .step_frame(&at(f), &at(f + 1), &[true, true, true, f > 0])
            .unwrap_or_else(|err| panic!("frame {f}: {err}"));
    }
}

type Snapshot<T> = (Vec<[f64; 3]>, Vec<[f64; 3]>, Vec<Mat3<T>>);

fn in_pool<T: Real>(threads: usize, frames: usize, viscosity: f64) -> Snapshot<T> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    pool.install(|| {
        let mut world = rich_scene::<T>(viscosity);
        run_rich_scene(&mut world, frames);
        assert!(world.actuators().coupling_count() > 0, "anchors must grasp");
        (
            world.positions(),
            world.velocities(),
            world.deformation_gradients(),
        )
    })
}

fn assert_bitwise<T: Real>(a: &Snapshot<T>, b: &Snapshot<T>) {
    let bits = |v: &[[f64; 3]]| -> Vec<u64> { v.iter().flatten().map(|x| x.to_bits()).collect() };
    assert!(bits(&a.0) == bits(&b.0), "positions differ");
    assert!(bits(&a.1) == bits(&b.1), "velocities differ");
    let fbits = |v: &[Mat3<T>]| -> Vec<u64> {
        v.iter()
            .flat_map(|m| m.iter().map(|x| x.to_f64().to_bits()))
            .collect()
    };
    assert!(fbits(&a.2) == fbits(&b.2), "deformation gradients differ");
}

#[test]
fn one_and_two_threads_give_bitwise_identical_results() {
    // η = 500 Pa·s adds the viscous solve's conjugate-gradient sums.
    for viscosity in [0.0, 500.0] {
        let one = in_pool::<f32>(1, 4, viscosity);
        let two = in_pool::<f32>(2, 4, viscosity);
        assert_bitwise(&one, &two);
        // The scene must have moved (else equality is trivial).
        let moved = one.2.iter().any(|f| (f - Mat3::identity()).amax() > 1e-3);
        assert!(moved, "no deformation");
        let one = in_pool::<f64>(1, 2, viscosity);
        let three = in_pool::<f64>(3, 2, viscosity);
        assert_bitwise(&one, &three);
    }
}

#[test]
fn f32_and_f64_worlds_agree_over_a_short_rollout() {
    for viscosity in [0.0, 500.0] {
        f32_and_f64_agree(viscosity);
    }
}

fn f32_and_f64_agree(viscosity: f64) {
    let mut config = floor_config();
    config.effects.viscosity = viscosity;
    let h = config.dx() / 2.0;
    let mut r = rng(32);
    let positions = jittered_lattice(&mut r, [-0.08, -0.08, 0.02], [0.08, 0.08, 0.18], h, 0.25);
    let run = |f32_world: bool| -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
        macro_rules! go {
            ($t:ty) => {{
                let mut w: World<$t> = block_world(
                    config.clone(),
                    &positions,
                    2e5,
                    0.3,
                    [0.5, 0.3, 0.2],
                    ActuatorConfig::default(),
                );
                for _ in 0..5 {
                    w.step_frame_free().expect("stable");
                }
                (w.positions(), w.velocities())
            }};
        }
        if f32_world { go!(f32) } else { go!(f64) }
    };
    let (x32, v32) = run(true);
    let (x64, v64) = run(false);
    let max_diff = |a: &[[f64; 3]], b: &[[f64; 3]]| {
        a.iter()
            .flatten()
            .zip(b.iter().flatten())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max)
    };
    let dx = max_diff(&x32, &x64);
    let dv = max_diff(&v32, &v64);
    assert!(
        dx < F32_F64_POSITION_TOL_M,
        "η {viscosity}: positions differ by {dx:e} m"
    );
    assert!(
        dv < F32_F64_VELOCITY_TOL,
        "η {viscosity}: velocities differ by {dv:e} m/s"
    );
    // The rollout includes the impact: the bottom has hit the floor.
    let fell = x64.iter().zip(&positions).all(|(x, p)| x[2] < p[2]);
    assert!(fell, "the block should be falling");
}

#[test]
fn accessors_speak_in_the_callers_particle_order() {
    let config = floor_config();
    let h = config.dx() / 2.0;
    let mut r = rng(33);
    let positions = jittered_lattice(&mut r, [-0.05, -0.05, 0.02], [0.05, 0.05, 0.1], h, 0.25);
    let reversed: Vec<[f64; 3]> = positions.iter().rev().copied().collect();
    let make = |pts: &[[f64; 3]]| -> World<f64> {
        block_world(
            config.clone(),
            pts,
            1e5,
            0.3,
            [0.5, 0.3, 0.2],
            ActuatorConfig::default(),
        )
    };
    let (mut fwd, mut rev) = (make(&positions), make(&reversed));
    // Before any step, positions come back exactly as given.
    assert_eq!(fwd.positions(), positions);
    assert_eq!(rev.positions(), reversed);
    // Velocities are read back in the order they were set.
    let v: Vec<[f64; 3]> = (0..positions.len())
        .map(|i| [i as f64 * 1e-3, 0.0, -0.1])
        .collect();
    let v_rev: Vec<[f64; 3]> = v.iter().rev().copied().collect();
    fwd.set_velocities(&v).expect("sizes match");
    rev.set_velocities(&v_rev).expect("sizes match");
    assert_eq!(fwd.velocities(), v);
    for _ in 0..3 {
        fwd.step_frame_free().expect("stable");
        rev.step_frame_free().expect("stable");
    }
    let (xf, xr) = (fwd.positions(), rev.positions());
    let n = xf.len();
    for i in 0..n {
        for a in 0..3 {
            let d = (xf[i][a] - xr[n - 1 - i][a]).abs();
            assert!(d < REORDER_POSITION_TOL_M, "particle {i} axis {a}: {d:e}");
        }
    }
    let (ff, fr) = (fwd.deformation_gradients(), rev.deformation_gradients());
    assert!((ff[0] - fr[n - 1]).amax() < REORDER_POSITION_TOL_M * 1e3);
    // A material set in caller order lands on the right particles: stiffen
    // the first half only; the two halves then deform differently.
    let half = n / 2;
    let e: Vec<f64> = (0..n).map(|i| if i < half { 3e5 } else { 1e4 }).collect();
    let material =
        dm_mpm::ParticleMaterial::<f64>::from_fields(&e, &vec![0.3; n], &vec![[1.0, 0.0, 0.0]; n]);
    let e_rev: Vec<f64> = e.iter().rev().copied().collect();
    let material_rev = dm_mpm::ParticleMaterial::<f64>::from_fields(
        &e_rev,
        &vec![0.3; n],
        &vec![[1.0, 0.0, 0.0]; n],
    );
    fwd.set_material(material).expect("sizes match");
    rev.set_material(material_rev).expect("sizes match");
    for _ in 0..2 {
        fwd.step_frame_free().expect("stable");
        rev.step_frame_free().expect("stable");
    }
    let (xf, xr) = (fwd.positions(), rev.positions());
    for i in 0..n {
        for a in 0..3 {
            assert!((xf[i][a] - xr[n - 1 - i][a]).abs() < REORDER_POSITION_TOL_M);
        }
    }
}

/// P2G takes every particle's impulse from the SIMD pass
/// (`Impulses::compute`, several particles per register); each must be
/// bitwise what the scalar `particle_impulse` gives, whatever its
/// neighbours in the register: mixed weights (some experts zero in some
/// lanes only), a particle count that leaves a partial register, the
/// pure Neo-Hookean fast path, and the polar rotations the backward pass
/// reads.
#[test]
fn simd_impulses_equal_the_scalar_impulse_bitwise() {
    simd_impulses_equal_scalar::<f32>();
    simd_impulses_equal_scalar::<f64>();
}

fn simd_impulses_equal_scalar<T: Real>() {
    use dm_mpm::real::cast_mat;
    use dm_mpm::state::{Consts, Particles};
    use dm_mpm::stress::{ImpulseInputs, Impulses, particle_impulse};
    use dm_mpm::svd::polar_rotation;
    let mut r = rng(5);
    let n = 8 * 40 + 3;
    let config = floor_config();
    let k = Consts::<T>::new(&config, 1e-3);
    let positions: Vec<_> = (0..n)
        .map(|_| dm_mpm::real::vec3::<T>([0; 3].map(|_| uniform(&mut r, -0.05, 0.05))))
        .collect();
    let mut particles = Particles::at_rest(&positions, T::lit(1e-6), T::lit(1e3));
    for p in 0..n {
        particles.f[p] = cast_mat(&common::random_f(&mut r, 0.6, 1.6));
        particles.c[p] = cast_mat(&Mat3::<f64>::from_fn(|_, _| uniform(&mut r, -1.0, 1.0)));
        particles.v[p] = dm_mpm::real::vec3([0; 3].map(|_| uniform(&mut r, -0.3, 0.3)));
    }
    let youngs: Vec<f64> = (0..n).map(|_| uniform(&mut r, 1e4, 1e6)).collect();
    let poisson: Vec<f64> = (0..n).map(|_| uniform(&mut r, 0.1, 0.45)).collect();
    // Particle p weights the experts whose bits are set in p % 8.
    let weights: Vec<[f64; 3]> = (0..n)
        .map(|p| {
            [0, 1, 2].map(|e| {
                if (p % 8) >> e & 1 == 1 {
                    0.2 + 0.1 * e as f64
                } else {
                    0.0
                }
            })
        })
        .collect();
    for pure in [false, true] {
        let material = dm_mpm::ParticleMaterial::<T>::from_fields(&youngs, &poisson, &weights);
        let inputs = ImpulseInputs {
            particles: &particles,
            material: &material,
            pure_neo_hookean: pure,
            external_accel: None,
        };
        let mut impulses = Impulses::default();
        impulses.compute(&k, &inputs, true);
        for p in 0..n {
            let (a, q) = particle_impulse(&k, &inputs, p);
            assert_eq!(
                impulses.affine[p], a,
                "affine of particle {p}, pure NH {pure}"
            );
            assert_eq!(impulses.momentum[p], q, "momentum of particle {p}");
            if !pure {
                assert_eq!(
                    impulses.rotation[p],
                    polar_rotation(&particles.f[p]),
                    "rotation {p}"
                );
            }
        }
        assert_eq!(impulses.rotation.is_empty(), pure);
    }
}
