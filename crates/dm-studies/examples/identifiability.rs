//! Can a material-recovery clip determine E and ν at all? The
//! Cramér–Rao lower bound of the clip's observed training tracks
//! (`dm_fit::identifiability`), at the scene's true material with the
//! truth's grip (or at a fitted model), over ln E, ν, ln k_p and ln k_d:
//! once with every parameter estimated, as dm-fit estimates them, and
//! once with the gains known.
//!
//!     cargo run --release -p dm-studies --example identifiability -- \
//!         SCENE SCENE.truth.json [--at-model MODEL_DIR] [--json OUT.json]
//!
//! Noise defaults to what `dm-synth` adds to its tracks (1.5 mm per axis
//! and frame, a 1 mm constant bias per track and axis).

use anyhow::{Context, Result};
use clap::Parser;
use dm_fit::identifiability::{TrackNoise, identifiability_at};
use dm_fit::run::FitOptions;
use dm_model::WorldModel;
use dm_studies::fit_support;
use dm_synth::sensor::SensorNoise;
use std::path::PathBuf;

#[derive(Parser)]
struct Args {
    bundle: PathBuf,
    truth: PathBuf,
    /// Take the bound at this fitted model instead of the true material
    /// with the truth's grip.
    #[arg(long)]
    at_model: Option<PathBuf>,
    /// Frames the fit sees (default: the bundle's training split).
    #[arg(long)]
    frames: Option<usize>,
    /// Track noise per axis and frame, mm (default: dm-synth's).
    #[arg(long)]
    sigma_mm: Option<f64>,
    /// Constant offset per track and axis, mm (default: dm-synth's bias).
    #[arg(long)]
    offset_sigma_mm: Option<f64>,
    /// Write the bound as JSON here too.
    #[arg(long)]
    json: Option<PathBuf>,
    #[command(flatten)]
    fit: FitOptions,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let (bundle, truth) = fit_support::open_scene(&args.bundle, &args.truth)?;
    let model = match &args.at_model {
        Some(dir) => dm_bundle::read_json::<WorldModel>(&dir.join("model.json"))
            .with_context(|| format!("reading the model in {}", dir.display()))?,
        None => {
            let untrained = WorldModel::from_bundle(&bundle, &args.fit.model)?;
            let mut model = fit_support::with_true_material(&untrained, &truth);
            model.actuator = dm_synth::truth::TRUTH_GRIP;
            model
        }
    };
    let sensor = SensorNoise::default();
    let noise = TrackNoise {
        sigma_m: args.sigma_mm.map_or(sensor.track_sigma, |v| 1e-3 * v),
        offset_sigma_m: args
            .offset_sigma_mm
            .map_or(sensor.track_bias_sigma, |v| 1e-3 * v),
    };
    let frames = args.frames.unwrap_or(bundle.meta.split.train[1]);
    let bound = identifiability_at(&model, &bundle, frames, noise, &mut |label| {
        eprintln!("rollout: {label}");
    })?;

    let (e, nu) = model.material_medians();
    println!(
        "\n{} — at E {e:.3e} Pa, ν {nu:.3}, k_p {:.3e}, k_d {:.3e}; {} frames, {} observations; noise σ {:.2} mm, offset σ {:.2} mm\n",
        args.bundle.display(),
        model.actuator.kp,
        model.actuator.kd,
        frames,
        bound.observations,
        1e3 * noise.sigma_m,
        1e3 * noise.offset_sigma_m,
    );
    println!("| parameter | step | bound σ, all estimated | bound σ, gains known | curvature |");
    println!("|---|---|---|---|---|");
    for row in &bound.parameters {
        let known = row
            .std_gains_known
            .map_or("—".to_string(), |v| format!("{v:.4}"));
        println!(
            "| {} | {} | {:.4} | {known} | {:.3} |",
            row.name, row.step, row.std_all_estimated, row.curvature
        );
    }
    println!("\ncorrelation (all estimated):\n");
    let names: Vec<&str> = bound.parameters.iter().map(|r| r.name.as_str()).collect();
    println!("| | {} |", names.join(" | "));
    println!("|---|{}", "---|".repeat(names.len()));
    for (name, row) in names.iter().zip(&bound.correlation) {
        let cells: Vec<String> = row.iter().map(|c| format!("{c:+.3}")).collect();
        println!("| {name} | {} |", cells.join(" | "));
    }
    if let Some(path) = &args.json {
        dm_bundle::write_json_atomic(path, &bound)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}
