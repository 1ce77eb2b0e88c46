//! Planning hand motions with a fitted world model (docs/plan.md).
//!
//! A plan is, per hand, a grasp point on the object and a few knots the
//! hand passes through ([`actions`]); it is scored at its last frame
//! against a goal cloud ([`goal`], [`cost`]) in a coarse simulation of the
//! model ([`world`]), searched by MPPI ([`mppi`]) and refined through the
//! simulator's adjoint ([`gradient`]), then carried out in a plant — the
//! fitted model itself or dm-synth's truth world — open loop or re-planned
//! from noisy observations every few frames ([`plant`], [`run`]).

pub mod actions;
pub mod cost;
pub mod goal;
pub mod gradient;
pub mod live;
pub mod mppi;
pub mod options;
pub mod output;
pub mod plant;
pub mod run;
mod search;
pub mod video;
pub mod world;

use std::path::PathBuf;

/// Why a plan could not be made or carried out.
#[derive(Debug, thiserror::Error)]
pub enum PlanError {
    #[error(transparent)]
    Bundle(#[from] dm_bundle::BundleError),
    #[error(transparent)]
    Model(#[from] dm_model::ModelError),
    #[error(transparent)]
    Simulation(#[from] dm_mpm::SimError),
    #[error(transparent)]
    Play(#[from] dm_play::PlayError),
    #[error(transparent)]
    Synth(#[from] dm_synth::SynthError),
    #[error("invalid option `{option}`: {problem}")]
    InvalidOption { option: String, problem: String },
    #[error("{path}: {problem}")]
    File { path: PathBuf, problem: String },
    /// The caller's progress callback asked to stop.
    #[error("stopped by the caller during {stage}")]
    Stopped { stage: String },
}

impl PlanError {
    /// Whether the simulator failed on the plan (it diverged, or refused a
    /// step), on either device: a bad sample or step, not a failed run.
    pub fn is_simulation(&self) -> bool {
        match self {
            PlanError::Simulation(_) => true,
            PlanError::Model(e) => e.simulation().is_some(),
            _ => false,
        }
    }
}

/// `Stopped` in `stage` where the caller's progress callback broke.
pub(crate) fn keep_going(flow: std::ops::ControlFlow<()>, stage: &str) -> Result<(), PlanError> {
    match flow {
        std::ops::ControlFlow::Continue(()) => Ok(()),
        std::ops::ControlFlow::Break(()) => Err(PlanError::Stopped {
            stage: stage.into(),
        }),
    }
}

/// An `InvalidOption` error.
pub(crate) fn invalid(option: &str, problem: impl Into<String>) -> PlanError {
    PlanError::InvalidOption {
        option: option.into(),
        problem: problem.into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn diverged() -> dm_mpm::SimError {
        dm_mpm::SimError::Diverged {
            frame: 3,
            substep: 7,
            particle: 11,
            reason: "det F <= 0".into(),
        }
    }

    /// Rollouts return the simulator's errors wrapped by the model layer
    /// (CPU or GPU); a search treats every form as a bad sample.
    #[test]
    fn a_divergence_is_a_simulation_failure_however_it_is_wrapped() {
        assert!(PlanError::Simulation(diverged()).is_simulation());
        assert!(PlanError::Model(dm_model::ModelError::Simulation(diverged())).is_simulation());
        let bad_option = PlanError::Model(dm_model::ModelError::InvalidOption {
            option: "x".into(),
            problem: "y".into(),
        });
        assert!(!bad_option.is_simulation());
        assert!(!invalid("--goal", "unknown").is_simulation());
    }
}
