//! dm-synth
