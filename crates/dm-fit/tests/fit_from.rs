//! Issue 6: `run_fit_from` runs dm-fit's stages from a given starting
//! model (dm-diagnose fits each candidate effect from the start).

mod common;

use dm_fit::run::{run_fit, run_fit_from};
use dm_model::WorldModel;

fn norm(v: [f64; 3]) -> f64 {
    v.iter().map(|c| c * c).sum::<f64>().sqrt()
}

fn saved(dir: &std::path::Path) -> WorldModel {
    dm_bundle::read_json(&dir.join("model.json")).expect("model.json")
}

#[test]
fn fit_from_a_starting_model_learns_or_keeps_its_effect_and_matches_run_fit_from_the_default() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());
    let flags = ["--residual", "none"];
    let options = common::fit_options(&flags);

    let plain = dir.path().join("plain");
    run_fit(&bundle, &options, &plain, false, None, &mut |_| {}).expect("fit");
    let default_start = WorldModel::from_bundle(&bundle, &options.model).expect("start");
    let from_default = dir.path().join("from_default");
    run_fit_from(
        &bundle,
        &options,
        default_start.clone(),
        &from_default,
        &mut |_| {},
    )
    .expect("fit from the default start");
    // Same start, same deterministic stages: the same model, bit for bit.
    assert_eq!(saved(&plain), saved(&from_default));

    let mut with_drag = default_start;
    with_drag.physics.effects.air_drag_linear = 25.0;
    let dragged = dir.path().join("dragged");
    let frozen = common::fit_options(&["--residual", "none", "--freeze-effects"]);
    run_fit_from(&bundle, &frozen, with_drag.clone(), &dragged, &mut |_| {})
        .expect("fit from a start with drag");
    let fitted = saved(&dragged);
    assert_eq!(fitted.physics.effects.air_drag_linear, 25.0);
    // The drag changed what the material step saw.
    assert_ne!(fitted.params, saved(&plain).params);

    // Learnt by default: one Adam step moves ln k by about the rate (0.1).
    let learnt = dir.path().join("learnt");
    run_fit_from(&bundle, &options, with_drag, &learnt, &mut |_| {}).expect("fit");
    let k = saved(&learnt).physics.effects.air_drag_linear;
    let moved = (k / 25.0).ln().abs();
    assert!(
        (0.05..0.15).contains(&moved),
        "one step moved ln k by {moved} (k = {k})"
    );
    // An effect that is off stays off.
    assert_eq!(saved(&learnt).physics.effects.viscosity, 0.0);
}

/// A tiny rope with `effect` hidden, and dm-fit's start model given the
/// truth's homogeneous material and grip, so the hidden effect is what the
/// training loss measures (with the effect's exciting action: a push
/// along the floor for friction). From dm-fit's default material and
/// gains the loss on these 14 frames only grows with drag, whatever is
/// hidden.
fn truth_start(
    dir: &std::path::Path,
    effect: &str,
) -> (dm_bundle::Bundle, dm_synth::TruthFile, WorldModel) {
    let scene = dir.join("scene");
    let truth_path = dir.join("truth.json");
    let effect: dm_synth::EffectSpec = effect.parse().expect("effect");
    let config = dm_synth::SynthConfig {
        effect: Some(effect),
        action: effect.name.exciting_action(),
        homogeneous: true,
        ..dm_synth::SynthConfig::tiny(dm_synth::Preset::Rope, 5)
    };
    dm_synth::generate(&config, &scene, &truth_path, &mut |_, _, _| {}).expect("scene");
    let truth: dm_synth::TruthFile = dm_bundle::read_json(&truth_path).expect("truth");
    let bundle = dm_bundle::Bundle::open(&scene).expect("bundle");
    let options = common::fit_options(&["--residual", "none"]);
    let mut model = WorldModel::from_bundle(&bundle, &options.model).expect("start");
    model.actuator = dm_synth::truth::TRUTH_GRIP;
    model.params = dm_mpm::PatchParams::uniform(
        model.patches.patch_count(),
        &model.bounds,
        truth.material.e_pa,
        truth.material.nu,
        dm_synth::truth::HOMOGENEOUS_EXPERT_WEIGHTS.map(f64::ln),
    );
    (bundle, truth, model)
}

/// Three material steps (no gain search) from `start`, the fitted model.
fn fit_three_steps(
    bundle: &dm_bundle::Bundle,
    start: WorldModel,
    out: &std::path::Path,
) -> WorldModel {
    let mut options = common::fit_options(&["--residual", "none"]);
    options.iters = 3;
    run_fit_from(bundle, &options, start, out, &mut |_| {}).expect("fit");
    saved(out)
}

/// Three-step fits from `truth_start` with one effect coefficient set to
/// each of `starts`: each must end nearer `target` on a log scale, by at
/// least 0.1 in the log.
fn assert_coefficient_moves_toward(
    bundle: &dm_bundle::Bundle,
    truth_start: &WorldModel,
    dir: &std::path::Path,
    target: f64,
    starts: [f64; 2],
    coefficient: fn(&mut dm_mpm::Effects) -> &mut f64,
    what: &str,
) {
    for start in starts {
        let mut model = truth_start.clone();
        *coefficient(&mut model.physics.effects) = start;
        let mut fitted = fit_three_steps(bundle, model, &dir.join(format!("start_{start}")));
        let end = *coefficient(&mut fitted.physics.effects);
        assert!(
            (end.ln() - target.ln()).abs() < (start.ln() - target.ln()).abs() - 0.1,
            "{what} {target}: started at {start}, ended at {end}"
        );
    }
}

/// Issue 6: a fit started with a quarter or four times the drag hidden
/// in the scene (60 /s) moves it toward the hidden drag (on this rope
/// the training loss is lowest at 30–60 /s).
#[test]
fn learnt_drag_moves_toward_the_hidden_drag() {
    let dir = tempfile::tempdir().expect("temp dir");
    let hidden: f64 = 60.0;
    let (bundle, _, truth_start) = truth_start(dir.path(), &format!("air_drag:{hidden}"));
    assert_coefficient_moves_toward(
        &bundle,
        &truth_start,
        dir.path(),
        hidden,
        [hidden / 4.0, hidden * 4.0],
        |e| &mut e.air_drag_linear,
        "air drag (/s), hidden",
    );
}

/// Issue 6: learnt friction on a rope pushed along a floor with μ = 0.8
/// hidden. On this 14-frame rope the training loss is lowest near μ 0.3
/// (measured from the truth start: 6.279e-5 m² at 0.1, 6.249e-5 at 0.3,
/// 6.308e-5 at 0.8, 6.619e-5 at 1.2; the push barely slides it), so fits
/// started on either side move μ toward 0.3 (its gradient flows through
/// the floor's sliding nodes).
#[test]
fn learnt_friction_moves_toward_the_train_loss_minimum() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (bundle, _, truth_start) = truth_start(dir.path(), "floor_friction:0.8");
    assert_coefficient_moves_toward(
        &bundle,
        &truth_start,
        dir.path(),
        0.3,
        [0.1, 1.2],
        |e| &mut e.floor_friction,
        "friction μ, train loss lowest near",
    );
}

/// Issue 6: a fit started with the hidden tilt's angle but an azimuth
/// 60° off turns gravity toward the hidden direction.
#[test]
fn learnt_tilt_turns_toward_the_hidden_tilt() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (bundle, truth, mut model) = truth_start(dir.path(), "ground_tilt:8");
    let params = &truth.effect.as_ref().expect("hidden effect").params;
    let angle = |key: &str| params[key].as_f64().expect("angle").to_radians();
    let (tilt, azimuth) = (angle("tilt_deg"), angle("azimuth_deg"));
    let up = model.physics.floor.as_ref().expect("floor").up;
    let (east, north) = dm_mpm::config::horizontal_basis(up);
    let g = norm(model.physics.gravity);
    let gravity_at = |azimuth: f64| -> [f64; 3] {
        std::array::from_fn(|a| {
            g * (tilt.sin() * (azimuth.cos() * east[a] + azimuth.sin() * north[a])
                - tilt.cos() * up[a])
        })
    };
    let hidden = gravity_at(azimuth);
    let miss = |gravity: [f64; 3]| norm(std::array::from_fn(|a| gravity[a] - hidden[a]));
    model.physics.gravity = gravity_at(azimuth + 60f64.to_radians());
    let before = miss(model.physics.gravity);
    let fitted = fit_three_steps(&bundle, model, &dir.path().join("tilt"));
    let after = miss(fitted.physics.gravity);
    assert!(
        after < 0.8 * before,
        "gravity off the hidden by {before:.3} m/s² before, {after:.3} after"
    );
    let magnitude = norm(fitted.physics.gravity);
    assert!((magnitude - g).abs() < 1e-9, "|g| kept: {magnitude}");
}

/// Issue 6: a tilted start through every stage, the residual-only one
/// included (its Adam holds the network's group alone, so the tilt's own
/// rate must stay out of it).
#[test]
fn tilted_start_fits_through_the_residual_stage() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());
    let mut options = common::fit_options(&["--residual", "pgnd"]);
    options.residual_iters = 1;
    let mut start = WorldModel::from_bundle(&bundle, &options.model).expect("start");
    let g = norm(start.physics.gravity);
    start.physics.gravity = [0.1 * g, 0.0, -(0.99f64).sqrt() * g];
    let out = dir.path().join("tilted");
    run_fit_from(&bundle, &options, start, &out, &mut |_| {}).expect("fit with a residual stage");
    assert!((norm(saved(&out).physics.gravity) - g).abs() < 1e-9);
}

/// The tiny rope with a density gradient hidden (excess [`HIDDEN_EXCESS`])
/// and its truth start with the hidden gradient's axis and heavy end
/// carrying `excess` (the sign taken care of), its total mass the truth's.
fn density_start(dir: &std::path::Path) -> (dm_bundle::Bundle, impl Fn(f64) -> WorldModel) {
    let (bundle, truth, truth_start) =
        truth_start(dir, &format!("density_variation:{HIDDEN_EXCESS}"));
    let params = &truth.effect.as_ref().expect("hidden effect").params;
    let axis_index = params["axis"].as_u64().expect("axis") as usize;
    let sign = if params["heavy_at_max"].as_bool().expect("heavy end") {
        1.0
    } else {
        -1.0
    };
    let mut axis = [0.0; 3];
    axis[axis_index] = 1.0;
    let with_excess = move |excess: f64| dm_model::ModelExtension {
        density: Some(dm_model::extension::DensityGradient {
            axis,
            excess: sign * excess,
        }),
        ..dm_model::ModelExtension::default()
    };
    let truth_mean = with_excess(HIDDEN_EXCESS).mean_density_factor(&truth_start.particles);
    let start = move |excess: f64| {
        let mut model = truth_start.clone();
        model.extension = with_excess(excess);
        model.physics.density *= truth_mean / model.extension.mean_density_factor(&model.particles);
        model
    };
    (bundle, start)
}

const HIDDEN_EXCESS: f64 = 3.0;

/// Issue 6: a fit started with the hidden density gradient's axis and
/// heavy end but a third of its excess moves the excess toward the hidden
/// one. (From above it would not: on this clip the training loss keeps
/// falling past the hidden excess, 8.26e-5 m² at 3 and 8.15e-5 at 5, as it
/// rises with drag whatever drag is hidden.)
#[test]
fn learnt_density_excess_moves_toward_the_hidden_gradient() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (bundle, start) = density_start(dir.path());
    let from = HIDDEN_EXCESS / 3.0;
    let fitted = fit_three_steps(&bundle, start(from), &dir.path().join("density"));
    let excess = fitted
        .extension
        .density
        .as_ref()
        .expect("kept")
        .excess
        .abs();
    assert!(
        (excess - HIDDEN_EXCESS).abs() < (from - HIDDEN_EXCESS).abs() - 0.1,
        "started at {from}, ended at {excess}, hidden {HIDDEN_EXCESS}"
    );
}

/// Issue 6: the fit's gradients of the extension's parameters (a density
/// gradient's excess and axis, total mass kept; a stiff ball's log factor) against
/// central differences of the training loss, full window. The world runs
/// in f32: the loss (≈ 8e-5 m²) moves by ≈ 1e-7 over the steps below, and
/// f32 rounding of positions leaves ≈ 1e-3 of that as noise, hence
/// `LOSS_FD_RTOL` (measured: 0.2 % for the excess, 0.1 % for the ball).
/// The ball is twice as stiff: at 4–8× the stiffest P-wave outruns the
/// substep and `World::new` refines it, a jump in the loss every few
/// percent of the factor that a finite difference would straddle (the
/// analytic gradient is that of a fixed substep count); the check asserts
/// that its three worlds share one.
///
/// The axis has its own tolerance and a shorter step: its gradient is that
/// of fixed end particles (`density_axis_gradient`, checked exactly in f64
/// in dm-model), and turning the axis switches which particle is an end, a
/// kink the finite difference averages over. Measured on this clip since
/// grid damping became a rate: analytic 5.04e-8, central differences
/// 5.48e-8 at step 0.005, 4.42e-8 at 0.01, 4.17e-8 at 0.02; least-squares
/// slopes over ±0.02, 4.3–4.7e-8.
#[test]
fn extension_gradients_match_finite_differences_of_the_train_loss() {
    const LOSS_FD_RTOL: f64 = 0.02;
    const AXIS_LOSS_FD_RTOL: f64 = 0.15;
    let dir = tempfile::tempdir().expect("temp dir");
    let (bundle, start) = density_start(dir.path());
    let frames = dm_fit::material_fit::fit_frames(
        &bundle,
        &dm_fit::material_fit::MaterialFitConfig::default(),
    );
    let loss_and_gradient = |model: &WorldModel| {
        dm_fit::material_fit::loss_and_gradient(model, &bundle, frames, usize::MAX, None)
            .expect("loss")
    };
    let substeps = |model: &WorldModel| model.world().expect("world").config().substeps_per_frame;
    let check_within =
        |tolerance: f64, name: &str, analytic: f64, minus: f64, plus: f64, step: f64| {
            let numeric = (plus - minus) / (2.0 * step);
            let rel = (analytic - numeric).abs() / numeric.abs();
            assert!(
                rel < tolerance,
                "{name}: {analytic:e} vs finite differences {numeric:e}"
            );
        };
    let check = |name: &str, analytic: f64, minus: f64, plus: f64, step: f64| {
        check_within(LOSS_FD_RTOL, name, analytic, minus, plus, step)
    };
    let step = 0.05;
    let at = |excess: f64| loss_and_gradient(&start(excess)).0;
    let (_, grads) = loss_and_gradient(&start(HIDDEN_EXCESS));
    for d in [-step, step] {
        assert_eq!(
            substeps(&start(HIDDEN_EXCESS + d)),
            substeps(&start(HIDDEN_EXCESS))
        );
    }
    let sign = start(1.0).extension.density.expect("gradient").excess;
    check(
        "density excess",
        sign * grads.extension.density_excess,
        at(HIDDEN_EXCESS - step),
        at(HIDDEN_EXCESS + step),
        step,
    );
    // The axis, turned sideways (its gradient is perpendicular to it).
    let turned = |h: f64| {
        let mut model = start(HIDDEN_EXCESS);
        let density = model.extension.density.clone().expect("gradient");
        let axis = [density.axis[0], density.axis[1] + h, density.axis[2]];
        model
            .extension
            .set_density_axis(&model.particles, axis, &mut model.physics.density);
        model
    };
    let step = 0.005;
    check_within(
        AXIS_LOSS_FD_RTOL,
        "density axis",
        grads.extension.density_axis[1],
        loss_and_gradient(&turned(-step)).0,
        loss_and_gradient(&turned(step)).0,
        step,
    );

    let mut model = start(0.0);
    model.extension.density = None;
    let centre = model.particles[model.particles.len() / 2];
    let with_ball = |log_factor: f64| {
        let mut m = model.clone();
        m.extension.stiff_ball = Some(dm_model::extension::StiffBall {
            centre,
            radius: 0.03,
            factor: log_factor.exp(),
        });
        m
    };
    let log_factor = 2f64.ln();
    let (_, grads) = loss_and_gradient(&with_ball(log_factor));
    let step = 0.05;
    for d in [-step, step] {
        assert_eq!(
            substeps(&with_ball(log_factor + d)),
            substeps(&with_ball(log_factor))
        );
    }
    check(
        "stiff ball ln factor",
        grads.extension.stiffness_log_factor,
        loss_and_gradient(&with_ball(log_factor - step)).0,
        loss_and_gradient(&with_ball(log_factor + step)).0,
        step,
    );
}
