//! Research harnesses behind docs/RESULTS.md, apart from the product
//! libraries: they call dm-diagnose, dm-fit and dm-appearance as a user
//! would and measure what those crates can do.
//!
//! * [`diagnosis_evaluation`]: scenes with a seeded hidden effect (or
//!   none) synthesised, fitted and diagnosed, the named causes tabulated
//!   against the hidden ones (`examples/diagnose_eval.rs`, the integration
//!   test `tests/issue6_diagnose.rs`).
//! * [`oracle`]: a scene refitted with its hidden effect's true term, the
//!   most the right candidate can show (`examples/oracle_gain.rs`).
//! * [`fit_support`]: what the material-recovery studies share: a model
//!   set to the truth's material, a bundle's hands or particles replaced
//!   by the truth's (`examples/{recovery_floor,identifiability,global_refit,loss_profile,mass_check}.rs`).
//!
//! The other examples: `effect_visibility` (how far each hidden effect
//! moves the truth), `fit_with_grasp_radius` and `appearance_table`.

pub mod diagnosis_evaluation;
pub mod fit_support;
pub mod oracle;
pub mod outside_library;
