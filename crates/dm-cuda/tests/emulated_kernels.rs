//! Kernels run one by one through the CUDA emulator (docs/gpu.md,
//! "Checks"), at sizes the worlds of the tests do not reach.

use std::path::Path;
use std::process::Command;

/// The cell sort's two-level scan at one chunk, at a chunk's edges, and
/// with more chunk sums than one block of `scan_sums` scans at a time
/// (128³ grids have 2 048 chunks), against a running sum on the host.
#[test]
fn the_cell_sorts_scan_matches_a_running_sum_at_every_chunk_count() {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("cuda-emulator-checks");
    let library = dm_cuda::emulator::build(&dir).unwrap_or_else(|e| panic!("{e}"));
    let program =
        dm_cuda::emulator::build_check("scan", &library).unwrap_or_else(|e| panic!("{e}"));
    let sizes = [
        "1", "1000", "1024", "1025", "32768", "1048576", "1048577", "2097152",
    ];
    let output = Command::new(&program)
        .args(sizes)
        .env("LD_LIBRARY_PATH", &dir)
        .output()
        .expect("running the scan check");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "the scan check failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert_eq!(
        stdout.matches("exclusive scan matches").count(),
        sizes.len(),
        "not every size was checked:\n{stdout}"
    );
}
