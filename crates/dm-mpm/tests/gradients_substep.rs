//! Issue 3: the adjoint of a whole MPM substep (stress → P2G → grid update
//! → G2P) against central finite differences in f64, for every input it
//! reads: x, v, F, C, μ, λ, expert weights and the external acceleration
//! (with air drag and viscous damping on), and the effect parameters
//! k₁, k₂ (drag) and η (viscosity); and with a floor under the particles,
//! sliding and sticking under Coulomb friction, with the friction
//! coefficient's own adjoint.

use dm_mpm::PhysicsConfig;
use dm_mpm::config::FloorConfig;
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::material::ParticleMaterial;
use dm_mpm::real::{Mat3, Vec3};
use dm_mpm::state::{Consts, Particles};
use dm_mpm::substep::{SubstepInputs, SubstepScratch, substep_backward, substep_forward};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Central differences with h = 1e-6 on O(1)-scaled directional
/// derivatives: truncation O(h²) ≈ 1e-12 and round-off ≈ 1e-16/h ≈ 1e-10,
/// so 1e-5 (the bound) leaves a wide margin for a correct adjoint
/// and is still far below what a wrong term produces (≥ 1e-2).
const FD_RTOL: f64 = 1e-5;
const FD_STEP: f64 = 1e-6;

fn uniform(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * rng.random::<f64>()
}

fn rand_vec(rng: &mut ChaCha8Rng, s: f64) -> Vec3<f64> {
    Vec3::new(
        uniform(rng, -s, s),
        uniform(rng, -s, s),
        uniform(rng, -s, s),
    )
}

fn rand_mat(rng: &mut ChaCha8Rng, s: f64) -> Mat3<f64> {
    Mat3::from_fn(|_, _| uniform(rng, -s, s))
}

struct Scene {
    consts: Consts<f64>,
    particles: Particles<f64>,
    material: ParticleMaterial<f64>,
    external_accel: Vec<Vec3<f64>>,
    pure_neo_hookean: bool,
}

/// A floor under the particles' lower grid nodes, its friction μ, and
/// whether the grid's viscous solve runs (the grid update's adjoint has a
/// path with it and one without).
#[derive(Clone, Copy)]
struct FloorCase {
    friction: f64,
    viscous: bool,
}

/// The floor case's plane: nodes at z ≤ 0.47 (grid rows 6 and 7 of 16,
/// which the lowest particles at z ≈ 0.43 reach) are floor nodes.
const FLOOR_HEIGHT: f64 = 0.47;

/// With a floor, every particle moves down and sideways, (0.8, 0.3, −0.4)
/// m/s plus 0.1 m/s noise, so most floor nodes move into the floor with
/// |v_t| ≈ 0.85 and v_n ≈ −0.4: μ = 0.5 makes most of them slide
/// (|v_t| > −μ v_n ≈ 0.2) and μ = 5 most of them stick. Light nodes, whose
/// velocity the elastic force dominates, can take the other branch: the
/// checks pass through both (dropping the sliding adjoint's curvature term
/// fails the μ = 5 case too). A node within FD_STEP of the switch would
/// break the check; these seeds have none.
const FLOOR_DRIFT: [f64; 3] = [0.8, 0.3, -0.4];

fn scene(seed: u64, pure_neo_hookean: bool) -> Scene {
    scene_with(seed, pure_neo_hookean, None)
}

fn scene_with(seed: u64, pure_neo_hookean: bool, floor: Option<FloorCase>) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut config = PhysicsConfig::volumetric([0.0; 3], 1.0, [0.0, 0.0, 1.0]);
    config.grid_res = 16;
    config.dt = 1e-3;
    config.floor = floor.map(|_| FloorConfig {
        up: [0.0, 0.0, 1.0],
        height: FLOOR_HEIGHT,
        margin: 0.0,
    });
    config.effects.floor_friction = floor.map_or(0.0, |f| f.friction);
    // Exactly continuous in the state: no node may cross the emptiness cut.
    config.empty_node_mass_ratio = 0.0;
    config.effects.air_drag_linear = 0.7;
    config.effects.air_drag_quadratic = 0.4;
    // Viscous damping, solved implicitly on the grid: with the
    // particles' density ρ = 1, dt η / (ρ dx²) ≈ 5, so the viscous term
    // outweighs the nodes' mass and a wrong term in its adjoint (the
    // solve, its mass dependence) moves every gradient beyond FD_RTOL.
    config.density = 1.0;
    config.effects.viscosity = if floor.is_none_or(|f| f.viscous) {
        20.0
    } else {
        0.0
    };
    let n = 60;
    let x: Vec<Vec3<f64>> = (0..n)
        .map(|_| Vec3::new(0.5, 0.5, 0.5) + rand_vec(&mut rng, 0.07))
        .collect();
    let mut particles = Particles::at_rest(&x, 1e-4, 1.0);
    let drift = match floor {
        Some(_) => Vec3::from(FLOOR_DRIFT),
        None => Vec3::zeros(),
    };
    for p in 0..n {
        particles.v[p] = drift + rand_vec(&mut rng, if floor.is_some() { 0.1 } else { 0.3 });
        particles.c[p] = rand_mat(&mut rng, 0.5);
        particles.f[p] = Mat3::identity() + rand_mat(&mut rng, 0.08);
    }
    let weights: Vec<[f64; 3]> = (0..n)
        .map(|_| {
            if pure_neo_hookean {
                [1.0, 0.0, 0.0]
            } else {
                let w = [
                    0.2 + rng.random::<f64>(),
                    0.2 + rng.random::<f64>(),
                    0.2 + rng.random::<f64>(),
                ];
                let s = w[0] + w[1] + w[2];
                w.map(|v| v / s)
            }
        })
        .collect();
    let youngs: Vec<f64> = (0..n).map(|_| uniform(&mut rng, 500.0, 1500.0)).collect();
    let poisson: Vec<f64> = (0..n).map(|_| uniform(&mut rng, 0.1, 0.4)).collect();
    let material = ParticleMaterial::from_fields(&youngs, &poisson, &weights);
    let external_accel = (0..n).map(|_| rand_vec(&mut rng, 2.0)).collect();
    Scene {
        consts: Consts::new(&config, 1e-4),
        particles,
        material,
        external_accel,
        pure_neo_hookean,
    }
}

/// Random linear functional of the substep's output.
struct Probe {
    out: ParticleGrads<f64>,
}

impl Probe {
    fn new(n: usize, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut out = ParticleGrads::zeros(n);
        for p in 0..n {
            out.x[p] = rand_vec(&mut rng, 1.0);
            out.v[p] = rand_vec(&mut rng, 1.0);
            out.f[p] = rand_mat(&mut rng, 1.0);
            out.c[p] = rand_mat(&mut rng, 0.01);
        }
        Self { out }
    }

    fn loss(&self, s: &Scene) -> f64 {
        let mut particles = s.particles.clone();
        let inputs = SubstepInputs {
            material: &s.material,
            pure_neo_hookean: s.pure_neo_hookean,
            external_accel: Some(&s.external_accel),
        };
        let mut scratch = SubstepScratch::new(s.consts.res);
        substep_forward(&s.consts, &inputs, &mut particles, &mut scratch, None)
            .expect("substep stays valid");
        (0..particles.len())
            .map(|p| {
                self.out.x[p].dot(&particles.x[p])
                    + self.out.v[p].dot(&particles.v[p])
                    + self.out.f[p].component_mul(&particles.f[p]).sum()
                    + self.out.c[p].component_mul(&particles.c[p]).sum()
            })
            .sum()
    }
}

/// Compares the adjoint with central differences along one random
/// direction of one input group.
fn check(name: &str, s: &Scene, probe: &Probe, analytic: f64, perturb: &dyn Fn(&mut Scene, f64)) {
    let shifted = |h: f64| {
        let mut t = Scene {
            consts: s.consts,
            particles: s.particles.clone(),
            material: s.material.clone(),
            external_accel: s.external_accel.clone(),
            pure_neo_hookean: s.pure_neo_hookean,
        };
        perturb(&mut t, h);
        probe.loss(&t)
    };
    let numeric = (shifted(FD_STEP) - shifted(-FD_STEP)) / (2.0 * FD_STEP);
    let rel = (analytic - numeric).abs() / analytic.abs().max(numeric.abs()).max(1e-8);
    assert!(
        rel <= FD_RTOL,
        "{name}: adjoint {analytic:.10e} vs finite differences {numeric:.10e} (relative error {rel:.2e})"
    );
}

fn check_all_inputs(seed: u64, pure_neo_hookean: bool) {
    check_scene(seed, scene(seed, pure_neo_hookean));
}

fn check_scene(seed: u64, s: Scene) {
    let pure_neo_hookean = s.pure_neo_hookean;
    let n = s.particles.len();
    let probe = Probe::new(n, seed + 100);
    let inputs = SubstepInputs {
        material: &s.material,
        pure_neo_hookean: s.pure_neo_hookean,
        external_accel: Some(&s.external_accel),
    };
    let mut scratch = SubstepScratch::new(s.consts.res);
    let grads = substep_backward(&s.consts, &inputs, &s.particles, &probe.out, &mut scratch)
        .expect("backward");
    let mut rng = ChaCha8Rng::seed_from_u64(seed + 200);
    let dx: Vec<Vec3<f64>> = (0..n).map(|_| rand_vec(&mut rng, 1.0)).collect();
    let dv: Vec<Vec3<f64>> = (0..n).map(|_| rand_vec(&mut rng, 1.0)).collect();
    let df: Vec<Mat3<f64>> = (0..n).map(|_| rand_mat(&mut rng, 1.0)).collect();
    let dc: Vec<Mat3<f64>> = (0..n).map(|_| rand_mat(&mut rng, 1.0)).collect();
    let dmu: Vec<f64> = (0..n).map(|_| uniform(&mut rng, -100.0, 100.0)).collect();
    let dla: Vec<f64> = (0..n).map(|_| uniform(&mut rng, -100.0, 100.0)).collect();
    let dw: Vec<[f64; 3]> = (0..n)
        .map(|_| [0; 3].map(|_| uniform(&mut rng, -1.0, 1.0)))
        .collect();
    // An acceleration moves the state by dt·a = 1e-3 a per substep, so its
    // derivative is ~1e-4 of the O(1) loss (1e-5 with a floor, whose
    // sticking nodes pass nothing back); at FD_STEP the central difference
    // then sits at the round-off floor (measured 1–2e-5 relative on the
    // floor scenes). A direction of length ACCEL_DIRECTION is a 1e-4 m/s²
    // step: still O(h²) truncation, and far from any stick/slip switch.
    const ACCEL_DIRECTION: f64 = 1e2;
    let da: Vec<Vec3<f64>> = (0..n)
        .map(|_| rand_vec(&mut rng, ACCEL_DIRECTION))
        .collect();
    let dot3 =
        |g: &[Vec3<f64>], d: &[Vec3<f64>]| g.iter().zip(d).map(|(a, b)| a.dot(b)).sum::<f64>();
    let dotm = |g: &[Mat3<f64>], d: &[Mat3<f64>]| {
        g.iter()
            .zip(d)
            .map(|(a, b)| a.component_mul(b).sum())
            .sum::<f64>()
    };
    let dots = |g: &[f64], d: &[f64]| g.iter().zip(d).map(|(a, b)| a * b).sum::<f64>();

    check("x", &s, &probe, dot3(&grads.state.x, &dx), &|t, h| {
        t.particles
            .x
            .iter_mut()
            .zip(&dx)
            .for_each(|(x, d)| *x += d * h)
    });
    check("v", &s, &probe, dot3(&grads.state.v, &dv), &|t, h| {
        t.particles
            .v
            .iter_mut()
            .zip(&dv)
            .for_each(|(v, d)| *v += d * h)
    });
    check("F", &s, &probe, dotm(&grads.state.f, &df), &|t, h| {
        t.particles
            .f
            .iter_mut()
            .zip(&df)
            .for_each(|(f, d)| *f += d * h)
    });
    check("C", &s, &probe, dotm(&grads.state.c, &dc), &|t, h| {
        t.particles
            .c
            .iter_mut()
            .zip(&dc)
            .for_each(|(c, d)| *c += d * h)
    });
    check("mu", &s, &probe, dots(&grads.mu, &dmu), &|t, h| {
        t.material
            .mu
            .iter_mut()
            .zip(&dmu)
            .for_each(|(m, d)| *m += d * h)
    });
    check("lambda", &s, &probe, dots(&grads.lambda, &dla), &|t, h| {
        t.material
            .lambda
            .iter_mut()
            .zip(&dla)
            .for_each(|(m, d)| *m += d * h)
    });
    // Masses (a density gradient's parameter): a relative
    // direction, so the FD_STEP step changes each 1e-4 kg mass by 1e-6 of
    // itself, like the other inputs' steps against their scale.
    let dmass: Vec<f64> = s
        .particles
        .mass
        .iter()
        .map(|m| m * uniform(&mut rng, -1.0, 1.0))
        .collect();
    check("mass", &s, &probe, dots(&grads.mass, &dmass), &|t, h| {
        t.particles
            .mass
            .iter_mut()
            .zip(&dmass)
            .for_each(|(m, d)| *m += d * h)
    });
    check(
        "external_accel",
        &s,
        &probe,
        dot3(&grads.external_accel, &da),
        &|t, h| {
            t.external_accel
                .iter_mut()
                .zip(&da)
                .for_each(|(a, d)| *a += d * h)
        },
    );
    // Effect parameters: the per-particle shares summed in order.
    // Their derivatives are small (∝ dt |v|, |v| ≲ 0.1 m/s here), so the
    // FD_STEP-sized step would sit at the round-off floor of the O(1) loss;
    // probing along a direction of length EFFECT_DIRECTION is a 1e-3 step,
    // whose truncation error is still O(h²) ≈ 1e-6 relative.
    const EFFECT_DIRECTION: f64 = 1e3;
    let effect_names = ["air_drag_linear", "air_drag_quadratic"];
    for (i, name) in effect_names.into_iter().enumerate() {
        let analytic: f64 = EFFECT_DIRECTION * grads.effects.iter().map(|g| g[i]).sum::<f64>();
        check(name, &s, &probe, analytic, &|t, h| match i {
            0 => t.consts.drag_linear += EFFECT_DIRECTION * h,
            _ => t.consts.drag_quadratic += EFFECT_DIRECTION * h,
        });
    }
    // η = 0 switches the viscous solve off: the adjoint has no η̄ there
    // (a fit learns ln η, so η stays > 0 once the term is on).
    if s.consts.viscosity > 0.0 {
        check(
            "viscosity",
            &s,
            &probe,
            EFFECT_DIRECTION * grads.viscosity,
            &|t, h| t.consts.viscosity += EFFECT_DIRECTION * h,
        );
    }
    // Gravity (a ground tilt's parameter): it moves the loss by dt per unit,
    // so it is probed along the same long direction.
    let dg = rand_vec(&mut rng, EFFECT_DIRECTION);
    check("gravity", &s, &probe, grads.gravity.dot(&dg), &|t, h| {
        t.consts.gravity += dg * h
    });
    // The floor's friction μ (a learnt friction's parameter): a unit step
    // moves a sliding node's velocity by v_n t̂ (|v_n| ≈ 0.4 m/s), an O(1)
    // change of the loss, so the plain FD_STEP serves; 1e-6 of μ crosses
    // no stick/slip switch on these seeds (see FLOOR_DRIFT).
    if s.consts.floor.is_some_and(|f| f.friction > 0.0) {
        check("floor_friction", &s, &probe, grads.friction, &|t, h| {
            if let Some(floor) = t.consts.floor.as_mut() {
                floor.friction += h;
            }
        });
    }
    if !pure_neo_hookean {
        let analytic: f64 = grads
            .weights
            .iter()
            .zip(&dw)
            .map(|(g, d)| (0..3).map(|k| g[k] * d[k]).sum::<f64>())
            .sum();
        check("expert weights", &s, &probe, analytic, &|t, h| {
            t.material
                .expert_weights
                .iter_mut()
                .zip(&dw)
                .for_each(|(w, d)| (0..3).for_each(|k| w[k] += d[k] * h))
        });
    }
}

#[test]
fn substep_adjoint_matches_finite_differences_mixture() {
    check_all_inputs(1, false);
    check_all_inputs(2, false);
}

#[test]
fn substep_adjoint_matches_finite_differences_neo_hookean() {
    check_all_inputs(3, true);
}

/// Issue 6: the floor's Coulomb friction in the grid update's adjoint,
/// floor nodes mostly sliding (μ = 0.5).
#[test]
fn substep_adjoint_matches_finite_differences_floor_sliding() {
    check_scene(
        3,
        scene_with(
            3,
            false,
            Some(FloorCase {
                friction: 0.5,
                viscous: true,
            }),
        ),
    );
}

/// The same floor with floor nodes mostly sticking (μ = 5): nothing flows
/// back through a sticking node.
#[test]
fn substep_adjoint_matches_finite_differences_floor_sticking() {
    check_scene(
        4,
        scene_with(
            4,
            false,
            Some(FloorCase {
                friction: 5.0,
                viscous: true,
            }),
        ),
    );
}

/// Sliding on the floor without the viscous solve: the grid update's
/// adjoint takes its other path, which sums μ̄ on its own.
#[test]
fn substep_adjoint_matches_finite_differences_floor_sliding_inviscid() {
    check_scene(
        6,
        scene_with(
            6,
            false,
            Some(FloorCase {
                friction: 0.5,
                viscous: false,
            }),
        ),
    );
}

/// The frictionless floor (projection only), for comparison.
#[test]
fn substep_adjoint_matches_finite_differences_floor_frictionless() {
    check_scene(
        5,
        scene_with(
            5,
            false,
            Some(FloorCase {
                friction: 0.0,
                viscous: true,
            }),
        ),
    );
}
