use dm_mpm::SimError;

/// Why the CUDA backend could not start or run.
#[derive(Debug, thiserror::Error)]
pub enum CudaError {
    #[error(
        "no CUDA driver found (libcuda.so could not be loaded): run on a machine with an NVIDIA GPU and driver, or use --device cpu"
    )]
    NoDriver,
    #[error(
        "NVRTC (libnvrtc.so.13) could not be loaded: install the CUDA 13 runtime compiler (the CUDA toolkit or PyPI nvidia-cuda-nvrtc) and put its lib folder on LD_LIBRARY_PATH"
    )]
    NoNvrtc,
    #[error("no CUDA device could be opened: {0}")]
    NoDevice(String),
    #[error("compiling the MPM kernels ({precision}) failed: {log}")]
    Compile {
        precision: &'static str,
        log: String,
    },
    #[error("CUDA driver call failed: {0}")]
    Driver(#[from] cudarc::driver::DriverError),
    #[error("not supported on the cuda device: {0}")]
    Unsupported(String),
    #[error(transparent)]
    Sim(#[from] SimError),
    #[error(transparent)]
    Residual(#[from] dm_residual::ResidualError),
}
