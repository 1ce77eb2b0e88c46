//! `--damping learnt`: the particle damping rate stays as the start model
//! has it through stage 1 and is stepped from stage 2 on.

mod common;

use dm_fit::run::{FitOutcome, run_fit_from};
use dm_model::WorldModel;

#[test]
fn learnt_damping_moves_from_stage_two_only() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bundle = common::tiny_rope(dir.path());
    // Below the rope's default of 20 /s, where the truth damps: stage 2's
    // steps have room to move it either way.
    let start_rate = 5.0;
    let fitted_rate = |stage2_iters: usize, out: &str| {
        let mut options = common::fit_options(&["--damping", "learnt", "--residual", "none"]);
        options.stage2_iters = stage2_iters;
        let mut start = WorldModel::from_bundle(&bundle, &options.model).expect("model");
        start.physics.particle_damping = start_rate;
        let out = dir.path().join(out);
        match run_fit_from(&bundle, &options, start, &out, &mut |_| {}).expect("fit") {
            FitOutcome::Finished(_) => {}
            FitOutcome::Paused { .. } => panic!("no step limit was given"),
        }
        let model: WorldModel = dm_bundle::read_json(&out.join("model.json")).expect("model");
        model.physics.particle_damping
    };
    assert_eq!(
        fitted_rate(0, "stage1"),
        start_rate,
        "stage 1 keeps the rate"
    );
    let moved = fitted_rate(2, "stage2");
    assert!(
        moved != start_rate && (0.5..=20.0).contains(&moved),
        "stage 2 steps the rate within its bounds: {moved}"
    );
}
