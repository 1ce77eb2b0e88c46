//! Where do the observed tracks put E, ν and the gains once the optimiser
//! is not the question? Levenberg–Marquardt on the homogeneous
//! directions (ln E, ν, ln k_p, ln k_d) of the bundle's model, by
//! central-difference Jacobians of whole rollouts over the training frames
//! (`dm_fit::identifiability::gauss_newton_step`): the least-squares fit of
//! the tracks, each track's constant offset free.
//!
//!     cargo run --release -p dm-studies --example global_refit -- \
//!         SCENE SCENE.truth.json [--start truth|untrained|MODEL_DIR] [--grasp-radius R] [--kp K] [--kd K] [--parameters ln_E,nu,ln_kp,ln_kd] [--steps N] [--out DIR]
//!
//! `truth` starts from the true material with the truth's grip; a grasp
//! radius or gains, when given, replace the start's.

use anyhow::{Context, Result};
use clap::Parser;
use dm_fit::identifiability::{
    Parameter, centred_track_cost, gauss_newton_step, moved_by, track_jacobian,
};
use dm_fit::run::FitOptions;
use dm_model::WorldModel;
use dm_studies::fit_support;
use std::path::PathBuf;

#[derive(Parser)]
struct Args {
    bundle: PathBuf,
    truth: PathBuf,
    /// `truth`, `untrained`, or a fitted model directory.
    #[arg(long, default_value = "truth")]
    start: String,
    #[command(flatten)]
    grip: fit_support::GripOverride,
    #[command(flatten)]
    scene: fit_support::SceneOverride,
    /// Parameters to refit (ln_E, nu, ln_kp, ln_kd); the rest stay.
    #[arg(long, value_delimiter = ',', default_value = "ln_E,nu,ln_kp,ln_kd")]
    parameters: Vec<String>,
    /// Write the refitted model's model.json here (for dm-sim --model-dir).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Jacobian evaluations.
    #[arg(long, default_value_t = 4)]
    steps: usize,
    #[command(flatten)]
    fit: FitOptions,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let (mut bundle, truth) = fit_support::open_scene(&args.bundle, &args.truth)?;
    args.scene.apply(&mut bundle, &truth)?;
    let untrained = WorldModel::from_bundle(&bundle, &args.fit.model)?;
    let mut model = match args.start.as_str() {
        "truth" => {
            let mut m = fit_support::with_true_material(&untrained, &truth);
            m.actuator = dm_synth::truth::TRUTH_GRIP;
            m
        }
        "untrained" => untrained,
        dir => dm_bundle::read_json::<WorldModel>(&PathBuf::from(dir).join("model.json"))
            .with_context(|| format!("reading the model in {dir}"))?,
    };
    args.grip.apply(&mut model.actuator);
    let frames = bundle.meta.split.train[1];
    let parameters: Vec<(Parameter, f64)> = Parameter::ALL
        .iter()
        .filter(|p| args.parameters.iter().any(|name| name == p.name()))
        .map(|&p| (p, p.default_step()))
        .collect();
    anyhow::ensure!(
        parameters.len() == args.parameters.len(),
        "--parameters: unknown name in {:?} (known: ln_E, nu, ln_kp, ln_kd)",
        args.parameters
    );
    let names: Vec<Parameter> = parameters.iter().map(|p| p.0).collect();
    let report = |m: &WorldModel, cost: f64, note: &str| {
        let (e, nu) = m.material_medians();
        println!(
            "| {note} | {:.3e} ({:+.1} %) | {nu:.3} ({:+.3}) | {:.3e} | {:.3e} | {:.4e} |",
            e,
            100.0 * (e / truth.material.e_pa - 1.0),
            nu - truth.material.nu,
            m.actuator.kp,
            m.actuator.kd,
            cost
        );
    };
    println!(
        "\n{} — start {}, grasp radius {} m\n",
        args.bundle.display(),
        args.start,
        model.actuator.grasp_radius
    );
    println!("| step | E (vs truth) | ν (vs truth) | k_p | k_d | centred track SSE (m²) |");
    println!("|---|---|---|---|---|---|");
    let mut damping = 1e-3;
    for step in 0..args.steps {
        let jacobian = track_jacobian(&model, &bundle, frames, &parameters, &mut |label| {
            eprintln!("step {step}: rollout {label}");
        })?;
        let cost = jacobian.centred_cost();
        report(&model, cost, &format!("{step}"));
        let mut accepted = false;
        for _ in 0..4 {
            let Some((delta, _)) = gauss_newton_step(&jacobian, damping) else {
                break;
            };
            // Trust region: at most four half-steps of the secant per move.
            let largest = delta
                .iter()
                .zip(&parameters)
                .map(|(d, p)| d.abs() / (4.0 * p.1))
                .fold(1.0, f64::max);
            let delta: Vec<f64> = delta.iter().map(|d| d / largest).collect();
            let trial = moved_by(&model, &names, &delta);
            let trial_cost = centred_track_cost(&trial, &bundle, frames)?;
            if trial_cost < cost {
                model = trial;
                damping = (damping / 3.0).max(1e-6);
                accepted = true;
                break;
            }
            damping *= 10.0;
        }
        if !accepted {
            println!("no descent at step {step}; stopping");
            break;
        }
    }
    let cost = centred_track_cost(&model, &bundle, frames)?;
    report(&model, cost, "end");
    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        dm_bundle::write_json_atomic(&dir.join("model.json"), &model)
            .with_context(|| format!("writing the model into {}", dir.display()))?;
    }
    Ok(())
}
