//! `dm-synth`: realistic synthetic "measured" scenes with known ground
//! truth — our test bed, since no real dataset can be downloaded here.
//!
//! The truth is simulated at higher fidelity than the model's defaults
//! (a 48³ grid instead of 32³, half the substep or less, twice the
//! particles) with a spatially varying material, so the model class never
//! contains it exactly. A sensor model turns it into what a 3-camera
//! RGB-D rig and trackers would give: shaded textured RGB, noisy depth
//! with holes, masks, noisy tracks with occlusion and dropouts, and sparse
//! noisy hand tracks. The truth goes to a JSON file outside the bundle.

pub mod actions;
pub mod effects;
mod field;
pub mod foreign;
pub mod foreign_plant;
pub mod sensor;
pub mod shapes;
pub mod truth;

pub use actions::Action;
pub use effects::{EffectName, EffectSpec, draw_hidden_effect, draw_hidden_effect_among};
pub use foreign::Engine;
pub use shapes::Preset;
pub use truth::{
    GroundTruth, TRUTH_VERSION, TruthFile, clip_hand_anchors, first_truth_version, plant_world,
    simulate_truth,
};

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Why a scene could not be generated.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error("invalid option `{option}`: {problem}")]
    InvalidOption { option: String, problem: String },
    #[error("ground-truth simulation failed: {0}")]
    Simulation(#[from] dm_mpm::SimError),
    #[error(transparent)]
    Bundle(#[from] dm_bundle::BundleError),
    #[error("foreign-physics engine: {0}")]
    Engine(String),
    #[error("writing the capture: {0}")]
    Capture(String),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// The options of one synthetic scene: the CLI of `dm-synth` and the run
/// record stored in the truth file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct SynthConfig {
    /// Object preset.
    #[arg(long, value_enum)]
    pub preset: Preset,
    /// Seed of everything random in the scene.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Hand interaction; drawn from the seed when omitted.
    #[arg(long, value_enum)]
    pub action: Option<Action>,
    /// Add a second hand that holds the opposite side still.
    #[arg(long)]
    pub two_hands: bool,
    /// Hidden physical effect, NAME[:MAGNITUDE].
    #[arg(long)]
    pub effect: Option<EffectSpec>,
    /// Make the true material one homogeneous E and ν (for recovery tests).
    #[arg(long)]
    pub homogeneous: bool,
    /// Recorded video frames (30 fps).
    #[arg(long, default_value_t = 72)]
    pub frames: usize,
    /// Image width of each camera.
    #[arg(long, default_value_t = 320)]
    pub width: u32,
    /// Image height of each camera.
    #[arg(long, default_value_t = 240)]
    pub height: u32,
    /// Particles of the ground-truth simulation.
    #[arg(long, default_value_t = 16_000)]
    pub truth_particles: usize,
    /// Tracked object points written to the bundle.
    #[arg(long, default_value_t = 400)]
    pub tracks: usize,
    /// First-frame particles written to the bundle (what dm-prep would fill).
    #[arg(long, default_value_t = 8_000)]
    pub bundle_particles: usize,
    /// Write the exact truth as the bundle's object tracks (no tracker
    /// noise, bias or dropout): a reference for scoring a capture's tracks.
    #[arg(long)]
    #[serde(default)]
    pub exact_tracks: bool,
    /// Hand tracks without tracker error (the scripted anchors, the lagged
    /// ones for `actuator_lag`), every frame seen: a reference for what
    /// hand-track noise costs.
    #[arg(long)]
    #[serde(default)]
    pub exact_hands: bool,
    /// Physics engine of the truth: dm-mpm, or MuJoCo's flex as foreign
    /// physics (a Python with `mujoco`, named by DM_MUJOCO_PYTHON).
    #[arg(long, value_enum, default_value_t = Engine::Mpm)]
    #[serde(default)]
    pub engine: Engine,
}

impl SynthConfig {
    /// Defaults for a preset (as the CLI gives them).
    pub fn new(preset: Preset, seed: u64) -> Self {
        Self {
            preset,
            seed,
            action: None,
            two_hands: false,
            effect: None,
            homogeneous: false,
            frames: 72,
            width: 320,
            height: 240,
            truth_particles: 16_000,
            tracks: 400,
            bundle_particles: 8_000,
            exact_tracks: false,
            exact_hands: false,
            engine: Engine::Mpm,
        }
    }

    /// A scene small enough for tests (seconds to generate): 14 frames of
    /// 48×36 images, 2000 truth particles.
    pub fn tiny(preset: Preset, seed: u64) -> Self {
        Self {
            frames: 14,
            width: 48,
            height: 36,
            truth_particles: 2000,
            tracks: 60,
            bundle_particles: 800,
            ..Self::new(preset, seed)
        }
    }

    /// 10 frames (the fewest dm-synth makes) and 400 particles: for tests
    /// of the GPU path under the driver's emulator, which runs the kernels
    /// far slower than the CPU path does its loops.
    pub fn smallest(preset: Preset, seed: u64) -> Self {
        Self {
            frames: 10,
            truth_particles: 800,
            bundle_particles: 400,
            ..Self::tiny(preset, seed)
        }
    }

    /// The short scene the diagnosis tests and evaluation use:
    /// 36 frames (1.2 s; the last 11 held out) of 48×36 images, 3000 truth
    /// particles, 120 tracks — a fit and a diagnosis take about a minute
    /// each on 2 cores.
    pub fn diagnosis(preset: Preset, seed: u64) -> Self {
        Self {
            frames: 36,
            width: 48,
            height: 36,
            truth_particles: 3000,
            tracks: 120,
            bundle_particles: 1000,
            ..Self::new(preset, seed)
        }
    }

    pub fn validate(&self) -> Result<(), SynthError> {
        let bad = |option: &str, problem: &str| {
            Err(SynthError::InvalidOption {
                option: option.into(),
                problem: problem.into(),
            })
        };
        if self.frames < 10 {
            return bad(
                "--frames",
                "need at least 10 frames (train and test splits)",
            );
        }
        if self.width < 16 || self.height < 16 || self.width > 4096 || self.height > 4096 {
            return bad("--width/--height", "image size must be within 16..4096");
        }
        if self.truth_particles < 500 {
            return bad("--truth-particles", "need at least 500 particles");
        }
        if self.tracks == 0 {
            return bad("--tracks", "need at least one tracked point");
        }
        if self.bundle_particles < 100 {
            return bad("--bundle-particles", "need at least 100 particles");
        }
        if self.engine == Engine::Mujoco {
            foreign::check_effect(self)?;
        }
        Ok(())
    }

    /// The action actually used (drawn from the seed when not given).
    pub fn resolved_action(&self) -> Action {
        self.action
            .unwrap_or(Action::ALL[(splitmix(self.seed ^ 0xac71) % 4) as usize])
    }
}

/// A well-mixed 64-bit hash, used to derive independent sub-seeds.
pub(crate) fn splitmix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
    x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    x ^ (x >> 31)
}

/// Progress report: stage name, done, total.
pub type Progress<'a> = &'a mut dyn FnMut(&str, usize, usize);

/// Simulates the truth and writes the bundle to `out` (atomically) and the
/// truth file to `truth_path`.
pub fn generate(
    config: &SynthConfig,
    out: &std::path::Path,
    truth_path: &std::path::Path,
    progress: Progress<'_>,
) -> Result<TruthFile, SynthError> {
    generate_with_capture(config, out, truth_path, None, progress)
}

/// [`generate`], also handing the raw capture (colour, depth) to `capture`.
pub fn generate_with_capture(
    config: &SynthConfig,
    out: &std::path::Path,
    truth_path: &std::path::Path,
    capture: Option<&mut dyn sensor::CaptureSink>,
    progress: Progress<'_>,
) -> Result<TruthFile, SynthError> {
    config.validate()?;
    let (truth, record) = match config.engine {
        Engine::Mpm => {
            let truth = simulate_truth(config, progress)?;
            let record = truth.truth_file(config);
            (truth, record)
        }
        Engine::Mujoco => {
            let foreign = foreign::simulate_foreign(config, progress)?;
            let mut record = foreign.truth.truth_file(config);
            record.engine = Some(foreign.engine);
            record.effect_displacement_m = foreign.effect_displacement_m;
            (foreign.truth, record)
        }
    };
    sensor::write_bundle(config, &truth, out, capture, progress)?;
    dm_bundle::write_json_atomic(truth_path, &record)?;
    Ok(record)
}
