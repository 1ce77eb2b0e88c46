//! The material gradient the fit steps along — an f32 world, only the
//! last `--window` substeps of each frame differentiated (truncated BPTT) —
//! against the gradient it stands in for: every substep differentiated, in
//! f64.

mod common;

use dm_bundle::Bundle;
use dm_fit::loss::{
    LengthPreservation, LossTerms, LossWeights, ObservedFrame, PairSelection, TrackMatch,
    frame_loss,
};
use dm_fit::material_fit::{MaterialFitConfig, fit_frames, loss_and_gradient};
use dm_model::{ExpertChoice, ModelOptions, ResidualKind, WorldModel};
use dm_mpm::PatchParams;
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::real::Vec3;

/// Least cosine between the fit's gradient and the full-window f64 one.
///
/// Measured on the tiny rope of `common::tiny_rope` (800 particles, 9
/// frames, 42 substeps per frame, the default window of 20): cosine 0.9968,
/// norm ratio 0.759. The same truncated loop run in f64 gives the same
/// 0.9968 and 0.759, and the full window in f32 gives 1 − 2e-11 and
/// 1.000006: the whole gap is the truncation, which drops the material's
/// share of each frame's first 22 substeps and so shortens the gradient
/// more than it turns it. 0.99 leaves three times the measured 1 − cosine
/// as margin. Other tiny scenes at the default window, for scale: rope
/// seed 21 0.997 / 0.60, cloth seed 4 0.989 / 0.51, toy seed 3 0.946 / 0.14
/// (the bounds here are this scene's, not a promise for every scene).
const MIN_COSINE: f64 = 0.99;

/// Range of |fit's gradient| / |full-window f64 gradient| (measured 0.759,
/// see [`MIN_COSINE`]; the truncation only shortens it on this scene).
const NORM_RATIO: [f64; 2] = [0.6, 1.05];

/// The bounds tell a truncated gradient from a poor one: with one substep
/// per frame differentiated the same scene gives cosine 0.898 and norm
/// ratio 0.022 (a window of 10: 0.967 and 0.489), outside both. The test
/// checks that a window of this many substeps falls outside them.
const POOR_WINDOW: usize = 1;

/// With every substep differentiated, f32 against f64 (measured cosine
/// 1 − 2e-11 and norm ratio 1 + 6e-6): the f32 adjoint itself.
const FULL_WINDOW_MIN_COSINE: f64 = 1.0 - 1e-6;
const FULL_WINDOW_NORM_RATIO: [f64; 2] = [1.0 - 1e-4, 1.0 + 1e-4];

/// The patch parameters' gradient as one vector: E, ν, expert logits.
fn flatten(p: &PatchParams) -> Vec<f64> {
    let mut all = p.youngs_raw.clone();
    all.extend(&p.poisson_raw);
    all.extend(p.logits.iter().flatten());
    all
}

/// The fit's loss and patch gradient of `model` over `frames` frames
/// (`material_fit::loss_and_gradient` for a model without a residual
/// network), in an f64 world with every substep of every frame
/// differentiated.
fn full_window_f64(model: &WorldModel, bundle: &Bundle, frames: usize) -> Vec<f64> {
    let steps = frames - 1;
    let mut world = model.world_in::<f64>().expect("f64 world");
    let n = world.particle_count();
    let observed = |t| ObservedFrame::from_tracks(&bundle.tracks, t).expect("tracks");
    let track = TrackMatch::new(&model.particles, &observed(0).points).expect("track match");
    let length =
        LengthPreservation::new(&model.particles, PairSelection::default()).expect("pairs");
    let terms = LossTerms {
        track: &track,
        length: &length,
        surface_count: model.surface_count,
    };
    // Forward: each frame's start state and the loss gradient at its end.
    let mut starts = Vec::with_capacity(steps);
    let mut seeds = Vec::with_capacity(steps);
    for t in 0..steps {
        starts.push(world.state());
        let (from, to, grasp) = model.hand_step(bundle, t);
        world.step_frame(&from, &to, &grasp).expect("frame");
        let value = frame_loss(
            &LossWeights::default(),
            &terms,
            &world.positions(),
            &observed(t + 1),
        )
        .expect("loss")
        .total;
        let seed: Vec<Vec3<f64>> = value
            .grad
            .iter()
            .map(|g| Vec3::new(g[0], g[1], g[2]) / steps as f64)
            .collect();
        seeds.push(seed);
    }
    // Backward: each frame replayed with a tape of all its substeps.
    let window = model.physics.substeps_per_frame;
    let mut carried = ParticleGrads::<f64>::zeros(n);
    let mut grad_mu = vec![0.0; n];
    let mut grad_lambda = vec![0.0; n];
    let mut grad_weights = vec![[0.0; 3]; n];
    for t in (0..steps).rev() {
        for (c, g) in carried.x.iter_mut().zip(&seeds[t]) {
            *c += g;
        }
        world.set_state(&starts[t]).expect("state");
        let (from, to, grasp) = model.hand_step(bundle, t);
        let tape = world
            .step_frame_taped(&from, &to, &grasp, window)
            .expect("taped frame");
        let g = world.backward_frame(&tape, &carried).expect("backward");
        for p in 0..n {
            grad_mu[p] += g.mu[p];
            grad_lambda[p] += g.lambda[p];
            for e in 0..3 {
                grad_weights[p][e] += g.weights[p][e];
            }
        }
        carried = g.state;
    }
    let mut grads = model.patches.particle_material_vjp(
        &model.params,
        &model.bounds,
        &grad_mu,
        &grad_lambda,
        &grad_weights,
    );
    if model.options.experts == ExpertChoice::Nh {
        grads.logits.iter_mut().for_each(|l| *l = [0.0; 3]);
    }
    flatten(&grads)
}

/// Cosine between `a` and `b`, and |a| / |b|.
fn cosine_and_norm_ratio(a: &[f64], b: &[f64]) -> (f64, f64) {
    let dot: f64 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
    (dot / (norm(a) * norm(b)), norm(a) / norm(b))
}

#[test]
fn truncated_f32_material_gradient_follows_the_full_window_f64_gradient() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());
    // dm-fit's defaults (patches, experts, window), without the residual
    // network, whose f64 adjoint this test does not rebuild.
    let fit = common::fit_options(&[]);
    let model = WorldModel::from_bundle(
        &bundle,
        &ModelOptions {
            residual: ResidualKind::None,
            ..fit.model.clone()
        },
    )
    .expect("model");
    let frames = fit_frames(&bundle, &MaterialFitConfig::default());
    let substeps = model.physics.substeps_per_frame;
    assert!(
        fit.window < substeps,
        "window {} of {substeps} substeps: nothing truncated to test",
        fit.window
    );
    let reference = full_window_f64(&model, &bundle, frames);
    let fit_gradient = |window| {
        let (_, grads) =
            loss_and_gradient(&model, &bundle, frames, window, None).expect("gradient");
        cosine_and_norm_ratio(&flatten(&grads.patches), &reference)
    };
    let within = |(cosine, ratio): (f64, f64)| {
        cosine >= MIN_COSINE && (NORM_RATIO[0]..=NORM_RATIO[1]).contains(&ratio)
    };

    let (cosine, ratio) = fit_gradient(fit.window);
    assert!(
        within((cosine, ratio)),
        "window {}: cosine {cosine:.5} (at least {MIN_COSINE}), norm ratio {ratio:.4} \
         (within {NORM_RATIO:?})",
        fit.window
    );

    let (cosine, ratio) = fit_gradient(substeps);
    assert!(
        cosine >= FULL_WINDOW_MIN_COSINE
            && (FULL_WINDOW_NORM_RATIO[0]..=FULL_WINDOW_NORM_RATIO[1]).contains(&ratio),
        "full window in f32: cosine 1 - {:.2e}, norm ratio {ratio:.7}",
        1.0 - cosine
    );

    let (cosine, ratio) = fit_gradient(POOR_WINDOW);
    assert!(
        !within((cosine, ratio)),
        "window {POOR_WINDOW} passes the bounds (cosine {cosine:.5}, norm ratio {ratio:.4}): \
         they no longer tell a truncated gradient from a poor one"
    );
}
