//! Optimisers of the fitting stages.
//!
//! * [`params`]: [`ParamSet`], the ordered named parameter groups shared by
//!   the optimiser and the clipping (gradients use the same type and layout).
//! * [`clip`]: gradient clipping per parameter group and globally.
//! * [`adam`]: Adam with serialisable state for bitwise checkpoint/resume.
//! * [`cmaes`]: a compact seeded (μ/μ_w, λ)-CMA-ES with an ask/tell
//!   interface and box bounds, for the actuator gain selection.

pub mod adam;
pub mod clip;
pub mod cmaes;
pub mod params;

pub use adam::{Adam, AdamConfig};
pub use clip::{
    ClipConfig, ClipReport, clip_global_norm, clip_group_norms, clip_physics_gradients, l2_norm,
};
pub use cmaes::{Bounds, Cmaes, CmaesOptions, CmaesResult, StopReason, minimize};
pub use params::{ParamGroup, ParamSet};

/// Why an optimiser operation was refused or failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OptimError {
    #[error("parameter group `{name}` appears twice in one parameter set")]
    DuplicateGroup { name: String },
    #[error("parameter layout mismatch: {detail}")]
    LayoutMismatch { detail: String },
    #[error("non-finite gradient {value} in parameter group `{group}` at index {index}")]
    NonFiniteGradient {
        group: String,
        index: usize,
        value: f64,
    },
    #[error("invalid optimiser option `{option}`: {problem}")]
    InvalidOption {
        option: &'static str,
        problem: String,
    },
    #[error(
        "CMA-ES start point coordinate {index} = {value} lies outside its bounds [{lower}, {upper}]"
    )]
    StartOutsideBounds {
        index: usize,
        value: f64,
        lower: f64,
        upper: f64,
    },
    #[error("CMA-ES `tell` called without a pending population from `ask`")]
    TellWithoutAsk,
    #[error("CMA-ES `tell` got {got} fitness values for a population of {expected}")]
    FitnessCountMismatch { expected: usize, got: usize },
    #[error("CMA-ES: every fitness value of generation {generation} is non-finite")]
    AllFitnessNonFinite { generation: u64 },
    #[error("CMA-ES numerical breakdown: {detail}")]
    NumericalBreakdown { detail: String },
}
