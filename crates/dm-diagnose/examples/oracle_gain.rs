//! How much the right candidate can show in each evaluation scene
//! (issue 6): the scene's base fit repeated with the hidden effect's true
//! term in place from the start (`dm_diagnose::oracle`).
//!
//!     cargo run --release -p dm-diagnose --example oracle_gain -- OUT_DIR SEED [SEED ...] [--frozen] [--effect NAME:MAG] [--frames N] [--quick-fit]
//!
//! For each hidden-effect draw SEED, OUT_DIR/hiddenSEED is the directory
//! `diagnose_eval` uses: its scene and base fit are reused (or made, with
//! the same fit options), and the oracle fit goes to
//! OUT_DIR/hiddenSEED/oracle. One line per scene is printed and appended
//! to OUT_DIR/oracle.jsonl. With `--frozen` the effect is held at the
//! truth instead of learnt from it (OUT_DIR/hiddenSEED/oracle_frozen,
//! OUT_DIR/oracle_frozen.jsonl). With `--effect NAME:MAG` each draw's
//! preset and action are kept but NAME is hidden at MAG instead of the
//! drawn effect (OUT_DIR/hiddenSEED-NAME-MAG): a magnitude sweep. With
//! `--frames N` the scene is filmed for N frames instead of the
//! evaluation's 36 (the hands' motion is stretched over the clip; the
//! last 30 % stay held out; directory suffix `-fN`): does a longer clip
//! let the true effect show?

use dm_diagnose::evaluation::{
    evaluation_fit_options, prepare_scene, quick_fit_options, scene_config,
    scene_config_with_effect,
};
use dm_diagnose::oracle::oracle_fit;
use dm_synth::EffectSpec;
use std::io::Write;
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let fit = if args.iter().any(|a| a == "--quick-fit") {
        quick_fit_options()
    } else {
        evaluation_fit_options()
    };
    let frozen = args.iter().any(|a| a == "--frozen");
    let effect: Option<EffectSpec> = match args.iter().position(|a| a == "--effect") {
        Some(i) => {
            let spec = args.get(i + 1).ok_or("--effect needs NAME:MAG")?.clone();
            args.drain(i..=i + 1);
            Some(spec.parse()?)
        }
        None => None,
    };
    let frames: Option<usize> = match args.iter().position(|a| a == "--frames") {
        Some(i) => {
            let n = args.get(i + 1).ok_or("--frames needs N")?.parse()?;
            args.drain(i..=i + 1);
            Some(n)
        }
        None => None,
    };
    let name = if frozen { "oracle_frozen" } else { "oracle" };
    args.retain(|a| a != "--quick-fit" && a != "--frozen");
    let usage = "usage: oracle_gain OUT_DIR SEED [SEED ...] [--frozen] [--effect NAME:MAG] [--frames N] [--quick-fit]";
    let out = PathBuf::from(args.first().ok_or(usage)?);
    let seeds: Vec<u64> = args[1..]
        .iter()
        .map(|s| s.parse())
        .collect::<Result<_, _>>()?;
    if seeds.is_empty() {
        return Err(usage.into());
    }
    for seed in seeds {
        let (mut config, mut dir) = match effect {
            Some(e) => (
                scene_config_with_effect(seed, e),
                out.join(format!("hidden{seed}-{}-{}", e.name.name(), e.magnitude)),
            ),
            None => (
                scene_config(seed, false).0,
                out.join(format!("hidden{seed}")),
            ),
        };
        if let Some(n) = frames {
            config.frames = n;
            dir.as_mut_os_string().push(format!("-f{n}"));
        }
        let effect = config.effect;
        let start = std::time::Instant::now();
        prepare_scene(&config, &dir, &fit)?;
        let r = oracle_fit(
            &dir.join("scene"),
            &dir.join("scene.truth.json"),
            &dir.join("model"),
            &dir.join(name),
            frozen,
        )?;
        println!(
            "seed {seed}: {} {}{} → {name} score {:.3} (train {:+.1} %, held-out {:+.1} %), test track {:.2} → {:.2} mm, {:.0} s",
            config.preset.name(),
            r.effect,
            effect
                .map(|e| format!(":{:.3}", e.magnitude))
                .unwrap_or_default(),
            r.score,
            -100.0 * r.train_reduction,
            -100.0 * r.held_out_reduction,
            1e3 * r.base_track_test,
            1e3 * r.oracle_track_test,
            start.elapsed().as_secs_f64()
        );
        let mut line = serde_json::to_value(&r)?;
        line["seed"] = seed.into();
        line["preset"] = config.preset.name().into();
        line["magnitude"] = effect.map(|e| e.magnitude).into();
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(out.join(format!("{name}.jsonl")))?;
        writeln!(f, "{line}")?;
    }
    Ok(())
}
