//! The kernel sources and their compilation by NVRTC.

use crate::error::CudaError;
use cudarc::nvrtc::{CompileOptions, Ptx};

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

/// Compiles `unit` (the kernels of `precision`, possibly with checks
/// appended) to PTX for `arch`.
pub fn compile_source(unit: String, precision: Precision, arch: &str) -> Result<Ptx, CudaError> {
    if !nvrtc_available() {
        return Err(CudaError::NoNvrtc);
    }
    let options = CompileOptions {
        options: vec![format!("--gpu-architecture={arch}"), "--std=c++17".into()],
        name: Some(format!("dm_mpm_{}.cu", precision.c_type())),
        ..Default::default()
    };
    cudarc::nvrtc::compile_ptx_with_opts(unit, options).map_err(|e| CudaError::Compile {
        precision: precision.c_type(),
        log: format!("{e:?}"),
    })
}
