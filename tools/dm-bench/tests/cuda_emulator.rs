//! The CUDA backend's kernels and the host code that launches them, run
//! without a GPU: `crates/dm-cuda/emulator` builds a libcuda.so that executes
//! the kernels (compiled as C++) on the CPU, and `dm-bench cuda-parity`
//! runs under it, comparing the CUDA world and the residual network on the
//! "device" with the CPU path. This checks what the kernels compute, not
//! the GPU's concurrency (docs/gpu.md, "Checks").

use std::path::{Path, PathBuf};
use std::process::Command;

/// The emulator, built once for the tests of this file (they run at once).
fn emulator() -> &'static Path {
    static LIBRARY: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    LIBRARY.get_or_init(|| {
        dm_cuda::emulator::build(&Path::new(env!("CARGO_TARGET_TMPDIR")).join("cuda-emulator"))
            .unwrap_or_else(|e| panic!("{e}"))
    })
}

/// Calls of `kind` in the emulator's counts file.
fn calls(counts: &str, kind: &str) -> u64 {
    counts
        .lines()
        .find_map(|line| line.strip_prefix(kind)?.strip_prefix(' '))
        .and_then(|rest| rest.split(' ').next()?.parse().ok())
        .unwrap_or(0)
}

/// `dm-bench cuda-parity ARGS` under the emulator (captured launches
/// refused where asked); asserts it succeeded and returns its stdout,
/// stderr and the emulator's counts.
fn parity_under_emulator(args: &[&str], refuse_captured_launches: bool) -> [String; 3] {
    let name = if refuse_captured_launches {
        "refused"
    } else {
        "graphs"
    };
    let counts = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("cuda-emulator-{name}.txt"));
    let _ = std::fs::remove_file(&counts);
    let mut command = Command::new(env!("CARGO_BIN_EXE_dm-bench"));
    command
        .arg("cuda-parity")
        .args(args)
        .env("LD_PRELOAD", emulator())
        .env("DM_CUDA_EMULATOR_COUNTS", &counts)
        .env_remove("DM_CUDA_GRAPHS")
        .env_remove("DM_CUDA_EMULATOR_REFUSE_CAPTURED_LAUNCHES");
    if refuse_captured_launches {
        command.env("DM_CUDA_EMULATOR_REFUSE_CAPTURED_LAUNCHES", "1");
    }
    let output = command.output().expect("running dm-bench cuda-parity");
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert!(
        output.status.success(),
        "cuda-parity {args:?} under the emulator failed:\n{stdout}\n{stderr}"
    );
    let counts = std::fs::read_to_string(&counts).expect("the emulator's counts");
    [stdout, stderr, counts]
}

#[test]
fn the_cuda_kernels_match_the_cpu_under_the_emulator() {
    let [stdout, stderr, counts] =
        parity_under_emulator(&["--particles", "400", "--frames", "2"], false);
    assert!(
        stdout.contains("CUDA emulator (CPU)"),
        "the parity ran on another device:\n{stdout}"
    );
    // The untaped substeps ran as CUDA graphs, captured and replayed.
    let calls = |kind: &str| calls(&counts, kind);
    assert!(
        calls("graph_capture") > 0 && calls("graph_launch") > calls("graph_capture"),
        "no CUDA graph was captured and replayed:\n{counts}\n{stderr}"
    );
    assert!(
        calls("replayed_launch") > 0,
        "graphs replayed no launch:\n{counts}"
    );
    assert!(
        !stderr.contains("graph capture failed"),
        "a graph capture failed:\n{stderr}"
    );
    // A world started again replays its graphs and steps as it did.
    for scene in ["Hands", "Plastic"] {
        for precision in ["double", "float"] {
            let line = format!(
                "restarted world {scene} {precision}: frame 1 again, max |dx|/domain 0.000e0, graphs captured again 0 — pass"
            );
            assert!(stdout.contains(&line), "no `{line}` in:\n{stdout}");
        }
    }
    // The fit's backward pass: a frame kept at its window, the window taped again.
    for precision in ["double", "float"] {
        assert!(
            stdout.contains(&format!("kept state parity Hands {precision}"))
                && stdout.contains("substeps from the kept state"),
            "no kept-state parity in {precision}:\n{stdout}"
        );
    }
    for kind in ["Pgnd", "Mlp"] {
        assert!(
            stdout.contains(&format!(
                "residual {kind} f64 on the GPU, VJP against finite differences"
            )),
            "no finite-difference check of the {kind} residual in:\n{stdout}"
        );
        for precision in ["f32", "f64"] {
            assert!(
                stdout.contains(&format!("residual {kind} {precision} gradients")),
                "no residual {kind} {precision} check in:\n{stdout}"
            );
        }
    }
}

/// Where the driver refuses a capture (here every launch while capturing),
/// the world says so once, gives up graphs and launches the substeps one
/// by one, with the same positions.
#[test]
fn a_refused_capture_falls_back_to_launches_one_by_one() {
    let [stdout, stderr, counts] = parity_under_emulator(
        &["--particles", "400", "--frames", "2", "--positions-only"],
        true,
    );
    assert_eq!(
        stderr.matches("graph capture failed").count(),
        1,
        "the refusal was not reported once:\n{stderr}"
    );
    assert_eq!(calls(&counts, "graph_launch"), 0, "a graph ran:\n{counts}");
    assert!(
        calls(&counts, "host_launch") > 0,
        "nothing launched:\n{counts}"
    );
    assert_eq!(
        stdout.matches(" — pass").count(),
        8,
        "not every position parity passed:\n{stdout}"
    );
}
