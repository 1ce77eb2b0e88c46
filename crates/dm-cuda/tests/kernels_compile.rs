//! Every kernel compiles to PTX with NVRTC, in both precisions — on any
//! machine, GPU or not. `make test` provides NVRTC (PyPI
//! nvidia-cuda-nvrtc) and names its library folder in LD_LIBRARY_PATH.

use dm_cuda::Precision;
use dm_cuda::consts::layout_check_source;
use dm_cuda::kernels::{
    ENTRY_POINTS, RESIDUAL_ENTRY_POINTS, compile, compile_source, nvrtc_available,
};

#[test]
fn every_kernel_compiles_to_ptx_in_both_precisions() {
    assert!(
        nvrtc_available(),
        "NVRTC (libnvrtc.so.13) not found: run through `make test`, which installs PyPI \
         nvidia-cuda-nvrtc and puts it on LD_LIBRARY_PATH"
    );
    for precision in [Precision::F32, Precision::F64] {
        // The oldest architecture with double-precision atomic adds, and
        // the H100's.
        for arch in ["compute_75", "compute_90"] {
            let ptx = compile(precision, arch)
                .unwrap_or_else(|e| panic!("{precision:?} for {arch}: {e}"))
                .to_src();
            for entry in ENTRY_POINTS.iter().chain(&RESIDUAL_ENTRY_POINTS) {
                assert!(
                    ptx.contains(&format!(".entry {entry}(")),
                    "{precision:?} {arch}: no entry point {entry}"
                );
            }
        }
    }
}

#[test]
fn the_kernels_constants_have_the_hosts_layout() {
    assert!(nvrtc_available(), "NVRTC not found (see above)");
    for precision in [Precision::F32, Precision::F64] {
        compile_source(layout_check_source(precision), precision, "compute_75")
            .unwrap_or_else(|e| panic!("{precision:?}: {e}"));
    }
}
