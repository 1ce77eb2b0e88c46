//! Shared set-up of the staged-fit tests: a tiny synthetic rope and
//! `FitOptions` parsed from dm-fit's own flags.

use clap::Parser;
use dm_bundle::Bundle;
use dm_fit::run::FitOptions;
use dm_synth::{Preset, SynthConfig};
use std::path::Path;

#[derive(Parser)]
#[command(name = "dm-fit", no_binary_name = true)]
struct Flags {
    #[command(flatten)]
    options: FitOptions,
}

/// One material step, no gain search, stage 3 off, 8 patches: the
/// shortest staged fit, before each test's own flags.
const ONE_STEP: [&str; 10] = [
    "--iters",
    "1",
    "--stage2-iters",
    "0",
    "--gain-evals",
    "0",
    "--patches",
    "8",
    "--rgb-iters",
    "0",
];

/// dm-fit's options for the shortest staged fit plus `flags`.
pub fn fit_options(flags: &[&str]) -> FitOptions {
    try_fit_options(flags).expect("flags")
}

/// The same, or clap's refusal of `flags`.
#[allow(dead_code)] // Not every test binary that shares this module refuses flags.
pub fn try_fit_options(flags: &[&str]) -> Result<FitOptions, clap::Error> {
    Flags::try_parse_from(ONE_STEP.iter().chain(flags)).map(|f| f.options)
}

/// `SynthConfig::tiny` rope, seed 5, written under `dir` and opened.
pub fn tiny_rope(dir: &Path) -> Bundle {
    let scene = dir.join("scene");
    dm_synth::generate(
        &SynthConfig::tiny(Preset::Rope, 5),
        &scene,
        &dir.join("truth.json"),
        &mut |_, _, _| {},
    )
    .expect("scene");
    Bundle::open(&scene).expect("bundle")
}
