//! Where the held-out error of a material-recovery scene comes from:
//! rolls out the bundle's model with the untrained, the true
//! and (optionally) the fitted parameters, and the model's own particles
//! carried by the true motion — the error no parameter choice can remove.
//! Each is scored twice: against the bundle's observed tracks (the
//! benchmark protocol, sensor noise included) and against the true surface
//! (every truth surface particle, noise-free).
//!
//!     cargo run --release -p dm-studies --example recovery_floor -- \
//!         SCENE SCENE.truth.json [--fitted MODEL_DIR ...] [--gain-search DIR]
//!
//! `--gain-search DIR` also runs dm-fit's CMA-ES gain search (its flags
//! apply: `--gain-evals`, `--seed`) from the true material, writing that
//! fit to DIR. Prints one markdown row per variant.

use anyhow::{Context, Result};
use clap::Parser;
use dm_bundle::{Bundle, Split, Tracks};
use dm_fit::run::{FitOptions, run_fit_from};
use dm_model::WorldModel;
use dm_model::metrics::{frame_errors, split_mean};
use dm_mpm::neighbors::PointIndex;
use dm_studies::fit_support;
use dm_synth::TruthFile;
use ndarray::{Array2, Array3};
use std::path::PathBuf;

#[derive(Parser)]
struct Args {
    bundle: PathBuf,
    truth: PathBuf,
    /// Fitted model directories to score beside the references.
    #[arg(long)]
    fitted: Vec<PathBuf>,
    /// Run the gain search from the true material, writing to this directory.
    #[arg(long)]
    gain_search: Option<PathBuf>,
    #[command(flatten)]
    fit: FitOptions,
}

/// A scored rollout.
struct Variant {
    name: String,
    rollout: Vec<Vec<[f32; 3]>>,
    surface_count: usize,
}

/// One markdown table of every variant's errors against `reference`.
fn table(title: &str, variants: &[Variant], reference: &Tracks, split: Split) {
    println!("\n{title}\n");
    println!(
        "| variant | frame-0 Chamfer (mm) | train Chamfer | held-out Chamfer | train Track | held-out Track |"
    );
    println!("|---|---|---|---|---|---|");
    for v in variants {
        let errors = frame_errors(&v.rollout, v.surface_count, reference);
        println!(
            "| {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} |",
            v.name,
            1e3 * errors.chamfer[0],
            1e3 * split_mean(&errors.chamfer, split.train),
            1e3 * split_mean(&errors.chamfer, split.test),
            1e3 * split_mean(&errors.track, split.train),
            1e3 * split_mean(&errors.track, split.test),
        );
    }
}

/// Every truth surface particle as an always-visible, exact track.
fn true_surface(truth: &dm_synth::GroundTruth) -> Tracks {
    let ids: Vec<usize> = (0..truth.cloud.len())
        .filter(|&i| truth.cloud.on_surface[i])
        .collect();
    let frames = truth.frames.len();
    let points = Array3::from_shape_fn((frames, ids.len(), 3), |(t, k, a)| {
        truth.frames[t][ids[k]][a]
    });
    Tracks {
        object_points: points,
        object_visibility: Array2::from_elem((frames, ids.len()), true),
        object_motion_valid: Array2::from_elem((frames, ids.len()), true),
        hand_points: Array3::zeros((frames, 0, 3)),
        hand_visibility: Array2::from_elem((frames, 0), false),
    }
}

/// The model's particles moved as the nearest truth particle at frame 0
/// moves: perfect dynamics on the model's particle set.
fn carried_by_truth(model: &WorldModel, truth: &dm_synth::GroundTruth) -> Vec<Vec<[f32; 3]>> {
    let first: Vec<[f64; 3]> = truth.frames[0].iter().map(|p| p.map(f64::from)).collect();
    let index = PointIndex::new(&first);
    let nearest: Vec<usize> = model
        .particles
        .iter()
        .map(|p| index.nearest(p, 1).first().map_or(0, |n| n.0))
        .collect();
    truth
        .frames
        .iter()
        .map(|frame| {
            model
                .particles
                .iter()
                .zip(&nearest)
                .map(|(p, &j)| {
                    std::array::from_fn(|a| {
                        (p[a] + f64::from(frame[j][a] - truth.frames[0][j][a])) as f32
                    })
                })
                .collect()
        })
        .collect()
}

fn main() -> Result<()> {
    let args = Args::parse();
    let bundle = Bundle::open(&args.bundle)
        .with_context(|| format!("reading bundle {}", args.bundle.display()))?;
    let truth_file: TruthFile = dm_bundle::read_json(&args.truth)
        .with_context(|| format!("reading {}", args.truth.display()))?;
    let frames = bundle.frame_count();
    let untrained = WorldModel::from_bundle(&bundle, &args.fit.model)?;
    let mut variants = Vec::new();
    let mut add = |name: String, model: &WorldModel| -> Result<()> {
        variants.push(Variant {
            name,
            rollout: model.rollout(&bundle, frames, &mut |_| {})?,
            surface_count: model.surface_count,
        });
        Ok(())
    };
    add("untrained".into(), &untrained)?;

    let true_material = fit_support::with_true_material(&untrained, &truth_file);
    add("true E, ν; default gains".into(), &true_material)?;

    // The truth's grip, on the model's hand tracks.
    let mut true_grip = true_material.clone();
    true_grip.actuator = dm_synth::truth::TRUTH_GRIP;
    add("true E, ν; truth's grip".into(), &true_grip)?;
    // How sharply the data pins the material: the bar's edges (E ±25 %,
    // ν ±0.05) with everything else true.
    for (e_factor, nu_shift) in [(0.75, 0.0), (1.25, 0.0), (1.0, -0.05), (1.0, 0.05)] {
        let shifted = fit_support::with_material(&true_grip, &truth_file, e_factor, nu_shift);
        add(
            format!("E ×{e_factor}, ν {nu_shift:+}; truth's grip"),
            &shifted,
        )?;
    }

    if let Some(dir) = &args.gain_search {
        let mut options = args.fit.clone();
        options.iters = 0;
        options.stage2_iters = 0;
        options.residual_iters = 0;
        options.rgb_iters = 0;
        run_fit_from(&bundle, &options, true_material.clone(), dir, &mut |_| {})?;
        let searched: WorldModel = dm_bundle::read_json(&dir.join("model.json"))?;
        let name = format!(
            "true E, ν; searched gains ({:.2e}, {:.2e})",
            searched.actuator.kp, searched.actuator.kd
        );
        add(name, &searched)?;
    }
    for dir in &args.fitted {
        let fitted: WorldModel = dm_bundle::read_json(&dir.join("model.json"))
            .with_context(|| format!("reading the fitted model in {}", dir.display()))?;
        let (e, nu) = fitted.material_medians();
        let name = format!(
            "{} (E {e:.3e}, ν {nu:.3}, gains {:.2e}, {:.2e})",
            dir.display(),
            fitted.actuator.kp,
            fitted.actuator.kd
        );
        add(name, &fitted)?;
    }
    let truth = dm_synth::simulate_truth(&truth_file.config, &mut |_, _, _| {})?;
    variants.push(Variant {
        name: "model particles carried by the true motion".into(),
        rollout: carried_by_truth(&untrained, &truth),
        surface_count: untrained.surface_count,
    });
    let split = bundle.meta.split;
    table(
        "Against the observed tracks (benchmark protocol):",
        &variants,
        &bundle.tracks,
        split,
    );
    table(
        "Against the true surface (noise-free):",
        &variants,
        &true_surface(&truth),
        split,
    );
    Ok(())
}
