//! Seeded, structure-aware mutation fuzzing of the parsers that read what
//! users give the tools (docs/RELIABILITY.md). Each [`Target`] starts from
//! committed seed inputs (`fuzz/corpus/TARGET/`), mutates them with a
//! seeded generator ([`mutate`]) and feeds every mutant to the parser: an
//! `Err` is the expected answer to bad input, a panic or an input slower
//! than [`SLOW_INPUT_SECONDS`] is a finding, saved for a regression test,
//! and so is one holding more than [`MAX_INPUT_BYTES`] of heap at once
//! (measured where [`alloc_meter::MeteredAllocator`] is installed).

pub mod alloc_meter;
pub mod kill;
pub mod mutate;
pub mod targets;

pub use targets::Target;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// An input taking longer than this counts as a hang.
pub const SLOW_INPUT_SECONDS: f64 = 2.0;

/// An input whose parse holds more heap than this at once counts as an
/// unbounded allocation (the largest valid seed needs a few MiB).
pub const MAX_INPUT_BYTES: usize = 256 << 20;

/// Why a fuzz run could not start.
#[derive(Debug, thiserror::Error)]
pub enum FuzzError {
    #[error("{path}: {message}")]
    Corpus { path: PathBuf, message: String },
    #[error("scratch directory: {0}")]
    Scratch(#[from] std::io::Error),
}

/// One input the parser panicked on or was slow with.
#[derive(Clone, Debug)]
pub struct Finding {
    pub input: Vec<u8>,
    pub what: String,
}

/// What a run of one target did.
#[derive(Clone, Debug)]
pub struct Report {
    pub target: Target,
    pub inputs: u64,
    /// Inputs the parser accepted (the rest it refused with an error).
    pub accepted: u64,
    pub seconds: f64,
    pub slowest_input_seconds: f64,
    /// The most heap one input held at once (bytes); `None` without the
    /// metered allocator.
    pub largest_input_bytes: Option<usize>,
    pub findings: Vec<Finding>,
}

/// Stop after this many inputs or this many seconds, whichever is first.
#[derive(Clone, Copy, Debug)]
pub struct Budget {
    pub inputs: u64,
    pub seconds: f64,
}

/// Fuzzes `target` from the seeds in `corpus` (its `corpus/TARGET/`
/// folder) with the generator seeded by `seed`.
pub fn run(target: Target, corpus: &Path, seed: u64, budget: Budget) -> Result<Report, FuzzError> {
    let seeds = target.seeds(corpus)?;
    let scratch = tempfile::tempdir()?;
    let mut harness = target.harness(scratch.path(), corpus)?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ target.salt());
    let quiet = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let start = Instant::now();
    let mut report = Report {
        target,
        inputs: 0,
        accepted: 0,
        seconds: 0.0,
        slowest_input_seconds: 0.0,
        largest_input_bytes: alloc_meter::is_installed().then_some(0),
        findings: Vec::new(),
    };
    // The seeds themselves first, then their mutants.
    let mut next = 0usize;
    while report.inputs < budget.inputs && start.elapsed().as_secs_f64() < budget.seconds {
        let input = if next < seeds.len() {
            seeds[next].clone()
        } else {
            mutate::mutant(&seeds, target.is_text(), &mut rng)
        };
        next += 1;
        let clock = Instant::now();
        let heap = alloc_meter::start();
        let outcome =
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| harness.feed(&input)));
        let took = clock.elapsed().as_secs_f64();
        let held = alloc_meter::peak_since(heap);
        if let Some(largest) = report.largest_input_bytes.as_mut() {
            *largest = (*largest).max(held);
            if held > MAX_INPUT_BYTES {
                report.findings.push(Finding {
                    input: input.clone(),
                    what: format!("allocation: {} MiB held at once", held >> 20),
                });
            }
        }
        report.inputs += 1;
        report.slowest_input_seconds = report.slowest_input_seconds.max(took);
        match outcome {
            Ok(true) => report.accepted += 1,
            Ok(false) => {}
            Err(payload) => report.findings.push(Finding {
                input: input.clone(),
                what: format!("panic: {}", panic_message(&payload)),
            }),
        }
        if took > SLOW_INPUT_SECONDS {
            report.findings.push(Finding {
                input,
                what: format!("slow: {took:.1} s"),
            });
        }
    }
    std::panic::set_hook(quiet);
    report.seconds = start.elapsed().as_secs_f64();
    Ok(report)
}

/// Feeds one input to `target` (seed files from the default corpus):
/// whether the parser accepted it, or the panic's message as an error.
pub fn feed_once(target: Target, input: &[u8]) -> Result<bool, String> {
    let corpus = default_corpus();
    let scratch = tempfile::tempdir().map_err(|e| e.to_string())?;
    let mut harness = target
        .harness(scratch.path(), &corpus)
        .map_err(|e| e.to_string())?;
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| harness.feed(input)))
        .map_err(|payload| format!("panic: {}", panic_message(&payload)))
}

fn panic_message(payload: &Box<dyn std::any::Any + Send>) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "(no message)".into())
}

/// The committed seed corpus (`fuzz/corpus` at the workspace root).
pub fn default_corpus() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fuzz/corpus")
}
