//! Issue 4: 300-frame open-loop rollouts with the neural residual stay
//! finite, and the residual's correction never exceeds α. The worst case is
//! tested: a residual whose weights are perturbed at random (a fresh one
//! has a zero last layer and changes nothing), so its bounded output
//! saturates and kicks every particle by up to α every frame. The clip's
//! hand track drives the first frames; after it the hands hold still.

use dm_bundle::Bundle;
use dm_model::device::Device;
use dm_model::residual::{RESIDUAL_ALPHA, apply_residual, frame_start};
use dm_model::{ModelOptions, ResidualKind, WorldModel};
use dm_synth::{Preset, SynthConfig};

const FRAMES: usize = 300;
/// Weight perturbation: large enough that the network's tanh output
/// saturates for many particles.
const WEIGHT_NOISE: f64 = 0.5;
/// |Δv| may exceed α only by f32 round-off of α·tanh(|y|)·y/|y|.
const ALPHA_ROUNDOFF: f64 = 1e-5;

fn stream(seed: u64) -> impl FnMut() -> f64 {
    let mut s = seed;
    move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }
}

fn long_rollout(preset: Preset, kind: ResidualKind, seed: u64) {
    let dir = tempfile::tempdir().expect("temp dir");
    let scene = dir.path().join("scene");
    dm_synth::generate(
        &SynthConfig::tiny(preset, seed),
        &scene,
        &dir.path().join("truth.json"),
        &mut |_, _, _| {},
    )
    .expect("scene generates");
    let bundle = Bundle::open(&scene).expect("bundle");
    let options = ModelOptions {
        residual: kind,
        ..ModelOptions::default()
    };
    let mut model = WorldModel::from_bundle(&bundle, &options).expect("model");
    let state = model.residual.as_mut().expect("a residual model");
    let mut noise = stream(seed);
    for w in &mut state.parameters {
        *w += WEIGHT_NOISE * noise();
    }
    let network = model
        .residual_network_on(Device::Cpu)
        .expect("network")
        .expect("residual present");
    let mut world = model.world().expect("world");
    let clip = bundle.frame_count();
    let mut starts = Vec::new();
    let mut largest_dv = 0.0f64;
    let (lo, hi) = (
        model.physics.domain_origin,
        model
            .physics
            .domain_origin
            .map(|o| o + model.physics.domain_size),
    );
    for t in 0..FRAMES {
        starts.push(frame_start(&world));
        let (from, to, grasp) = if t + 1 < clip {
            model.hand_step(&bundle, t)
        } else {
            // Past the clip the hands hold still where it left them.
            let (_, last, _) = model.hand_step(&bundle, clip - 2);
            let n = last.len();
            (last.clone(), last, vec![false; n])
        };
        world
            .step_frame(&from, &to, &grasp)
            .unwrap_or_else(|e| panic!("{preset:?} {kind:?}: frame {t} diverged: {e}"));
        let (dv, _) = apply_residual(&mut world, &network, &starts, t)
            .unwrap_or_else(|e| panic!("{preset:?} {kind:?}: residual at frame {t}: {e}"));
        for v in &dv {
            let speed = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            // Each node's output is no longer than α and the particle's Δv
            // is a B-spline-weighted mean of its nodes' outputs.
            assert!(
                speed <= RESIDUAL_ALPHA * (1.0 + ALPHA_ROUNDOFF),
                "{preset:?} {kind:?}: |dv| = {speed} > alpha at frame {t}"
            );
            largest_dv = largest_dv.max(speed);
        }
        for p in world.positions() {
            assert!(
                (0..3).all(|a| p[a].is_finite() && p[a] >= lo[a] && p[a] <= hi[a]),
                "{preset:?} {kind:?}: particle at {p:?} left the domain at frame {t}"
            );
        }
    }
    // The perturbed residual really acted (otherwise the test proves nothing).
    assert!(
        largest_dv > 0.1 * RESIDUAL_ALPHA,
        "{preset:?} {kind:?}: largest |dv| only {largest_dv}"
    );
    eprintln!("{preset:?} {kind:?}: {FRAMES} frames finite, largest |dv| {largest_dv:.3} m/s");
}

#[test]
fn pgnd_300_frame_rollouts_stay_finite() {
    for (i, preset) in [Preset::Rope, Preset::Cloth, Preset::Toy]
        .into_iter()
        .enumerate()
    {
        long_rollout(preset, ResidualKind::Pgnd, 40 + i as u64);
    }
}
