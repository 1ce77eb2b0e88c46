//! dm-fit's stages from the bundle's model with another actuator grasp
//! radius (m): does the grip's width move the fitted material?
//!
//!     cargo run --release -p dm-studies --example fit_with_grasp_radius -- \
//!         SCENE --grasp-radius 0.014 --out DIR [dm-fit's flags]

use anyhow::{Context, Result};
use clap::Parser;
use dm_bundle::Bundle;
use dm_fit::run::{FitOptions, run_fit_from};
use dm_model::WorldModel;
use std::path::PathBuf;

#[derive(Parser)]
struct Args {
    bundle: PathBuf,
    #[arg(long)]
    grasp_radius: f64,
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    fit: FitOptions,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let bundle = Bundle::open(&args.bundle)
        .with_context(|| format!("reading bundle {}", args.bundle.display()))?;
    let mut model = WorldModel::from_bundle(&bundle, &args.fit.model)?;
    model.actuator.grasp_radius = args.grasp_radius;
    run_fit_from(&bundle, &args.fit, model, &args.out, &mut |m| {
        eprintln!("{m}")
    })
    .with_context(|| format!("fitting into {}", args.out.display()))?;
    let report: serde_json::Value = dm_bundle::read_json(&args.out.join("fit_report.json"))?;
    println!("{}", report["material"]);
    println!("{}", report["dca"]);
    Ok(())
}
