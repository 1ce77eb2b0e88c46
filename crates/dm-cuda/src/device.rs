//! Opening the GPU and compiling the kernels for it.

use crate::error::CudaError;
use crate::kernels::{self, Precision};
use cudarc::driver::{CudaContext, CudaFunction, CudaModule, CudaStream};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// The environment variable that turns CUDA graphs off (`off` or `0`),
/// for comparing with launches one by one.
pub const GRAPHS_VARIABLE: &str = "DM_CUDA_GRAPHS";

/// One GPU with a stream and the kernels compiled for it (per precision,
/// on first use).
#[derive(Debug)]
pub struct CudaDevice {
    context: Arc<CudaContext>,
    stream: Arc<CudaStream>,
    arch: String,
    /// Shared by the handles of every stream of this GPU.
    modules: Arc<Mutex<HashMap<Precision, Arc<CudaModule>>>>,
    /// Whether frames replay their substeps as CUDA graphs (shared by
    /// every stream's handle; turned off for good by a failed capture).
    graphs: Arc<AtomicBool>,
}

/// The entry points of one compiled module.
#[derive(Clone, Debug)]
pub(crate) struct Kernels {
    pub cell_count: CudaFunction,
    pub scan_chunks: CudaFunction,
    pub scan_sums: CudaFunction,
    pub scatter_order: CudaFunction,
    pub p2g: CudaFunction,
    pub grid_update: CudaFunction,
    pub g2p: CudaFunction,
    pub actuator_accel: CudaFunction,
    pub enforce_rigid: CudaFunction,
    pub g2p_backward_gather: CudaFunction,
    pub g2p_backward_scatter: CudaFunction,
    pub grid_update_backward: CudaFunction,
    pub p2g_backward: CudaFunction,
    pub actuator_accel_backward: CudaFunction,
    pub zero_coupled: CudaFunction,
}

/// Has the device's default memory pool keep what is freed for the next
/// allocation: by default the pool hands its unused memory back to the
/// driver at every synchronisation, and each frame of a fit synchronises
/// (the divergence check) and then allocates its tape anew, which would
/// map fresh memory every frame. The process keeps its peak use until it
/// exits.
fn keep_freed_memory(context: &CudaContext) -> Result<(), CudaError> {
    use cudarc::driver::{result::mem_pool, sys};
    let mut threshold = u64::MAX;
    // SAFETY: the device is the context's; the release threshold is a u64,
    // and the pointer lives for the call.
    unsafe {
        let pool = cudarc::driver::result::device::get_default_mem_pool(context.cu_device())?;
        mem_pool::set_attribute(
            pool,
            sys::CUmemPool_attribute::CU_MEMPOOL_ATTR_RELEASE_THRESHOLD,
            (&raw mut threshold).cast(),
        )?;
    }
    Ok(())
}

impl CudaDevice {
    /// Opens GPU `ordinal`: fails with a clear error where no driver, no
    /// device or no NVRTC is found.
    pub fn open(ordinal: usize) -> Result<Arc<Self>, CudaError> {
        // SAFETY: only probes whether the shared library can be opened.
        if !unsafe { cudarc::driver::sys::is_culib_present() } {
            return Err(CudaError::NoDriver);
        }
        if !kernels::nvrtc_available() {
            return Err(CudaError::NoNvrtc);
        }
        let context = CudaContext::new(ordinal).map_err(|e| CudaError::NoDevice(e.to_string()))?;
        // cudarc otherwise records an event per buffer argument of every
        // launch and makes the stream wait on each (about 15 driver calls
        // per launch here), which costs more host time than the launch
        // itself at the scale of a fitted scene.
        // SAFETY: every buffer is allocated, used and freed on one stream
        // (a world's, a residual call's); the one exception, the residual
        // network's weights, is read by other streams only after the
        // stream that wrote them has been waited for (`CudaResidual`).
        unsafe { context.disable_event_tracking() };
        if context.has_async_alloc() {
            keep_freed_memory(&context)?;
        }
        let (major, minor) = context.compute_capability()?;
        let stream = context.new_stream()?;
        let graphs = !matches!(std::env::var(GRAPHS_VARIABLE).as_deref(), Ok("off" | "0"));
        Ok(Arc::new(Self {
            context,
            stream,
            arch: format!("compute_{major}{minor}"),
            modules: Arc::new(Mutex::new(HashMap::new())),
            graphs: Arc::new(AtomicBool::new(graphs)),
        }))
    }

    /// The same GPU and compiled kernels with a stream of its own: worlds
    /// on different streams run concurrently (many small worlds stepped
    /// from several host threads fill the GPU where one cannot).
    pub fn with_own_stream(&self) -> Result<Arc<Self>, CudaError> {
        Ok(Arc::new(Self {
            context: self.context.clone(),
            stream: self.context.new_stream()?,
            arch: self.arch.clone(),
            modules: self.modules.clone(),
            graphs: self.graphs.clone(),
        }))
    }

    /// Whether frames replay their substeps as CUDA graphs.
    pub fn graphs_enabled(&self) -> bool {
        self.graphs.load(Ordering::Relaxed)
    }

    /// Turns CUDA graphs off after a capture failed, saying so once:
    /// substeps are then launched one by one, which computes the same.
    pub(crate) fn give_up_graphs(&self, why: &CudaError) {
        if self.graphs.swap(false, Ordering::Relaxed) {
            eprintln!("warning: CUDA graph capture failed ({why}); launching substeps one by one");
        }
    }

    /// The device's name as the driver reports it.
    pub fn name(&self) -> String {
        self.context
            .name()
            .unwrap_or_else(|e| format!("unknown ({e})"))
    }

    pub fn stream(&self) -> &Arc<CudaStream> {
        &self.stream
    }

    /// The virtual architecture kernels are compiled for.
    pub fn arch(&self) -> &str {
        &self.arch
    }

    /// The kernels of `precision`, compiled on first use.
    pub(crate) fn module(&self, precision: Precision) -> Result<Arc<CudaModule>, CudaError> {
        let mut modules = self
            .modules
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        Ok(match modules.get(&precision) {
            Some(module) => module.clone(),
            None => {
                let cache = kernels::cache_dir();
                let ptx = kernels::compile_cached(precision, &self.arch, cache.as_deref())?;
                // A cached file the driver refuses (changed by hand, or
                // written for another driver) is replaced by a fresh compile.
                let module = match self.context.load_module(ptx) {
                    Ok(module) => module,
                    Err(_) if cache.is_some() => {
                        kernels::forget_cached(precision, &self.arch, cache.as_deref());
                        let fresh =
                            kernels::compile_cached(precision, &self.arch, cache.as_deref())?;
                        self.context.load_module(fresh)?
                    }
                    Err(e) => return Err(e.into()),
                };
                modules.insert(precision, module.clone());
                module
            }
        })
    }

    pub(crate) fn kernels(&self, precision: Precision) -> Result<Kernels, CudaError> {
        let module = self.module(precision)?;
        Ok(Kernels {
            cell_count: module.load_function("cell_count")?,
            scan_chunks: module.load_function("scan_chunks")?,
            scan_sums: module.load_function("scan_sums")?,
            scatter_order: module.load_function("scatter_order")?,
            p2g: module.load_function("p2g")?,
            grid_update: module.load_function("grid_update")?,
            g2p: module.load_function("g2p")?,
            actuator_accel: module.load_function("actuator_accel")?,
            enforce_rigid: module.load_function("enforce_rigid")?,
            g2p_backward_gather: module.load_function("g2p_backward_gather")?,
            g2p_backward_scatter: module.load_function("g2p_backward_scatter")?,
            grid_update_backward: module.load_function("grid_update_backward")?,
            p2g_backward: module.load_function("p2g_backward")?,
            actuator_accel_backward: module.load_function("actuator_accel_backward")?,
            zero_coupled: module.load_function("zero_coupled")?,
        })
    }
}
