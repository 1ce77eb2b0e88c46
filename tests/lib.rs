//! Shared helpers for the end-to-end tests in this folder.

use dm_synth::{Preset, SynthConfig};

/// A scene small enough for a test: 14 frames, tiny images, few particles.
pub fn tiny_config(preset: Preset, seed: u64) -> SynthConfig {
    let mut config = SynthConfig::new(preset, seed);
    config.frames = 14;
    config.width = 48;
    config.height = 36;
    config.truth_particles = 2000;
    config.tracks = 60;
    config.bundle_particles = 800;
    config
}
