//! End-to-end tests of the whole pipeline, one file per issue
//! (`pipeline.rs`, ...); scenes come from `dm_synth::SynthConfig::tiny`.
