//! Issue 4: the residual trained through the physics. Two frames of MPM,
//! each followed by a tiny PNPGD network's correction, in f64; the
//! gradient of a loss on the final state (plus the Δv regulariser) with
//! respect to the network's weights, chained through `residual_backward`
//! and `World::backward_frame` exactly as the fit chains them, against
//! central finite differences.

use dm_model::residual::{
    FrameStart, ResidualNetwork, apply_residual, frame_inputs, frame_start, residual_backward,
};
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::real::{Mat3, Vec3};
use dm_mpm::{ActuatorConfig, ParticleMaterial, PhysicsConfig, World};
use dm_residual::Precision;
use dm_residual::{NetworkSize, Residual, ResidualKind, ResidualSpec};

/// Two frames of 6 substeps and two network passes compose many f64
/// operations; round-off stays near 1e-9 relative, far below the issue's
/// 1e-5, and no ReLU kink or stencil cell change is crossed by a 1e-6 step.
const FD_RTOL: f64 = 1e-5;
const FD_STEP: f64 = 1e-6;
const FRAMES: usize = 2;
const REGULARISER: f64 = 1e-3;

fn stream(seed: u64) -> impl FnMut() -> f64 {
    let mut s = seed;
    move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }
}

fn world() -> World<f64> {
    let mut config = PhysicsConfig::volumetric([-0.25, -0.25, -0.1], 0.5, [0.0, 0.0, 1.0]);
    config.grid_res = 16;
    config.dt = 1e-3;
    config.substeps_per_frame = 6;
    config.position_clip = [0.1, 0.9];
    config.empty_node_mass_ratio = 0.0;
    let mut positions = Vec::new();
    for i in 0..4 {
        for j in 0..3 {
            for k in 0..3 {
                positions.push([
                    -0.03 + 0.02 * i as f64,
                    -0.02 + 0.02 * j as f64,
                    0.05 + 0.02 * k as f64,
                ]);
            }
        }
    }
    let n = positions.len();
    let material =
        ParticleMaterial::from_fields(&vec![3e3; n], &vec![0.3; n], &vec![[0.6, 0.3, 0.1]; n]);
    let mut w = World::new(
        config,
        &positions,
        8e-6,
        material,
        ActuatorConfig::default(),
    )
    .expect("world");
    let mut r = stream(5);
    let v: Vec<[f64; 3]> = (0..n).map(|_| [0.2 * r(), 0.2 * r(), 0.2 * r()]).collect();
    w.set_velocities(&v).expect("velocities");
    w
}

fn network(w: &World<f64>) -> Residual {
    let c = w.config();
    let spec = ResidualSpec {
        kind: ResidualKind::Pgnd,
        size: NetworkSize {
            encoder: [8, 16, 8],
            decoder: 16,
            groups: 4,
        },
        alpha: 1.0,
        grid_origin: c.domain_origin,
        grid_dx: c.dx(),
        domain_size: c.domain_size,
        seed: 1,
    };
    let mut net = Residual::new(spec, Precision::F64).expect("network");
    let mut r = stream(9);
    let values: Vec<f64> = (0..net.parameter_count()).map(|_| 0.3 * r()).collect();
    net.set_parameters(&values).expect("parameters");
    net
}

fn on_cpu(net: &Residual) -> ResidualNetwork {
    ResidualNetwork::Cpu(net.clone())
}

fn probe(n: usize) -> ParticleGrads<f64> {
    let mut r = stream(13);
    ParticleGrads {
        x: (0..n).map(|_| Vec3::new(r(), r(), r())).collect(),
        v: (0..n).map(|_| Vec3::new(r(), r(), r())).collect(),
        f: vec![Mat3::zeros(); n],
        c: vec![Mat3::zeros(); n],
    }
}

/// The loss: ⟨probe, final state⟩ + regulariser · Σ_t Σ_p |Δv|².
fn forward(net: &Residual, probe: &ParticleGrads<f64>) -> f64 {
    let mut w = world();
    let mut starts: Vec<FrameStart> = Vec::new();
    let mut penalty = 0.0;
    for t in 0..FRAMES {
        starts.push(frame_start(&w));
        w.step_frame(&[], &[], &[]).expect("frame");
        let (dv, _) = apply_residual(&mut w, &on_cpu(net), &starts, t).expect("residual");
        penalty += dv.iter().flatten().map(|c| c * c).sum::<f64>();
    }
    let s = w.state();
    let linear: f64 = (0..s.len())
        .map(|p| probe.x[p].dot(&s.x[p]) + probe.v[p].dot(&s.v[p]))
        .sum();
    linear + REGULARISER * penalty
}

#[test]
fn residual_gradient_through_the_physics_matches_finite_differences() {
    let mut net = network(&world());
    let n = world().particle_count();
    let probe = probe(n);

    // Forward with checkpoints, then replay each frame backwards as the fit does.
    let mut w = world();
    let mut starts: Vec<FrameStart> = Vec::new();
    let mut checkpoints = Vec::new();
    let mut corrections = Vec::new();
    for t in 0..FRAMES {
        checkpoints.push(w.state());
        starts.push(frame_start(&w));
        w.step_frame(&[], &[], &[]).expect("frame");
        corrections.push(
            apply_residual(&mut w, &on_cpu(&net), &starts, t)
                .expect("residual")
                .0,
        );
    }
    let mut carried = probe.clone();
    let mut gradient = vec![0.0; net.parameter_count()];
    let cpu = on_cpu(&net);
    for t in (0..FRAMES).rev() {
        w.set_state(&checkpoints[t]).expect("state");
        let tape = w
            .step_frame_taped(&[], &[], &[], usize::MAX)
            .expect("taped frame");
        let inputs = frame_inputs(&w, &starts, t);
        let correction_tape = w
            .apply_velocity_correction(&corrections[t])
            .expect("correction");
        let grads = residual_backward(
            &cpu,
            &inputs,
            &corrections[t],
            &correction_tape,
            &mut carried,
            REGULARISER,
        )
        .expect("residual backward");
        gradient
            .iter_mut()
            .zip(&grads.parameters)
            .for_each(|(g, d)| *g += d);
        carried = w
            .backward_frame(&tape, &carried)
            .expect("frame backward")
            .state;
        for (c, g) in carried.x.iter_mut().zip(&grads.x_start) {
            *c += Vec3::new(g[0], g[1], g[2]);
        }
    }

    let base = net.parameters().expect("parameters");
    let mut r = stream(21);
    let direction: Vec<f64> = (0..base.len()).map(|_| r()).collect();
    let analytic: f64 = gradient.iter().zip(&direction).map(|(g, d)| g * d).sum();
    let mut at = |h: f64| {
        let moved: Vec<f64> = base
            .iter()
            .zip(&direction)
            .map(|(b, d)| b + h * d)
            .collect();
        net.set_parameters(&moved).expect("parameters");
        forward(&net, &probe)
    };
    let numeric = (at(FD_STEP) - at(-FD_STEP)) / (2.0 * FD_STEP);
    let rel = (analytic - numeric).abs() / analytic.abs().max(numeric.abs()).max(1e-8);
    assert!(
        analytic.abs() > 1e-6,
        "the check must see a gradient, got {analytic:e}"
    );
    assert!(
        rel <= FD_RTOL,
        "weights: chained adjoint {analytic:.10e} vs finite differences {numeric:.10e} (relative error {rel:.2e})"
    );
}
