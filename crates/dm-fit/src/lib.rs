//! Fitting the DeformMaster world model to video tracks (method.md §7):
//! [`run::run_fit`] runs stage 1 (material with default gains), the CMA-ES
//! gain selection, stage 2 (material with the selected gains) and stage 3
//! (first-frame Gaussians, then RGB-guided refinement, [`rgb_stage`]);
//! [`material_fit`] is one differentiated rollout and Adam step;
//! [`sensitivity`] reports how sharply the clip pins the fitted material
//! and [`identifiability`] how precisely its tracks could (the Cramér–Rao
//! bound);
//! [`learnt_effects`] are the effect terms a fit learns beside it.
//!
//! The optimisers:
//!
//! * [`optim::Adam`] with the method's gradient clipping
//!   ([`optim::clip_physics_gradients`]: 1.0 per physics parameter, 10.0
//!   global, method.md §2) for the material fields and the residual network
//!   (stages 1 and 2);
//! * [`optim::Cmaes`] / [`optim::minimize`], a gradient-free
//!   (μ/μ_w, λ)-CMA-ES for selecting the actuator gains (k_p, k_d)
//!   (method.md §4, §7 step 2).
//!
//! Parameters live in an [`optim::ParamSet`]: ordered, named groups of
//! `f64` values, stored unbounded; the model maps them through bounded
//! activations (e.g. log-sigmoid for Young's modulus), so the optimisers
//! never need to know about physical bounds.

pub mod identifiability;
pub mod learnt_effects;
pub mod loss;
pub mod material_fit;
pub mod optim;
pub mod plot;
pub mod residual_check;
pub mod rgb_stage;
pub mod run;
pub mod sensitivity;
