//! `dm-plan`'s options: the command line and the run record in plan.json.

use std::path::PathBuf;

use dm_model::device::Device;
use serde::Serialize;

use crate::{PlanError, invalid};

/// Which optimiser searches the knots.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Optimizer {
    /// Sampling only (MPPI).
    Mppi,
    /// Adam through the simulator's adjoint only.
    Gradient,
    /// MPPI, then gradient refinement of its best plan.
    MppiGradient,
}

/// How a plan is searched: the horizon and knots, the optimisers and the
/// planning world. dm-plan's flags, and what a plan from a live
/// simulation takes.
#[derive(Clone, Debug, Serialize, clap::Args)]
pub struct SearchOptions {
    /// Search: MPPI, gradient refinement through the simulator, or both in turn.
    #[arg(long, value_enum, default_value_t = Optimizer::MppiGradient)]
    pub optimizer: Optimizer,
    /// Frames the plan spans.
    #[arg(long, default_value_t = 120)]
    pub horizon: usize,
    /// Knots per hand.
    #[arg(long, default_value_t = 4)]
    pub knots: usize,
    /// MPPI samples per iteration.
    #[arg(long, default_value_t = 20)]
    pub samples: usize,
    /// MPPI iterations.
    #[arg(long, default_value_t = 10)]
    pub iterations: usize,
    /// MPPI knot noise, metres.
    #[arg(long, default_value_t = 0.02)]
    pub noise_m: f64,
    /// Gradient refinement steps.
    #[arg(long, default_value_t = 20)]
    pub gradient_iters: usize,
    /// Gradient refinement step (Adam), metres.
    #[arg(long, default_value_t = 0.004)]
    pub learning_rate_m: f64,
    /// Substeps per frame differentiated exactly in the refinement.
    #[arg(long, default_value_t = 8)]
    pub window: usize,
    /// Fastest hand speed before the cost penalises it, m/s.
    #[arg(long, default_value_t = 0.5)]
    pub max_speed: f64,
    /// How far the hands may move beyond the object's box where the plan starts, metres.
    #[arg(long, default_value_t = 0.2)]
    pub workspace_margin_m: f64,
    /// Plan in the model's own particles, grid and substeps (slower) instead of the playground's coarse simulation.
    #[arg(long)]
    pub exact: bool,
    /// Apply the model's residual network in the planning world (off: physics only).
    #[arg(long)]
    pub residual: bool,
    /// Seed of MPPI's samples and of the observation noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Where the planning world runs, and the model when it is the plant (cuda: the first NVIDIA GPU, the residual network too; a truth plant stays on the CPU).
    #[arg(long, value_enum, default_value_t = Device::Cpu)]
    pub device: Device,
}

/// `dm-plan`'s options, saved as the run record in plan.json.
#[derive(Clone, Debug, Serialize, clap::Parser)]
#[command(
    name = "dm-plan",
    about = "Plan hand motions that bring an object to a goal with its fitted world model, and carry them out"
)]
pub struct PlanOptions {
    /// Model directory (dm-fit's output).
    pub model_dir: PathBuf,
    /// The scene bundle the model was fitted on (first-frame hands, cameras, goal frames).
    #[arg(long)]
    pub bundle: PathBuf,
    /// The goal: `frame:T` (the bundle's tracked points at frame T), a binary PLY point cloud, or a name (rope: straighten, u-shape, move; cloth: fold, flatten, move; toy: place, squash, rotate).
    #[arg(long)]
    pub goal: String,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// dm-synth's truth file of the scene: carry the plan out in that truth world (hidden effects included) instead of the fitted model.
    #[arg(long)]
    pub plant: Option<PathBuf>,
    /// Start where the clip leaves the object at frame T: the recorded hands play frames 0 to T, let go, and the object settles before the plan begins (0: the first frame, at rest).
    #[arg(long, default_value_t = 0)]
    pub start_frame: usize,
    /// Frames the object settles for after the hands let go at `--start-frame`.
    #[arg(long, default_value_t = 30)]
    pub settle_frames: usize,
    /// Hands (grasp points chosen where the goal moves the object most).
    #[arg(long, default_value_t = 2)]
    pub hands: usize,
    #[command(flatten)]
    #[serde(flatten)]
    pub search: SearchOptions,
    /// Re-plan from the observed state every N frames (0: open loop).
    #[arg(long, default_value_t = 0)]
    pub replan_every: usize,
    /// MPPI iterations (and refinement steps) of each re-plan.
    #[arg(long, default_value_t = 3)]
    pub replan_iterations: usize,
    /// Noise of the observed positions re-planning starts from, millimetres.
    #[arg(long, default_value_t = 1.5)]
    pub observation_noise_mm: f64,
    /// Plan with the untrained model of the bundle instead of MODEL_DIR's (for comparison).
    #[arg(long)]
    pub untrained: bool,
    /// Bundle camera of the video.
    #[arg(long, default_value_t = 0)]
    pub camera: usize,
    /// Write the frames but no MP4.
    #[arg(long)]
    pub no_video: bool,
}

impl SearchOptions {
    pub(crate) fn validate(&self) -> Result<(), PlanError> {
        let checks: [(&str, bool, &str); 8] = [
            ("--horizon", self.horizon >= 2, "needs at least 2 frames"),
            (
                "--knots",
                self.knots >= 1 && self.knots <= self.horizon,
                "needs 1 to HORIZON knots",
            ),
            ("--samples", self.samples >= 2, "needs at least 2 samples"),
            (
                "--noise-m",
                self.noise_m.is_finite() && self.noise_m > 0.0,
                "needs a positive noise",
            ),
            (
                "--learning-rate-m",
                self.learning_rate_m.is_finite() && self.learning_rate_m > 0.0,
                "needs a positive step",
            ),
            ("--window", self.window >= 1, "needs at least 1 substep"),
            (
                "--max-speed",
                self.max_speed.is_finite() && self.max_speed > 0.0,
                "needs a positive speed",
            ),
            (
                "--workspace-margin-m",
                self.workspace_margin_m.is_finite() && self.workspace_margin_m >= 0.0,
                "needs a margin ≥ 0",
            ),
        ];
        for (option, ok, problem) in checks {
            if !ok {
                return Err(invalid(option, problem));
            }
        }
        Ok(())
    }
}

impl PlanOptions {
    pub(crate) fn validate(&self) -> Result<(), PlanError> {
        self.search.validate()?;
        if !(1..=4).contains(&self.hands) {
            return Err(invalid("--hands", "needs 1 to 4 hands"));
        }
        if !(self.observation_noise_mm.is_finite() && self.observation_noise_mm >= 0.0) {
            return Err(invalid("--observation-noise-mm", "needs a noise ≥ 0"));
        }
        if self.search.residual && self.untrained {
            return Err(invalid(
                "--residual",
                "the untrained model has no trained residual network (drop --untrained or --residual)",
            ));
        }
        Ok(())
    }
}
