//! How much the right candidate can show in each evaluation scene
//! (issue 6): the scene's base fit repeated with the hidden effect's true
//! term in place from the start (`dm_diagnose::oracle`).
//!
//!     cargo run --release -p dm-diagnose --example oracle_gain -- OUT_DIR SEED [SEED ...] [OPTIONS]
//!
//! For each hidden-effect draw SEED, OUT_DIR/hiddenSEED is the directory
//! `diagnose_eval` uses: its scene and base fit are reused (or made, with
//! the same fit options), and the oracle fit goes to
//! OUT_DIR/hiddenSEED/oracle. One line per scene is printed and appended
//! to OUT_DIR/oracle.jsonl. The options (`--help`) vary one thing at a
//! time, each in a directory of its own: the effect held at the truth, a
//! magnitude sweep, a longer clip, a finer model grid, a narrower grip,
//! exact tracks or hands, more particles.

use clap::Parser;
use dm_diagnose::evaluation::{
    evaluation_fit_options, prepare_scene, quick_fit_options, scene_config,
    scene_config_with_effect,
};
use dm_diagnose::oracle::oracle_fit;
use dm_synth::EffectSpec;
use std::io::Write;
use std::path::PathBuf;

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
    /// Film N frames instead of the evaluation's 36, the hands' motion
    /// stretched over the clip; the last 30 % stay held out (suffix -fN).
    #[arg(long, value_name = "N")]
    frames: Option<usize>,
    /// Fit base and oracle on a model grid of N cells per axis instead of
    /// the evaluation's 32 (suffix -gN): does a grid as fine as the
    /// truth's let the true effect show?
    #[arg(long, value_name = "N")]
    grid: Option<usize>,
    /// Fit base and oracle with this grasp radius, metres, instead of the
    /// model's default 0.03 (suffix -rMM, in mm): the truth grips with
    /// 0.014 m. Does the grip's width hide the effect?
    #[arg(long, value_name = "METRES")]
    grasp_radius: Option<f64>,
    /// Film the scene with the truth as its object tracks: no tracker
    /// noise, bias or dropout (suffix -x). Does the tracker's noise hide
    /// the effect?
    #[arg(long)]
    exact_tracks: bool,
    /// Film the scene with the scripted hands as its hand tracks: no
    /// jitter or dropout (suffix -h). Does the noisy drive hide the effect?
    #[arg(long)]
    exact_hands: bool,
    /// Write N first-frame particles to the bundle instead of the
    /// evaluation's 1000 (suffix -pN): does the model's sparser particle
    /// set hide the effect?
    #[arg(long, value_name = "N")]
    bundle_particles: Option<usize>,
    /// The 3 + 1 steps of sessions one to fourteen.
    #[arg(long)]
    quick_fit: bool,
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args = Args::parse();
    let mut fit = if args.quick_fit {
        quick_fit_options()
    } else {
        evaluation_fit_options()
    };
    let mut suffix = String::new();
    if let Some(n) = args.frames {
        suffix.push_str(&format!("-f{n}"));
    }
    if let Some(n) = args.grid {
        fit.model.grid = n;
        suffix.push_str(&format!("-g{n}"));
    }
    if let Some(r) = args.grasp_radius {
        fit.model.grasp_radius = Some(r);
        suffix.push_str(&format!("-r{}", 1e3 * r));
    }
    if args.exact_tracks {
        suffix.push_str("-x");
    }
    if args.exact_hands {
        suffix.push_str("-h");
    }
    if let Some(n) = args.bundle_particles {
        suffix.push_str(&format!("-p{n}"));
    }
    let name = if args.frozen {
        "oracle_frozen"
    } else {
        "oracle"
    };
    for seed in args.seeds {
        let (mut config, mut dir) = match args.effect {
            Some(e) => (
                scene_config_with_effect(seed, e),
                args.out
                    .join(format!("hidden{seed}-{}-{}", e.name.name(), e.magnitude)),
            ),
            None => (
                scene_config(seed, false).0,
                args.out.join(format!("hidden{seed}")),
            ),
        };
        if let Some(n) = args.frames {
            config.frames = n;
        }
        config.exact_tracks = args.exact_tracks;
        config.exact_hands = args.exact_hands;
        if let Some(n) = args.bundle_particles {
            config.bundle_particles = n;
        }
        dir.as_mut_os_string().push(&suffix);
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
