//! Which term of L_dyn prefers which E? Rolls out the bundle's
//! model with the scene's true homogeneous material scaled by each factor
//! (ν and the expert mix true), with given actuators, and sums each term
//! of the training loss (track, shape, length) and their weighted total
//! over the training frames.
//!
//!     cargo run --release -p dm-studies --example loss_profile -- \
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
use dm_studies::fit_support;
use std::path::PathBuf;

#[derive(Parser)]
struct Args {
    bundle: PathBuf,
    truth: PathBuf,
    #[command(flatten)]
    grip: fit_support::GripOverride,
    #[command(flatten)]
    scene: fit_support::SceneOverride,
    /// Score the losses on a seeded random subset of this many of the
    /// model's particles (the rollout keeps them all): separates what a
    /// sparser particle set does to the dynamics from what it does to the
    /// nearest-particle losses.
    #[arg(long)]
    loss_keep: Option<usize>,
    /// Profile once per subset seed (with --exact-particles
    /// --keep-particles N): how much the optimum moves with which particles
    /// the model is given. The truth is simulated once.
    #[arg(long, value_delimiter = ',')]
    subset_seeds: Vec<u64>,
    /// Factors on the true E.
    #[arg(long, value_delimiter = ',', default_value = "0.6,0.75,1,1.25")]
    factors: Vec<f64>,
    #[command(flatten)]
    fit: FitOptions,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let (recorded, truth) = fit_support::open_scene(&args.bundle, &args.truth)?;
    let seeds: Vec<Option<u64>> = if args.subset_seeds.is_empty() {
        vec![args.scene.subset_seed]
    } else {
        args.subset_seeds.iter().map(|&s| Some(s)).collect()
    };
    for seed in seeds {
        let mut bundle = recorded.clone();
        let scene = fit_support::SceneOverride {
            subset_seed: seed,
            ..args.scene
        };
        scene.apply(&mut bundle, &truth)?;
        if let Some(seed) = seed {
            println!("\nsubset seed {seed}");
        }
        profile(&args, &bundle, &truth)?;
    }
    Ok(())
}

/// One table: the training loss terms along E.
fn profile(args: &Args, bundle: &dm_bundle::Bundle, truth: &dm_synth::TruthFile) -> Result<()> {
    let mut base = WorldModel::from_bundle(bundle, &args.fit.model)?;
    base.actuator = dm_synth::truth::TRUTH_GRIP;
    args.grip.apply(&mut base.actuator);
    let frames = bundle.meta.split.train[1];
    // Surface-first order is kept, so the subset's surface comes first too.
    let scored: Vec<usize> = match args.loss_keep {
        Some(keep) => fit_support::seeded_subset(base.particles.len(), keep, truth.config.seed),
        None => (0..base.particles.len()).collect(),
    };
    let scored_surface = scored.iter().filter(|&&i| i < base.surface_count).count();
    let first: Vec<[f64; 3]> = scored.iter().map(|&i| base.particles[i]).collect();
    let observed_first = ObservedFrame::from_tracks(&bundle.tracks, 0)?.points;
    let track = TrackMatch::new(&first, &observed_first)?;
    let length = LengthPreservation::new(&first, PairSelection::default())?;
    let embedded = EmbeddedTracks::new(&first, &observed_first);
    let terms = LossTerms {
        track: &track,
        length: &length,
        surface_count: scored_surface,
    };
    let weights = LossWeights::default();
    // How many particles the hands hold once they grasp (frame 0 → 1).
    let mut world = base.world()?;
    let (from, to, grasp) = base.hand_step(bundle, 0);
    world.step_frame(&from, &to, &grasp)?;
    eprintln!(
        "{} particles, {} held by the hands ({} couplings)",
        base.particles.len(),
        world.actuators().coupled_particle_count(),
        world.actuators().coupling_count()
    );
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
    println!(
        "| E factor | track | shape | length | L_dyn | track, offsets free | track, embedded |"
    );
    println!("|---|---|---|---|---|---|---|");
    for &factor in &args.factors {
        let model = fit_support::with_material(&base, truth, factor, 0.0);
        let rollout = model.rollout(bundle, frames, &mut |_| {})?;
        let mut sums = [0.0; 4];
        let mut embedded_sum = 0.0;
        // Per track: Σ r, Σ |r|², count of valid frames (r = predicted − observed).
        let mut residuals = vec![([0.0f64; 3], 0.0f64, 0usize); track.point_count()];
        for (t, frame) in rollout.iter().enumerate().skip(1) {
            let predicted: Vec<[f64; 3]> =
                scored.iter().map(|&i| frame[i].map(f64::from)).collect();
            let observed = ObservedFrame::from_tracks(&bundle.tracks, t)?;
            embedded_sum += embedded.loss(&predicted, &observed) / (frames - 1) as f64;
            for (k, &p) in track.particles().iter().enumerate() {
                if observed.track_valid[k] {
                    let r: [f64; 3] =
                        std::array::from_fn(|a| predicted[p][a] - observed.points[k][a]);
                    let entry = &mut residuals[k];
                    for a in 0..3 {
                        entry.0[a] += r[a];
                    }
                    entry.1 += r.iter().map(|c| c * c).sum::<f64>();
                    entry.2 += 1;
                }
            }
            let loss = frame_loss(&weights, &terms, &predicted, &observed)?;
            for (sum, v) in
                sums.iter_mut()
                    .zip([loss.track, loss.shape, loss.length, loss.total.value])
            {
                *sum += v / (frames - 1) as f64;
            }
        }
        // Each track's constant offset removed: Σ|r|² − |Σr|²/n per track.
        let (centred, valid) =
            residuals
                .iter()
                .filter(|r| r.2 > 0)
                .fold((0.0, 0usize), |(sum, count), (s, s2, n)| {
                    let mean_part = s.iter().map(|c| c * c).sum::<f64>() / *n as f64;
                    (sum + s2 - mean_part, count + n)
                });
        println!(
            "| {factor} | {:.4e} | {:.4e} | {:.4e} | {:.4e} | {:.4e} | {:.4e} |",
            sums[0],
            sums[1],
            sums[2],
            sums[3],
            centred / valid.max(1) as f64,
            embedded_sum
        );
    }
    Ok(())
}

/// Tracked points embedded in the particle cloud at frame 0: each follows
/// the inverse-distance-weighted mean of its 8 nearest particles plus its
/// frame-0 offset from that mean (an alternative to the nearest particle).
struct EmbeddedTracks {
    neighbours: Vec<Vec<(usize, f64)>>,
    offsets: Vec<[f64; 3]>,
}

impl EmbeddedTracks {
    fn new(particles: &[[f64; 3]], observed: &[[f64; 3]]) -> Self {
        let index = dm_mpm::neighbors::PointIndex::new(particles);
        let neighbours: Vec<Vec<(usize, f64)>> = observed
            .iter()
            .map(|o| {
                let near = index.nearest(o, 8);
                let weights: Vec<f64> = near.iter().map(|&(_, d)| 1.0 / (d + 1e-4)).collect();
                let total: f64 = weights.iter().sum();
                near.iter()
                    .zip(&weights)
                    .map(|(&(i, _), w)| (i, w / total))
                    .collect()
            })
            .collect();
        let offsets = observed
            .iter()
            .zip(&neighbours)
            .map(|(o, near)| {
                let mean = weighted_mean(particles, near);
                std::array::from_fn(|a| o[a] - mean[a])
            })
            .collect();
        Self {
            neighbours,
            offsets,
        }
    }

    fn position(&self, particles: &[[f64; 3]], k: usize) -> [f64; 3] {
        let mean = weighted_mean(particles, &self.neighbours[k]);
        std::array::from_fn(|a| mean[a] + self.offsets[k][a])
    }

    /// Mean squared distance over the frame's valid tracks.
    fn loss(&self, predicted: &[[f64; 3]], observed: &ObservedFrame) -> f64 {
        let (sum, count) = (0..self.neighbours.len())
            .filter(|&k| observed.track_valid[k])
            .fold((0.0, 0usize), |(sum, count), k| {
                let p = self.position(predicted, k);
                let d: f64 = (0..3).map(|a| (p[a] - observed.points[k][a]).powi(2)).sum();
                (sum + d, count + 1)
            });
        sum / count.max(1) as f64
    }
}

/// Σ w_i x_i over `(i, w_i)`.
fn weighted_mean(particles: &[[f64; 3]], weights: &[(usize, f64)]) -> [f64; 3] {
    let mut sum = [0.0; 3];
    for &(i, w) in weights {
        for a in 0..3 {
            sum[a] += w * particles[i][a];
        }
    }
    sum
}
