//! Does the model weigh the object right? E is measured
//! against inertia and gravity, so a model mass off by some factor
//! shifts the recovered E by about the same factor. Compares the
//! bundle model's particle count × particle volume with the truth's.
//!
//!     cargo run --release -p dm-studies --example mass_check -- SCENE SCENE.truth.json

use anyhow::Result;
use clap::Parser;
use dm_fit::run::FitOptions;
use dm_model::WorldModel;
use dm_studies::fit_support;
use std::path::PathBuf;

#[derive(Parser)]
struct Args {
    bundle: PathBuf,
    truth: PathBuf,
    #[command(flatten)]
    fit: FitOptions,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let (bundle, truth) = fit_support::open_scene(&args.bundle, &args.truth)?;
    let model = WorldModel::from_bundle(&bundle, &args.fit.model)?;
    let cloud = dm_synth::shapes::ParticleCloud::fill(
        truth.config.preset,
        truth.config.truth_particles,
        // The lattice's jitter seed moves the volume by well under 1 %.
        truth.config.seed,
    );
    let model_volume = model.particles.len() as f64 * model.particle_volume;
    let truth_volume = cloud.len() as f64 * cloud.particle_volume();
    println!(
        "{}: model {} particles × {:.3e} m³ = {:.4e} m³; truth {} × {:.3e} m³ = {:.4e} m³; model / truth {:.3}",
        args.bundle.display(),
        model.particles.len(),
        model.particle_volume,
        model_volume,
        cloud.len(),
        cloud.particle_volume(),
        truth_volume,
        model_volume / truth_volume
    );
    Ok(())
}
