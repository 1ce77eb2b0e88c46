//! End-to-end tests of the whole pipeline, one file per issue
//! (`issue2_pipeline.rs`, ...); scenes come from `dm_synth::SynthConfig::tiny`.
