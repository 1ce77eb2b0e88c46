//! The kernel sources and their compilation by NVRTC.

use crate::error::CudaError;
use cudarc::nvrtc::{CompileOptions, Ptx};
use std::path::{Path, PathBuf};

/// The float type a compiled module works in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Precision {
    F32,
    F64,
}

impl Precision {
    /// The C type the kernels' `real` stands for.
    pub fn c_type(self) -> &'static str {
        match self {
            Precision::F32 => "float",
            Precision::F64 => "double",
        }
    }
}

/// The kernel files in the order they are concatenated into one unit.
pub const FILES: [(&str, &str); 17] = [
    ("common.cuh", include_str!("../kernels/common.cuh")),
    ("svd.cuh", include_str!("../kernels/svd.cuh")),
    ("stress.cuh", include_str!("../kernels/stress.cuh")),
    ("moments.cuh", include_str!("../kernels/moments.cuh")),
    (
        "svd_backward.cuh",
        include_str!("../kernels/svd_backward.cuh"),
    ),
    (
        "stress_backward.cuh",
        include_str!("../kernels/stress_backward.cuh"),
    ),
    ("sort.cu", include_str!("../kernels/sort.cu")),
    ("p2g.cu", include_str!("../kernels/p2g.cu")),
    ("grid_update.cu", include_str!("../kernels/grid_update.cu")),
    ("g2p.cu", include_str!("../kernels/g2p.cu")),
    ("actuators.cu", include_str!("../kernels/actuators.cu")),
    (
        "g2p_backward.cu",
        include_str!("../kernels/g2p_backward.cu"),
    ),
    (
        "grid_update_backward.cu",
        include_str!("../kernels/grid_update_backward.cu"),
    ),
    (
        "p2g_backward.cu",
        include_str!("../kernels/p2g_backward.cu"),
    ),
    (
        "actuators_backward.cu",
        include_str!("../kernels/actuators_backward.cu"),
    ),
    ("residual.cu", include_str!("../kernels/residual.cu")),
    (
        "residual_backward.cu",
        include_str!("../kernels/residual_backward.cu"),
    ),
];

/// The MPM substep's entry points.
pub const ENTRY_POINTS: [&str; 15] = [
    "cell_count",
    "scan_chunks",
    "scan_sums",
    "scatter_order",
    "p2g",
    "grid_update",
    "g2p",
    "actuator_accel",
    "enforce_rigid",
    "g2p_backward_gather",
    "g2p_backward_scatter",
    "grid_update_backward",
    "p2g_backward",
    "actuator_accel_backward",
    "zero_coupled",
];

/// The residual network's entry points.
pub const RESIDUAL_ENTRY_POINTS: [&str; 26] = [
    "residual_gemm",
    "residual_fill_rows",
    "residual_relu",
    "residual_column_sums",
    "residual_group_sums",
    "residual_norm_forward",
    "residual_column_max",
    "residual_pooled_bias",
    "residual_mark_nodes",
    "residual_number_nodes",
    "residual_stencil_slots",
    "residual_node_encoding",
    "residual_spline_weights",
    "residual_node_sums",
    "residual_node_divide",
    "residual_to_particles",
    "residual_bound",
    "residual_relu_backward",
    "residual_scale_columns",
    "residual_norm_backward",
    "residual_pooled_backward",
    "residual_spline_weights_backward",
    "residual_node_means_backward_nodes",
    "residual_node_means_backward_weights",
    "residual_to_particles_backward",
    "residual_bound_backward",
];

/// The whole translation unit for `precision`.
pub fn source(precision: Precision) -> String {
    let mut unit = format!("#define REAL {}\n", precision.c_type());
    for (name, text) in FILES {
        unit.push_str(&format!("// ---- {name}\n#line 1 \"{name}\"\n"));
        unit.push_str(text);
        unit.push('\n');
    }
    unit
}

/// Whether NVRTC can be loaded on this machine.
pub fn nvrtc_available() -> bool {
    // SAFETY: only probes whether the shared library can be opened.
    unsafe { cudarc::nvrtc::sys::is_culib_present() }
}

/// Compiles the kernels to PTX for the virtual architecture `arch`
/// (e.g. `compute_90`).
pub fn compile(precision: Precision, arch: &str) -> Result<Ptx, CudaError> {
    compile_source(source(precision), precision, arch)
}

/// The options NVRTC compiles for `arch` with.
fn compile_options(arch: &str) -> Vec<String> {
    vec![format!("--gpu-architecture={arch}"), "--std=c++17".into()]
}

/// Compiles `unit` (the kernels of `precision`, possibly with checks
/// appended) to PTX for `arch`.
pub fn compile_source(unit: String, precision: Precision, arch: &str) -> Result<Ptx, CudaError> {
    if !nvrtc_available() {
        return Err(CudaError::NoNvrtc);
    }
    let options = CompileOptions {
        options: compile_options(arch),
        name: Some(format!("dm_mpm_{}.cu", precision.c_type())),
        ..Default::default()
    };
    cudarc::nvrtc::compile_ptx_with_opts(unit, options).map_err(|e| CudaError::Compile {
        precision: precision.c_type(),
        log: format!("{e:?}"),
    })
}

/// The environment variable naming the folder compiled kernels are kept
/// in between processes (`off` keeps none); by default
/// `$XDG_CACHE_HOME/deformmaster/cuda`, else `~/.cache/deformmaster/cuda`.
pub const CACHE_VARIABLE: &str = "DM_CUDA_CACHE";

/// The folder [`CACHE_VARIABLE`] names, or none where it is `off` or no
/// home is known.
pub fn cache_dir() -> Option<PathBuf> {
    match std::env::var_os(CACHE_VARIABLE) {
        Some(dir) if dir == "off" || dir == "0" => None,
        Some(dir) if !dir.is_empty() => Some(PathBuf::from(dir)),
        _ => std::env::var_os("XDG_CACHE_HOME")
            .filter(|d| !d.is_empty())
            .map(PathBuf::from)
            .or_else(|| std::env::var_os("HOME").map(|h| Path::new(&h).join(".cache")))
            .map(|d| d.join("deformmaster").join("cuda")),
    }
}

/// NVRTC's version, which the cache key includes: another compiler may
/// emit other PTX for the same source.
fn nvrtc_version() -> (i32, i32) {
    let (mut major, mut minor) = (0, 0);
    // SAFETY: NVRTC is loaded (checked by the caller); the pointers live
    // for the call.
    unsafe { cudarc::nvrtc::sys::nvrtcVersion(&raw mut major, &raw mut minor) };
    (major, minor)
}

/// The file the PTX of `unit` for `arch` is kept in under a cache folder:
/// named by a digest of everything the compiler is given.
pub fn cache_file(unit: &str, arch: &str) -> String {
    use sha2::Digest;
    let mut digest = sha2::Sha256::new();
    let (major, minor) = nvrtc_version();
    digest.update(format!("nvrtc {major}.{minor}\n").as_bytes());
    for option in compile_options(arch) {
        digest.update(option.as_bytes());
        digest.update(b"\n");
    }
    digest.update(unit.as_bytes());
    let hex: String = digest
        .finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    format!("dm_mpm_{arch}_{}.ptx", &hex[..32])
}

/// The kernels of `precision` for `arch` as [`compile`] makes them, read
/// from `cache` where an earlier process left them there, else compiled
/// and left there (NVRTC takes seconds for the whole unit). A cache that
/// cannot be written is skipped with a warning: the kernels still run.
pub fn compile_cached(
    precision: Precision,
    arch: &str,
    cache: Option<&Path>,
) -> Result<Ptx, CudaError> {
    let Some(dir) = cache else {
        return compile(precision, arch);
    };
    if !nvrtc_available() {
        return Err(CudaError::NoNvrtc);
    }
    let unit = source(precision);
    let path = dir.join(cache_file(&unit, arch));
    if let Ok(text) = std::fs::read_to_string(&path) {
        return Ok(Ptx::from_src(text));
    }
    let ptx = compile_source(unit, precision, arch)?;
    if let Err(e) = write_atomically(&path, ptx.to_src().as_bytes()) {
        eprintln!(
            "warning: compiled kernels not cached in {} ({e}); set {CACHE_VARIABLE}=off to skip the cache",
            dir.display()
        );
    }
    Ok(ptx)
}

/// Removes what [`compile_cached`] keeps for `precision` and `arch` in
/// `cache`, if anything.
pub fn forget_cached(precision: Precision, arch: &str, cache: Option<&Path>) {
    if let Some(dir) = cache {
        let _ = std::fs::remove_file(dir.join(cache_file(&source(precision), arch)));
    }
}

/// Writes `bytes` to `path` under a temporary name, then renames it, so a
/// process reading the cache never sees half a file.
fn write_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir)?;
    let temporary = dir.join(format!(
        ".{}.{}.tmp",
        path.file_name().and_then(|n| n.to_str()).unwrap_or("ptx"),
        std::process::id()
    ));
    std::fs::write(&temporary, bytes)?;
    std::fs::rename(&temporary, path).inspect_err(|_| {
        let _ = std::fs::remove_file(&temporary);
    })
}
