//! Research harnesses behind docs/RESULTS.md, apart from the product
//! libraries: they call dm-diagnose, dm-fit and dm-appearance as a user
//! would and measure what those crates can do.
//!
//! * [`diagnosis_evaluation`]: scenes with a seeded hidden effect (or
//!   none) synthesised, fitted and diagnosed, the named causes tabulated
//!   against the hidden ones (`examples/diagnose_eval.rs`, the integration
//!   test `tests/diagnose.rs`).
//! * [`detection_limits`]: an effect hidden at multiples of the limit the
//!   diagnosis reported on the scene's null twin
//!   (`examples/detection_limits_eval.rs`).
//! * [`oracle`]: a scene refitted with its hidden effect's true term, the
//!   most the right candidate can show (`examples/oracle_gain.rs`).
//! * [`fit_support`]: what the material-recovery studies share: a model
//!   set to the truth's material, a bundle's hands or particles replaced
//!   by the truth's (`examples/{recovery_floor,identifiability,global_refit,loss_profile,mass_check}.rs`).
//!
//! The other examples: `effect_visibility` (how far each hidden effect
//! moves the truth), `fit_with_grasp_radius` and `appearance_table`.

pub mod detection_limits;
pub mod diagnosis_evaluation;
pub mod fit_support;
pub mod oracle;
pub mod outside_library;

/// `SHARD/SHARDS` of an evaluation example (e.g. `0/2`: every second scene
/// from the first), so several processes can share one output directory.
pub fn parse_shard(text: &str) -> Result<(usize, usize), String> {
    let (shard, shards) = text.split_once('/').ok_or("SHARD/SHARDS, e.g. 0/2")?;
    let shard: usize = shard.parse().map_err(|e| format!("SHARD `{shard}`: {e}"))?;
    let shards: usize = shards
        .parse()
        .map_err(|e| format!("SHARDS `{shards}`: {e}"))?;
    if shard >= shards {
        return Err(format!("SHARD {shard} must be below SHARDS {shards}"));
    }
    Ok((shard, shards))
}
