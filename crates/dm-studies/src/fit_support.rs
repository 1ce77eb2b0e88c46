//! What the material-recovery examples share: the bundle's model set to
//! the synthetic scene's true homogeneous material, the bundle's hands or
//! first-frame particles replaced by the truth's.

use dm_model::WorldModel;
use dm_synth::TruthFile;

/// `model` with the truth's homogeneous material: its E, ν and expert mix
/// on every patch (the gains and everything else kept).
pub fn with_true_material(model: &WorldModel, truth: &TruthFile) -> WorldModel {
    with_material(model, truth, 1.0, 0.0)
}

/// `model` with the truth's material, E scaled by `youngs_factor` and ν
/// moved by `poisson_shift`.
pub fn with_material(
    model: &WorldModel,
    truth: &TruthFile,
    youngs_factor: f64,
    poisson_shift: f64,
) -> WorldModel {
    let mut moved = model.clone();
    moved.params = dm_mpm::PatchParams::uniform(
        model.patches.patch_count(),
        &model.bounds,
        youngs_factor * truth.material.e_pa,
        truth.material.nu + poisson_shift,
        dm_synth::truth::HOMOGENEOUS_EXPERT_WEIGHTS.map(f64::ln),
    );
    moved
}

/// The scene bundle and its truth file, errors naming the file.
pub fn open_scene(
    bundle: &std::path::Path,
    truth: &std::path::Path,
) -> anyhow::Result<(dm_bundle::Bundle, TruthFile)> {
    use anyhow::Context;
    let opened = dm_bundle::Bundle::open(bundle)
        .with_context(|| format!("reading bundle {}", bundle.display()))?;
    let truth_file: TruthFile =
        dm_bundle::read_json(truth).with_context(|| format!("reading {}", truth.display()))?;
    Ok((opened, truth_file))
}

/// Actuator values that replace the start model's where given.
#[derive(clap::Args, Clone, Copy, Debug)]
pub struct GripOverride {
    /// Spring gain k_p (1/s²).
    #[arg(long)]
    pub kp: Option<f64>,
    /// Damper gain k_d (1/s).
    #[arg(long)]
    pub kd: Option<f64>,
    /// Grasp radius (m).
    #[arg(long)]
    pub grasp_radius: Option<f64>,
}

impl GripOverride {
    pub fn apply(&self, actuator: &mut dm_mpm::ActuatorConfig) {
        if let Some(kp) = self.kp {
            actuator.kp = kp;
        }
        if let Some(kd) = self.kd {
            actuator.kd = kd;
        }
        if let Some(radius) = self.grasp_radius {
            actuator.grasp_radius = radius;
        }
    }
}

/// What the analysis examples may replace in a synthetic scene's bundle.
#[derive(clap::Args, Clone, Copy, Debug)]
pub struct SceneOverride {
    /// Drive the hands by the truth's own anchors (no tracker noise, no
    /// dropout) instead of the bundle's recorded hand track.
    #[arg(long)]
    pub exact_hands: bool,
    /// Start the model from every truth particle at its exact first-frame
    /// position (reruns the truth simulation) instead of the bundle's
    /// noisy random half.
    #[arg(long)]
    pub exact_particles: bool,
    /// With --exact-particles: keep a seeded random subset of this many.
    #[arg(long, requires = "exact_particles")]
    pub keep_particles: Option<usize>,
    /// With --exact-particles: add this Gaussian noise (mm) to each
    /// coordinate, as dm-synth does to the bundle's particles.
    #[arg(long, requires = "exact_particles", default_value_t = 0.0)]
    pub particle_noise_mm: f64,
    /// With --exact-particles: take them from a truth simulation of the
    /// same scene filled with this many particles (a regular lattice of
    /// another spacing) instead of the scene's own.
    #[arg(long, requires = "exact_particles")]
    pub lattice_particles: Option<usize>,
    /// Seed of the --keep-particles subset (default: the scene's seed).
    #[arg(long)]
    pub subset_seed: Option<u64>,
    /// Double the bundle's first-frame particles: each adds the midpoint
    /// to a seeded random one of its 6 nearest neighbours of the same kind
    /// (surface or interior).
    #[arg(long)]
    pub densify: bool,
}

impl SceneOverride {
    pub fn apply(&self, bundle: &mut dm_bundle::Bundle, truth: &TruthFile) -> anyhow::Result<()> {
        if self.exact_hands {
            replace_hands_by_truth(bundle, truth)?;
        }
        if self.exact_particles {
            let mut source = truth.clone();
            if let Some(n) = self.lattice_particles {
                source.config.truth_particles = n;
            }
            replace_particles_by_truth(
                bundle,
                &source,
                self.keep_particles
                    .map(|n| (n, self.subset_seed.unwrap_or(truth.config.seed))),
                self.particle_noise_mm,
            )?;
        }
        if self.densify {
            densify_particles(bundle, truth.config.seed);
        }
        Ok(())
    }
}

/// See [`SceneOverride::densify`].
pub fn densify_particles(bundle: &mut dm_bundle::Bundle, seed: u64) {
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0xde75);
    let mut double = |points: &ndarray::Array2<f32>, colors: &ndarray::Array2<f32>| {
        let n = points.nrows();
        let as_f64: Vec<[f64; 3]> = (0..n)
            .map(|i| [0, 1, 2].map(|a| f64::from(points[[i, a]])))
            .collect();
        let index = dm_mpm::neighbors::PointIndex::new(&as_f64);
        let mut new_points = points.clone().into_raw_vec_and_offset().0;
        let mut new_colors = colors.clone().into_raw_vec_and_offset().0;
        for i in 0..n {
            let near = index.nearest(&as_f64[i], 7);
            if near.len() < 2 {
                continue;
            }
            let j = near[rng.random_range(1..near.len())].0;
            for a in 0..3 {
                new_points.push(0.5 * (points[[i, a]] + points[[j, a]]));
            }
            for a in 0..3 {
                new_colors.push(0.5 * (colors[[i, a]] + colors[[j, a]]));
            }
        }
        let rows = new_points.len() / 3;
        (
            ndarray::Array2::from_shape_vec((rows, 3), new_points).expect("rows of 3"),
            ndarray::Array2::from_shape_vec((rows, 3), new_colors).expect("rows of 3"),
        )
    };
    let p = &bundle.particles;
    let (surface_points, surface_colors) = double(&p.surface_points, &p.surface_colors);
    let (interior_points, interior_colors) = double(&p.interior_points, &p.interior_colors);
    bundle.particles = dm_bundle::FirstFrameParticles {
        surface_points,
        surface_colors,
        interior_points,
        interior_colors,
    };
}

/// Overwrites the bundle's hand track by the truth's scripted anchors at
/// each frame's time, every anchor visible.
pub fn replace_hands_by_truth(
    bundle: &mut dm_bundle::Bundle,
    truth: &TruthFile,
) -> anyhow::Result<()> {
    let hands = &mut bundle.tracks.hand_points;
    let (frames, anchors) = (hands.shape()[0], hands.shape()[1]);
    for t in 0..frames {
        let exact: Vec<[f64; 3]> = truth
            .hands
            .iter()
            .flat_map(|h| h.anchors_at(t as f64 / bundle.meta.fps))
            .collect();
        anyhow::ensure!(
            exact.len() == anchors,
            "the truth has {} anchors, the bundle's hand track {anchors}",
            exact.len()
        );
        for (j, p) in exact.iter().enumerate() {
            for a in 0..3 {
                hands[[t, j, a]] = p[a] as f32;
            }
        }
    }
    bundle.tracks.hand_visibility.fill(true);
    Ok(())
}

/// The truth's first frame: positions, surface flags, rest positions.
type TruthFirstFrame = (Vec<[f32; 3]>, Vec<bool>, Vec<[f64; 3]>);

/// [`TruthFirstFrame`], simulated once per process: the examples compare
/// several particle subsets of one scene.
fn truth_first_frame(truth: &TruthFile) -> anyhow::Result<&'static TruthFirstFrame> {
    static FIRST: std::sync::OnceLock<TruthFirstFrame> = std::sync::OnceLock::new();
    if let Some(first) = FIRST.get() {
        return Ok(first);
    }
    let mut progress = |stage: &str, done: usize, total: usize| {
        if done == total {
            eprintln!("{stage}: {total} done");
        }
    };
    let simulated = dm_synth::simulate_truth(&truth.config, &mut progress)?;
    Ok(FIRST.get_or_init(|| {
        (
            simulated.frames[0].clone(),
            simulated.cloud.on_surface.clone(),
            simulated.cloud.positions.clone(),
        )
    }))
}

/// Overwrites the bundle's first-frame particles by the truth's own at
/// their first-frame positions (the truth simulation is rerun): all of
/// them, or a random subset of `keep.0` seeded by `keep.1`, with
/// `noise_mm` of Gaussian noise per coordinate.
pub fn replace_particles_by_truth(
    bundle: &mut dm_bundle::Bundle,
    truth: &TruthFile,
    keep: Option<(usize, u64)>,
    noise_mm: f64,
) -> anyhow::Result<()> {
    use rand::SeedableRng;
    use rand_distr::Distribution;
    let (first, on_surface, rest) = truth_first_frame(truth)?;
    let preset = truth.config.preset;
    let ids = match keep {
        Some((n, seed)) => seeded_subset(first.len(), n, seed),
        None => (0..first.len()).collect(),
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(truth.config.seed ^ 0x9a27);
    let noise = rand_distr::Normal::new(0.0, 1e-3 * noise_mm)?;
    let moved: Vec<[f32; 3]> = (0..first.len())
        .map(|i| first[i].map(|c| c + noise.sample(&mut rng) as f32))
        .collect();
    let arrays = |surface: bool| {
        let ids: Vec<usize> = ids
            .iter()
            .copied()
            .filter(|&i| on_surface[i] == surface)
            .collect();
        let points = ndarray::Array2::from_shape_fn((ids.len(), 3), |(r, a)| moved[ids[r]][a]);
        let colors =
            ndarray::Array2::from_shape_fn((ids.len(), 3), |(r, a)| preset.albedo(rest[ids[r]])[a]);
        (points, colors)
    };
    let (surface_points, surface_colors) = arrays(true);
    let (interior_points, interior_colors) = arrays(false);
    bundle.particles = dm_bundle::FirstFrameParticles {
        surface_points,
        surface_colors,
        interior_points,
        interior_colors,
    };
    Ok(())
}

/// A seeded uniform random subset of `keep` of the indices 0..n, sorted.
/// A partial Fisher–Yates of its own rather than `rand::seq::index::sample`
/// (another draw): the subset seeds in docs/RESULTS.md name these subsets.
pub fn seeded_subset(n: usize, keep: usize, seed: u64) -> Vec<usize> {
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x5b5e);
    let mut ids: Vec<usize> = (0..n).collect();
    let keep = keep.min(n);
    for i in 0..keep {
        let j = rng.random_range(i..n);
        ids.swap(i, j);
    }
    ids.truncate(keep);
    ids.sort_unstable();
    ids
}
