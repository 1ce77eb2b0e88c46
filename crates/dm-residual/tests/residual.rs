//! Issue 4: the residual network's bound, its vector-Jacobian product
//! against central finite differences in f64, save/load, determinism.

use dm_residual::Precision;
use dm_residual::{FrameInputs, HISTORY, NetworkSize, Residual, ResidualKind, ResidualSpec};

/// Relative error allowed between the hand-written VJP and central differences
/// in f64: the network is smooth away from ReLU/max-pool kinks and stencil
/// cell changes, which a 1e-6 step almost surely does not cross; what is
/// left is round-off (~1e-10 / 1e-6) and the O(h²) truncation.
const FD_RTOL: f64 = 1e-5;
const FD_STEP: f64 = 1e-6;

fn stream(seed: u64) -> impl FnMut() -> f64 {
    let mut s = seed;
    move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }
}

fn spec(kind: ResidualKind) -> ResidualSpec {
    ResidualSpec {
        kind,
        size: NetworkSize {
            encoder: [8, 16, 8],
            decoder: 16,
            groups: 4,
        },
        alpha: 1.0,
        grid_origin: [-0.5, -0.5, -0.5],
        grid_dx: 1.0 / 16.0,
        domain_size: 1.0,
        seed: 3,
    }
}

fn cloud(n: usize, seed: u64) -> FrameInputs {
    let mut r = stream(seed);
    let mut points = |scale: f64, offset: f64| -> Vec<[f64; 3]> {
        (0..n)
            .map(|_| {
                [
                    offset + scale * r(),
                    offset + scale * r(),
                    offset + scale * r(),
                ]
            })
            .collect()
    };
    let x_tilde = points(0.1, 0.0);
    let v_tilde = points(0.5, 0.0);
    let x_start = points(0.1, 0.0);
    let history = (0..HISTORY)
        .map(|_| (points(0.1, 0.0), points(0.5, 0.0)))
        .collect();
    FrameInputs {
        x_tilde,
        v_tilde,
        x_start,
        history,
    }
}

/// Non-zero weights everywhere (the fresh network's last layer is zero).
fn randomised(kind: ResidualKind, precision: Precision, scale: f64) -> Residual {
    let mut net = Residual::new(spec(kind), precision).expect("network");
    let mut r = stream(17);
    let values: Vec<f64> = (0..net.parameter_count()).map(|_| scale * r()).collect();
    net.set_parameters(&values).expect("parameters");
    net
}

fn dot(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| x[0] * y[0] + x[1] * y[1] + x[2] * y[2])
        .sum()
}

fn check(name: &str, analytic: f64, eval: &mut dyn FnMut(f64) -> f64) {
    let numeric = (eval(FD_STEP) - eval(-FD_STEP)) / (2.0 * FD_STEP);
    let rel = (analytic - numeric).abs() / analytic.abs().max(numeric.abs()).max(1e-8);
    assert!(
        rel <= FD_RTOL,
        "{name}: vjp {analytic:.10e} vs finite differences {numeric:.10e} (relative error {rel:.2e})"
    );
}

fn shifted(points: &[[f64; 3]], direction: &[[f64; 3]], h: f64) -> Vec<[f64; 3]> {
    points
        .iter()
        .zip(direction)
        .map(|(p, d)| [p[0] + h * d[0], p[1] + h * d[1], p[2] + h * d[2]])
        .collect()
}

fn vjp_matches_finite_differences(kind: ResidualKind, particles: usize) {
    let mut net = randomised(kind, Precision::F64, 0.5);
    let inputs = cloud(particles, 5);
    let n = inputs.particle_count();
    let mut r = stream(23);
    let mut directions = || -> Vec<[f64; 3]> { (0..n).map(|_| [r(), r(), r()]).collect() };
    let probe = directions();
    let grads = net.vjp(&inputs, &probe).expect("vjp");
    let objective =
        |net: &Residual, inputs: &FrameInputs| dot(&net.predict(inputs).expect("predict"), &probe);

    for (name, field) in [("x_tilde", 0), ("v_tilde", 1), ("x_start", 2)] {
        let direction = directions();
        let analytic = dot(
            match field {
                0 => &grads.x_tilde,
                1 => &grads.v_tilde,
                _ => &grads.x_start,
            },
            &direction,
        );
        check(&format!("{kind:?} {name}"), analytic, &mut |h| {
            let mut moved = inputs.clone();
            let target = match field {
                0 => &mut moved.x_tilde,
                1 => &mut moved.v_tilde,
                _ => &mut moved.x_start,
            };
            *target = shifted(target, &direction, h);
            objective(&net, &moved)
        });
    }
    for k in 0..inputs.history.len() {
        for (name, velocity) in [("x", false), ("v", true)] {
            let direction = directions();
            let (gx, gv) = &grads.history[k];
            let analytic = dot(if velocity { gv } else { gx }, &direction);
            check(
                &format!("{kind:?} history[{k}].{name}"),
                analytic,
                &mut |h| {
                    let mut moved = inputs.clone();
                    let (hx, hv) = &mut moved.history[k];
                    let target = if velocity { hv } else { hx };
                    *target = shifted(target, &direction, h);
                    objective(&net, &moved)
                },
            );
        }
    }
    let base = net.parameters().expect("parameters");
    let direction: Vec<f64> = (0..base.len()).map(|_| r()).collect();
    let analytic: f64 = grads
        .parameters
        .iter()
        .zip(&direction)
        .map(|(g, d)| g * d)
        .sum();
    check(&format!("{kind:?} parameters"), analytic, &mut |h| {
        let moved: Vec<f64> = base
            .iter()
            .zip(&direction)
            .map(|(b, d)| b + h * d)
            .collect();
        net.set_parameters(&moved).expect("parameters");
        let value = objective(&net, &inputs);
        net.set_parameters(&base).expect("parameters");
        value
    });
}

#[test]
fn pgnd_vjp_matches_finite_differences() {
    vjp_matches_finite_differences(ResidualKind::Pgnd, 40);
}

#[test]
fn mlp_vjp_matches_finite_differences() {
    vjp_matches_finite_differences(ResidualKind::Mlp, 40);
}

/// Enough particles that the layers split their rows into several
/// parallel ranges and partial sums (128 and 512 rows each).
#[test]
fn vjp_matches_finite_differences_across_row_ranges() {
    vjp_matches_finite_differences(ResidualKind::Pgnd, 1100);
    vjp_matches_finite_differences(ResidualKind::Mlp, 1100);
}

#[test]
fn vjp_is_independent_of_thread_count() {
    let net = randomised(ResidualKind::Pgnd, Precision::F32, 0.3);
    let inputs = cloud(2000, 8);
    let grad_dv = vec![[0.3, -0.2, 0.1]; inputs.particle_count()];
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool")
            .install(|| net.vjp(&inputs, &grad_dv).expect("vjp"))
    };
    assert_eq!(run(1), run(2));
}

#[test]
fn zero_widths_and_far_particles_are_refused() {
    let mut zero = spec(ResidualKind::Pgnd);
    zero.size.decoder = 0;
    let err = Residual::new(zero, Precision::F32).expect_err("zero width");
    assert!(err.to_string().contains("size"), "{err}");
    let net = Residual::new(spec(ResidualKind::Pgnd), Precision::F32).expect("network");
    let mut inputs = cloud(10, 3);
    inputs.x_tilde[7] = [1e12, 0.0, 0.0];
    let err = net.predict(&inputs).expect_err("far particle");
    assert!(err.to_string().contains("particle 7"), "{err}");
}

#[test]
fn velocity_correction_never_exceeds_alpha() {
    for kind in [ResidualKind::Pgnd, ResidualKind::Mlp] {
        // Huge weights and inputs saturate the bound.
        let net = randomised(kind, Precision::F32, 20.0);
        let mut inputs = cloud(300, 9);
        inputs
            .v_tilde
            .iter_mut()
            .for_each(|v| *v = v.map(|c| 1e3 * c));
        let dv = net.predict(&inputs).expect("predict");
        let largest = dv
            .iter()
            .map(|d| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt())
            .fold(0.0, f64::max);
        // f32 rounding of α·tanh(|y|)·y/|y|.
        assert!(largest <= 1.0 + 1e-5, "{kind:?}: |dv| = {largest} > alpha");
        assert!(
            largest > 0.5,
            "{kind:?}: the bound should be approached, got {largest}"
        );
    }
}

#[test]
fn untrained_residual_changes_nothing() {
    let net = Residual::new(spec(ResidualKind::Pgnd), Precision::F32).expect("network");
    let dv = net.predict(&cloud(50, 1)).expect("predict");
    assert!(dv.iter().flatten().all(|&c| c == 0.0));
}

#[test]
fn weights_round_trip_and_bad_files_are_named() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("residual.safetensors");
    let net = randomised(ResidualKind::Pgnd, Precision::F32, 0.3);
    net.save(&path).expect("save");
    let loaded = Residual::load(spec(ResidualKind::Pgnd), &path, Precision::F32).expect("load");
    assert_eq!(
        net.parameters().expect("p"),
        loaded.parameters().expect("p")
    );
    let inputs = cloud(30, 2);
    assert_eq!(
        net.predict(&inputs).expect("a"),
        loaded.predict(&inputs).expect("b")
    );

    let mut other = spec(ResidualKind::Pgnd);
    other.size.decoder = 32;
    let err = Residual::load(other, &path, Precision::F32).expect_err("shape mismatch");
    let message = err.to_string();
    assert!(
        message.contains("residual.safetensors") && message.contains("shape"),
        "{message}"
    );

    std::fs::write(&path, b"not safetensors").expect("write");
    let err = Residual::load(spec(ResidualKind::Pgnd), &path, Precision::F32).expect_err("garbage");
    assert!(err.to_string().contains("residual.safetensors"), "{err}");
}

#[test]
fn bad_inputs_name_the_field() {
    let net = Residual::new(spec(ResidualKind::Mlp), Precision::F32).expect("network");
    let mut inputs = cloud(10, 4);
    inputs.v_tilde[3][0] = f64::NAN;
    let err = net.predict(&inputs).expect_err("NaN input");
    assert!(
        err.to_string().contains("v_tilde") && err.to_string().contains("particle 3"),
        "{err}"
    );
    let mut inputs = cloud(10, 4);
    inputs.history.pop();
    assert!(
        net.predict(&inputs)
            .expect_err("short history")
            .to_string()
            .contains("history")
    );
}

#[test]
fn prediction_is_independent_of_thread_count() {
    let net = randomised(ResidualKind::Pgnd, Precision::F32, 0.3);
    let inputs = cloud(2000, 8);
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool")
            .install(|| net.predict(&inputs).expect("predict"))
    };
    assert_eq!(run(1), run(2));
}

/// Issue 4 regression: Adam's first step moves every weight by about its
/// learning rate (5e-3) whatever the gradient; from the fresh network that
/// must give a small correction, not the 0.8 m/s that blew a rope fit up.
#[test]
fn one_adam_sized_step_from_fresh_weights_stays_small() {
    // The method's sizes: the blow-up grows with the decoder's width.
    let method_sized = ResidualSpec {
        size: NetworkSize::default(),
        grid_dx: 1.0 / 32.0,
        ..spec(ResidualKind::Pgnd)
    };
    let mut net = Residual::new(method_sized, Precision::F32).expect("network");
    // Gradient-aligned: every weight moves the same way (a sign pattern
    // with random signs would mostly cancel).
    let stepped: Vec<f64> = net
        .parameters()
        .expect("parameters")
        .iter()
        .map(|w| w + 5e-3)
        .collect();
    net.set_parameters(&stepped).expect("parameters");
    let dv = net.predict(&cloud(500, 6)).expect("predict");
    let largest = dv
        .iter()
        .map(|d| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt())
        .fold(0.0, f64::max);
    assert!(largest < 0.05, "one step moved |dv| to {largest} m/s");
}

/// Regression (a toy fit stopped by a NaN gradient): a particle
/// just below a cell's half-way point reaches its stencil's far corner
/// node with a weight near f32's smallest normal; the node's feature is a
/// ratio of two such numbers, whose derivative overflowed. The VJP must
/// stay finite.
#[test]
fn vjp_is_finite_where_a_node_gets_a_vanishing_spline_weight() {
    let s = spec(ResidualKind::Pgnd);
    let mut inputs = cloud(40, 5);
    // Grid coordinate 14.5 − 1.6e-6 on every axis (after f32 rounding):
    // the far corner node's weight is (½·ε²)³ ≈ 2e-36.
    let edge = s.grid_origin[0] + 14.5 * s.grid_dx - 1e-7;
    inputs.x_tilde[0] = [edge; 3];
    inputs.x_start[0] = [edge; 3];
    let net = randomised(ResidualKind::Pgnd, Precision::F32, 0.5);
    let dv = net.predict(&inputs).expect("predict");
    assert!(dv.iter().flatten().all(|c| c.is_finite()));
    let grad_dv = vec![[1.0, -0.5, 0.25]; inputs.particle_count()];
    let grads = net.vjp(&inputs, &grad_dv).expect("vjp");
    let bad_parameters = grads.parameters.iter().filter(|g| !g.is_finite()).count();
    let bad_inputs = [&grads.x_tilde, &grads.v_tilde, &grads.x_start]
        .iter()
        .flat_map(|g| g.iter().flatten())
        .filter(|g| !g.is_finite())
        .count();
    assert_eq!((bad_parameters, bad_inputs), (0, 0), "non-finite gradients");
}

/// The input channels (which other backends form on the host) and their
/// adjoint: the channels are linear in the inputs, so
/// ⟨adjoint(g), δ⟩ = ⟨g, channels(inputs + δ) − channels(inputs)⟩ holds
/// to round-off for any g and δ.
#[test]
fn the_input_channels_adjoint_is_their_transpose() {
    use dm_residual::network::{input_channels, input_channels_backward};
    let n = 30;
    let inputs = cloud(n, 41);
    let delta = cloud(n, 43);
    let moved = FrameInputs {
        x_tilde: shifted(&inputs.x_tilde, &delta.x_tilde, 1.0),
        v_tilde: shifted(&inputs.v_tilde, &delta.v_tilde, 1.0),
        x_start: shifted(&inputs.x_start, &delta.x_start, 1.0),
        history: inputs
            .history
            .iter()
            .zip(&delta.history)
            .map(|((x, v), (dx, dv))| (shifted(x, dx, 1.0), shifted(v, dv, 1.0)))
            .collect(),
    };
    let mut r = stream(47);
    let g: Vec<f64> = (0..n * dm_residual::CHANNELS).map(|_| r()).collect();
    let change: f64 = input_channels(&moved)
        .iter()
        .zip(input_channels(&inputs))
        .zip(&g)
        .map(|((a, b), g)| (a - b) * g)
        .sum();
    let ([x, v, s], history) = input_channels_backward(g);
    let mut through_adjoint =
        dot(&x, &delta.x_tilde) + dot(&v, &delta.v_tilde) + dot(&s, &delta.x_start);
    for ((hx, hv), (dx, dv)) in history.iter().zip(&delta.history) {
        through_adjoint += dot(hx, dx) + dot(hv, dv);
    }
    assert!(
        (change - through_adjoint).abs() <= 1e-12 * change.abs().max(1.0),
        "⟨g, Δchannels⟩ {change:.15e} vs ⟨adjoint(g), δ⟩ {through_adjoint:.15e}"
    );
}
