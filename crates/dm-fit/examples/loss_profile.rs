//! Which term of L_dyn prefers which E (issue 3)? Rolls out the bundle's
//! model with the scene's true homogeneous material scaled by each factor
//! (ν and the expert mix true), with given actuators, and sums each term
//! of the training loss (track, shape, length) and their weighted total
//! over the training frames.
//!
//!     cargo run --release -p dm-fit --example loss_profile -- \
//!         SCENE SCENE.truth.json [--kp K --kd K --grasp-radius R] [--factors 0.6,0.75,1,1.25]
//!
//! Without gains the truth's grip is used.

use anyhow::Result;
use clap::Parser;
use dm_fit::loss::{
    LengthPreservation, LossTerms, LossWeights, ObservedFrame, PairSelection, TrackMatch,
    frame_loss,
};
use dm_fit::run::FitOptions;
use dm_model::WorldModel;
use std::path::PathBuf;

mod support;

#[derive(Parser)]
struct Args {
    bundle: PathBuf,
    truth: PathBuf,
    #[command(flatten)]
    grip: support::GripOverride,
    /// Factors on the true E.
    #[arg(long, value_delimiter = ',', default_value = "0.6,0.75,1,1.25")]
    factors: Vec<f64>,
    #[command(flatten)]
    fit: FitOptions,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let (bundle, truth) = support::open_scene(&args.bundle, &args.truth)?;
    let mut base = WorldModel::from_bundle(&bundle, &args.fit.model)?;
    base.actuator = dm_synth::truth::TRUTH_GRIP;
    args.grip.apply(&mut base.actuator);
    let frames = bundle.meta.split.train[1];
    let track = TrackMatch::new(
        &base.particles,
        &ObservedFrame::from_tracks(&bundle.tracks, 0)?.points,
    )?;
    let length = LengthPreservation::new(&base.particles, PairSelection::default())?;
    let terms = LossTerms {
        track: &track,
        length: &length,
        surface_count: base.surface_count,
    };
    let weights = LossWeights::default();
    println!(
        "\n{} — k_p {:.3e}, k_d {:.3e}, grasp radius {} m; weights track {}, shape {}, length {}\n",
        args.bundle.display(),
        base.actuator.kp,
        base.actuator.kd,
        base.actuator.grasp_radius,
        weights.track,
        weights.shape,
        weights.length
    );
    println!("| E factor | track | shape | length | L_dyn |");
    println!("|---|---|---|---|---|");
    for &factor in &args.factors {
        let model = support::with_material(&base, &truth, factor, 0.0);
        let rollout = model.rollout(&bundle, frames, &mut |_| {})?;
        let mut sums = [0.0; 4];
        for (t, frame) in rollout.iter().enumerate().skip(1) {
            let predicted: Vec<[f64; 3]> = frame.iter().map(|p| p.map(f64::from)).collect();
            let observed = ObservedFrame::from_tracks(&bundle.tracks, t)?;
            let loss = frame_loss(&weights, &terms, &predicted, &observed)?;
            for (sum, v) in
                sums.iter_mut()
                    .zip([loss.track, loss.shape, loss.length, loss.total.value])
            {
                *sum += v / (frames - 1) as f64;
            }
        }
        println!(
            "| {factor} | {:.4e} | {:.4e} | {:.4e} | {:.4e} |",
            sums[0], sums[1], sums[2], sums[3]
        );
    }
    Ok(())
}
