//! MLS-MPM world model of DeformMaster (method.md §2–4): quadratic
//! B-splines with APIC transfers, a per-particle Mixture of Constitutive
//! Experts over material patches, and Distributed Compliant Actuators.
//!
//! One file per solver stage, each a pure function over struct-of-arrays
//! slices: [`stress`] → [`p2g`] → [`grid_update`] → [`g2p`]. [`world::World`]
//! strings them together and reports divergence instead of writing NaNs.

pub mod actuators;
pub mod actuators_backward;
pub mod config;
pub mod correction;
pub mod correction_backward;
pub mod domain;
pub mod experts;
pub mod experts_backward;
pub mod g2p;
pub mod grid;
pub mod grid_update;
pub mod lanes;
pub mod material;
pub mod material_backward;
pub mod neighbors;
pub mod p2g;
pub mod real;
pub mod scenes;
pub mod state;
pub mod stress;
pub mod svd;
pub mod svd_backward;
pub mod tape;
pub mod viscosity;
pub mod world;

pub use actuators::{ActuatorConfig, ActuatorMode};
pub use config::{Effects, FloorConfig, ForceField, GRID_DAMPING_REFERENCE_DT, PhysicsConfig};
pub use material::{MaterialBounds, MaterialPatches, ParticleMaterial, PatchParams};
pub use real::Real;
pub use world::World;

/// Why a simulation could not run or continue.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("invalid physics config: field `{field}`: {problem}")]
    InvalidConfig { field: String, problem: String },
    #[error("invalid simulation input: {0}")]
    InvalidInput(String),
    #[error(
        "simulation diverged at frame {frame}, substep {substep}: particle {particle}: {reason}"
    )]
    Diverged {
        frame: usize,
        substep: usize,
        particle: usize,
        reason: String,
    },
}
pub mod g2p_backward;
pub mod grid_update_backward;
pub mod p2g_backward;
pub mod stress_backward;
pub mod substep;
pub mod viscosity_backward;
