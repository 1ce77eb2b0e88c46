//! How much the right candidate can show in each evaluation scene:
//! the scene's base fit repeated with the hidden effect's true
//! term in place from the start (`dm_studies::oracle`).
//!
//!     cargo run --release -p dm-studies --example oracle_gain -- OUT_DIR SEED [SEED ...] [OPTIONS]
//!
//! For each hidden-effect draw SEED, OUT_DIR/hiddenSEED is the directory
//! `diagnose_eval` uses: its scene and base fit are reused (or made, with
//! the same fit options), and the oracle fit goes to
//! OUT_DIR/hiddenSEED/oracle. One line per scene is printed and appended
//! to OUT_DIR/oracle.jsonl. The options (`--help`) vary one thing at a
//! time, each in a directory of its own: the effect held at the truth, a
//! magnitude sweep, a longer clip, a finer model grid, a narrower grip,
//! exact tracks or hands, more particles, fewer material patches, longer
//! fit stages.

use clap::Parser;
use dm_studies::diagnosis_evaluation::{
    SceneVariant, evaluation_fit_options, prepare_scene, quick_fit_options, scene_config,
    scene_config_with_effect,
};
use dm_studies::oracle::oracle_fit;
use dm_synth::EffectSpec;
use std::io::Write;
use std::path::PathBuf;

/// How much the right candidate can show in each evaluation scene: its
/// base fit repeated with the hidden effect's true term in place.
#[derive(Parser)]
struct Args {
    /// The evaluation's directory (`diagnose_eval`'s OUT_DIR).
    out: PathBuf,
    /// Hidden-effect draws.
    #[arg(required = true)]
    seeds: Vec<u64>,
    /// Hold the effect at the truth instead of learning it from there
    /// (OUT_DIR/hiddenSEED/oracle_frozen, OUT_DIR/oracle_frozen.jsonl).
    #[arg(long)]
    frozen: bool,
    /// Keep each draw's preset and action but hide NAME at MAG instead of
    /// the drawn effect (directory hiddenSEED-NAME-MAG).
    #[arg(long, value_name = "NAME:MAG")]
    effect: Option<EffectSpec>,
    // The scene or fit settings changed (the evaluation's by default).
    #[command(flatten)]
    variant: SceneVariant,
    /// Fit with `quick_fit_options`: 3 + 1 material steps.
    #[arg(long)]
    quick_fit: bool,
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args = Args::parse();
    let fit = if args.quick_fit {
        quick_fit_options()
    } else {
        evaluation_fit_options()
    };
    let suffix = args.variant.suffix();
    let name = if args.frozen {
        "oracle_frozen"
    } else {
        "oracle"
    };
    for seed in args.seeds {
        let (mut config, stem) = match args.effect {
            Some(e) => (
                scene_config_with_effect(seed, e),
                format!("hidden{seed}-{}-{}", e.name.name(), e.magnitude),
            ),
            None => (
                scene_config(seed, false, args.variant.engine.unwrap_or_default()).0,
                format!("hidden{seed}"),
            ),
        };
        let mut fit = fit.clone();
        args.variant.apply(&mut config, &mut fit);
        let dir = args.variant.scene_dir(&args.out, &stem);
        let effect = config.effect;
        let start = std::time::Instant::now();
        prepare_scene(&config, &dir, &fit)?;
        let r = oracle_fit(
            &dir.join("scene"),
            &dir.join("scene.truth.json"),
            &dir.join("model"),
            &dir.join(name),
            args.frozen,
        )?;
        println!(
            "seed {seed}{suffix}: {} {}{} → {name} score {:.3} (train {:+.1} %, held-out {:+.1} %), test track {:.2} → {:.2} mm, {:.0} s",
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
        line["variant"] = suffix.clone().into();
        line["preset"] = config.preset.name().into();
        line["magnitude"] = effect.map(|e| e.magnitude).into();
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(args.out.join(format!("{name}.jsonl")))?;
        writeln!(f, "{line}")?;
    }
    Ok(())
}
