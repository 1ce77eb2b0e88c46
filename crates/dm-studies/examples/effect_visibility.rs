//! How far each hidden effect moves the object in the diagnosis scenes:
//! the evidence behind the "detectable range" of
//! `dm_synth::EffectName::test_range`.
//!
//!     cargo run --release -p dm-studies --example effect_visibility -- OUT_DIR [SEED] [EFFECTS] [PRESETS]
//!
//! EFFECTS (optional) is a comma-separated list of `name:magnitude`, e.g.
//! `viscous_damping:250,viscous_damping:1000`, run instead of the library;
//! PRESETS (optional) a comma-separated list of presets, e.g. `rope,cloth`.
//!
//! For every preset, the same seed's truth simulation
//! (`SynthConfig::diagnosis`: same particles, same action) runs without an
//! effect and with each effect at the low end of its test range (the
//! weakest case the evaluation draws);
//! the two runs' surface particles are compared one by one. Printed (and
//! written to OUT_DIR/visibility.md): the mean and the 90th percentile over
//! surface particles of the distance between the runs, averaged over the
//! test frames, in mm (not the median: in a push or a lift most of the
//! object can rest on the floor in both runs); for `actuator_lag`, which
//! moves only the recorded hand track, the shift of that track instead.

use dm_bundle::Split;
use dm_synth::{EffectName, EffectSpec, GroundTruth, Preset, SynthConfig, simulate_truth};
use std::fmt::Write as _;
use std::path::PathBuf;

fn truth(preset: Preset, seed: u64, effect: Option<EffectSpec>) -> GroundTruth {
    let mut config = SynthConfig::diagnosis(preset, seed);
    config.effect = effect;
    simulate_truth(&config, &mut |_, _, _| {}).expect("truth simulation")
}

/// Mean and 90th percentile of `d`.
fn mean_p90(mut d: Vec<f64>) -> [f64; 2] {
    if d.is_empty() {
        return [f64::NAN; 2];
    }
    d.sort_by(f64::total_cmp);
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    [mean, d[d.len() * 9 / 10]]
}

fn distance_mm(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt() * 1e3
}

/// Mean and 90th-percentile distance at frame `t` between the runs:
/// surface particles, or for a lag the recorded hand anchors against the
/// true ones.
fn shift_mm(null: &GroundTruth, with: &GroundTruth, name: EffectName, t: usize) -> [f64; 2] {
    if name == EffectName::ActuatorLag {
        return mean_p90(
            with.recorded_anchors[t]
                .iter()
                .zip(&with.anchors[t])
                .map(|(r, a)| distance_mm(*r, *a))
                .collect(),
        );
    }
    mean_p90(
        (0..null.cloud.positions.len())
            .filter(|&i| null.cloud.on_surface[i])
            .map(|i| {
                distance_mm(
                    null.frames[t][i].map(f64::from),
                    with.frames[t][i].map(f64::from),
                )
            })
            .collect(),
    )
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let out = PathBuf::from(
        args.first()
            .ok_or("usage: effect_visibility OUT_DIR [SEED] [name:magnitude,...] [preset,...]")?,
    );
    let seed: u64 = args.get(1).map_or(Ok(2000), |s| s.parse())?;
    let effects: Vec<EffectSpec> = match args.get(2) {
        Some(list) => list
            .split(',')
            .map(|s| s.parse::<EffectSpec>())
            .collect::<Result<_, _>>()?,
        None => EffectName::ALL
            .into_iter()
            .map(|name| EffectSpec {
                name,
                magnitude: name.test_range()[0],
            })
            .collect(),
    };
    std::fs::create_dir_all(&out)?;
    let mut table = String::from(
        "| effect | magnitude | preset (action) | mean shift (mm) | 90th-percentile shift (mm) |\n|---|---:|---|---:|---:|\n",
    );
    let presets: Vec<Preset> = match args.get(3) {
        Some(list) => list
            .split(',')
            .map(|s| <Preset as clap::ValueEnum>::from_str(s, true))
            .collect::<Result<_, _>>()?,
        None => vec![Preset::Rope, Preset::Cloth, Preset::Toy],
    };
    for preset in presets {
        let null = truth(preset, seed, None);
        let frames = null.frames.len();
        let [a, b] = Split::default_for(frames).test;
        let action = SynthConfig::diagnosis(preset, seed).resolved_action();
        for &spec in &effects {
            let (name, magnitude) = (spec.name, spec.magnitude);
            let with = truth(preset, seed, Some(spec));
            let [mean, p90] = (a..b)
                .map(|t| shift_mm(&null, &with, name, t))
                .fold([0.0; 2], |acc, v| [acc[0] + v[0], acc[1] + v[1]])
                .map(|v| v / (b - a).max(1) as f64);
            let row = format!(
                "| {} | {magnitude} | {} ({}) | {mean:.1} | {p90:.1} |",
                name.name(),
                preset.name(),
                action.name()
            );
            println!("{row}");
            writeln!(table, "{row}")?;
        }
    }
    std::fs::write(out.join("visibility.md"), table)?;
    Ok(())
}
