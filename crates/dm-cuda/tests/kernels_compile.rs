//! Every kernel compiles to PTX with NVRTC, in both precisions — on any
//! machine, GPU or not. `make test` provides NVRTC (PyPI
//! nvidia-cuda-nvrtc) and names its library folder in LD_LIBRARY_PATH.

use dm_cuda::Precision;
use dm_cuda::consts::layout_check_source;
use dm_cuda::kernels::{
    ENTRY_POINTS, RESIDUAL_ENTRY_POINTS, cache_file, compile, compile_cached, compile_source,
    forget_cached, nvrtc_available, source,
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

#[test]
fn compiled_kernels_are_kept_in_the_cache_and_read_back_from_it() {
    assert!(nvrtc_available(), "NVRTC not found (see above)");
    let cache = tempfile::tempdir().expect("a temporary folder");
    let (precision, arch) = (Precision::F32, "compute_90");
    let compiled = compile_cached(precision, arch, Some(cache.path()))
        .expect("compiling into the cache")
        .to_src();
    let file = cache.path().join(cache_file(&source(precision), arch));
    let kept = std::fs::read_to_string(&file).expect("the cache holds the compiled kernels");
    assert_eq!(kept, compiled);
    // A later call reads the file rather than compiling: what it returns
    // follows a change to the file.
    std::fs::write(&file, format!("{kept}// kept\n")).expect("writing the cache file");
    let read_back = compile_cached(precision, arch, Some(cache.path()))
        .expect("reading the cache")
        .to_src();
    assert!(
        read_back.ends_with("// kept\n"),
        "the cache file was not read"
    );
    // Another architecture or source is another file.
    assert_ne!(
        cache_file(&source(precision), "compute_75"),
        cache_file(&source(precision), arch)
    );
    assert_ne!(
        cache_file(&source(Precision::F64), arch),
        cache_file(&source(precision), arch)
    );
    forget_cached(precision, arch, Some(cache.path()));
    assert!(!file.exists(), "forget_cached left the file");
    // Nothing but the one file was written (no temporary left behind).
    assert_eq!(
        std::fs::read_dir(cache.path())
            .expect("the cache folder")
            .count(),
        0
    );
}
