//! The device buffers of a world and the launches of the substep's
//! stages over them, shared by the forward substep (`world.rs`) and its
//! adjoint (`backward.rs`).

use crate::consts::KernelConsts;
use crate::device::Kernels;
use crate::error::CudaError;
use crate::world::CouplingBuffers;
use crate::world::DeviceReal;
use cudarc::driver::{CudaSlice, CudaStream, CudaView, LaunchConfig, PushKernelArg};
use std::sync::Arc;
use std::time::Instant;

const BLOCK_THREADS: u32 = 256;

/// Launch shape covering `count` threads.
pub(crate) fn launch_for(count: usize) -> LaunchConfig {
    LaunchConfig {
        // Blocks counted before narrowing: `count` itself may pass u32.
        grid_dim: (
            u32::try_from(count.div_ceil(BLOCK_THREADS as usize).max(1)).unwrap_or(u32::MAX),
            1,
            1,
        ),
        block_dim: (BLOCK_THREADS, 1, 1),
        shared_mem_bytes: 0,
    }
}

/// Cells per block edge of the sort keys (sort.cu's SORT_BLOCK).
const SORT_BLOCK: usize = 4;
/// Values one block of the scan handles (sort.cu's SCAN_CHUNK), and its
/// threads (SCAN_THREADS).
pub(crate) const SCAN_CHUNK: usize = 1024;
pub(crate) const SCAN_THREADS: u32 = 256;

/// How many sort keys a grid of `res`³ cells has.
fn sort_key_count(res: usize) -> usize {
    res.div_ceil(SORT_BLOCK).pow(3) * SORT_BLOCK.pow(3)
}

/// A particle state (x, v, F, C), or its adjoint, on the device; matrices
/// column-major.
#[derive(Debug)]
pub(crate) struct ParticleBuffers<T> {
    pub x: CudaSlice<T>,
    pub v: CudaSlice<T>,
    pub f: CudaSlice<T>,
    pub c: CudaSlice<T>,
}

impl<T: DeviceReal> ParticleBuffers<T> {
    pub(crate) fn zeros(stream: &Arc<CudaStream>, n: usize) -> Result<Self, CudaError> {
        Ok(Self {
            x: stream.alloc_zeros(3 * n)?,
            v: stream.alloc_zeros(3 * n)?,
            f: stream.alloc_zeros(9 * n)?,
            c: stream.alloc_zeros(9 * n)?,
        })
    }

    /// Refuses states taped on another stream than `stream` (another
    /// world's): the backward pass would read them unsynchronised, as
    /// buffers carry no events (docs/gpu.md, "Streams").
    pub(crate) fn check_taped_on(
        states: &[Self],
        stream: &Arc<CudaStream>,
    ) -> Result<(), CudaError> {
        if states.iter().all(|s| Arc::ptr_eq(s.x.stream(), stream)) {
            Ok(())
        } else {
            Err(CudaError::Unsupported(
                "the tape was recorded by another world".into(),
            ))
        }
    }

    /// A device copy of `self`.
    pub(crate) fn duplicate(&self, stream: &Arc<CudaStream>) -> Result<Self, CudaError> {
        Ok(Self {
            x: stream.clone_dtod(&self.x)?,
            v: stream.clone_dtod(&self.v)?,
            f: stream.clone_dtod(&self.f)?,
            c: stream.clone_dtod(&self.c)?,
        })
    }
}

/// Per-particle mass, volume, Lamé parameters and expert weights.
#[derive(Debug)]
pub(crate) struct MaterialBuffers<T> {
    pub mass: CudaSlice<T>,
    pub volume: CudaSlice<T>,
    pub mu: CudaSlice<T>,
    pub lambda: CudaSlice<T>,
    pub weights: CudaSlice<T>,
}

/// The cell sort (sort.cu): each particle's cell key and rank in its
/// cell, the particles per key (scanned into starts), the scan's chunk
/// sums, and the slots in key order.
#[derive(Debug)]
pub(crate) struct SortBuffers {
    keys: CudaSlice<u32>,
    ranks: CudaSlice<u32>,
    counts: CudaSlice<u32>,
    chunk_sums: CudaSlice<u32>,
    order: CudaSlice<u32>,
}

impl SortBuffers {
    pub(crate) fn new(stream: &Arc<CudaStream>, n: usize, res: usize) -> Result<Self, CudaError> {
        let keys = sort_key_count(res);
        Ok(Self {
            keys: stream.alloc_zeros(n)?,
            ranks: stream.alloc_zeros(n)?,
            counts: stream.alloc_zeros(keys)?,
            chunk_sums: stream.alloc_zeros(keys.div_ceil(SCAN_CHUNK))?,
            order: stream.alloc_zeros(n)?,
        })
    }
}

/// What every launch of one substep shares.
pub(crate) struct Launcher<'a, T> {
    pub stream: &'a Arc<CudaStream>,
    pub kernels: &'a Kernels,
    pub k: &'a KernelConsts<T>,
    pub n: usize,
    pub res: usize,
}

impl<T: DeviceReal> Launcher<'_, T> {
    fn n_i32(&self) -> i32 {
        self.n as i32
    }

    /// The actuators' acceleration of the particles `p` towards the
    /// anchors at `anchor_x` (this substep's) moving at `anchor_v`.
    pub(crate) fn actuator_accel(
        &self,
        couplings: &CouplingBuffers<T>,
        p: &ParticleBuffers<T>,
        anchor_x: &CudaView<'_, T>,
        anchor_v: &CudaSlice<T>,
        accel: &mut CudaSlice<T>,
    ) -> Result<(), CudaError> {
        let n = self.n_i32();
        let mut launch = self.stream.launch_builder(&self.kernels.actuator_accel);
        launch
            .arg(self.k)
            .arg(&n)
            .arg(&p.x)
            .arg(&p.v)
            .arg(&couplings.row_start)
            .arg(&couplings.anchor)
            .arg(&couplings.rest_offset)
            .arg(anchor_x)
            .arg(anchor_v)
            .arg(accel);
        // SAFETY: the arguments match actuator_accel's signature and every
        // buffer holds what the launch shape indexes.
        unsafe { launch.launch(launch_for(self.n)) }?;
        Ok(())
    }

    /// Sorts the particles at `x` by cell.
    pub(crate) fn sort(&self, x: &CudaSlice<T>, sort: &mut SortBuffers) -> Result<(), CudaError> {
        let stream = self.stream;
        let n = self.n_i32();
        let keys = sort_key_count(self.res);
        let (keys_i32, chunks) = (keys as i32, keys.div_ceil(SCAN_CHUNK));
        let chunks_i32 = chunks as i32;
        stream.memset_zeros(&mut sort.counts)?;
        let mut launch = stream.launch_builder(&self.kernels.cell_count);
        launch
            .arg(self.k)
            .arg(&n)
            .arg(x)
            .arg(&mut sort.keys)
            .arg(&mut sort.ranks)
            .arg(&mut sort.counts);
        // SAFETY: the arguments match cell_count's signature; keys index
        // `counts`, sized for every key of the grid.
        unsafe { launch.launch(launch_for(self.n)) }?;
        let scan_block = |blocks: usize| LaunchConfig {
            grid_dim: (blocks as u32, 1, 1),
            block_dim: (SCAN_THREADS, 1, 1),
            shared_mem_bytes: 0,
        };
        let mut launch = stream.launch_builder(&self.kernels.scan_chunks);
        launch
            .arg(&mut sort.counts)
            .arg(&keys_i32)
            .arg(&mut sort.chunk_sums);
        // SAFETY: as above, for scan_chunks (one block per chunk).
        unsafe { launch.launch(scan_block(chunks)) }?;
        let mut launch = stream.launch_builder(&self.kernels.scan_sums);
        launch.arg(&mut sort.chunk_sums).arg(&chunks_i32);
        // SAFETY: as above, for scan_sums (one block).
        unsafe { launch.launch(scan_block(1)) }?;
        let mut launch = stream.launch_builder(&self.kernels.scatter_order);
        launch
            .arg(&n)
            .arg(&sort.keys)
            .arg(&sort.ranks)
            .arg(&sort.counts)
            .arg(&sort.chunk_sums)
            .arg(&mut sort.order);
        // SAFETY: as above, for scatter_order (starts + rank < n).
        unsafe { launch.launch(launch_for(self.n)) }?;
        Ok(())
    }

    /// Stress and P2G of the particles `p` (sorted by `sort`) into `grid`
    /// (cleared first); `accel` is the actuators' acceleration, if any.
    pub(crate) fn p2g(
        &self,
        sort: &SortBuffers,
        p: &ParticleBuffers<T>,
        material: &MaterialBuffers<T>,
        accel: Option<&CudaSlice<T>>,
        grid: &mut CudaSlice<T>,
    ) -> Result<(), CudaError> {
        self.stream.memset_zeros(grid)?;
        let has_accel = accel.is_some() as i32;
        // Never read without an acceleration; any buffer of the right type.
        let accel = accel.unwrap_or(&p.x);
        let n = self.n_i32();
        let mut launch = self.stream.launch_builder(&self.kernels.p2g);
        launch
            .arg(self.k)
            .arg(&n)
            .arg(&sort.order)
            .arg(&sort.keys)
            .arg(&p.x)
            .arg(&p.v)
            .arg(&p.f)
            .arg(&p.c)
            .arg(&material.mass)
            .arg(&material.volume)
            .arg(&material.mu)
            .arg(&material.lambda)
            .arg(&material.weights)
            .arg(&has_accel)
            .arg(accel)
            .arg(grid);
        // SAFETY: as above, for p2g.
        unsafe { launch.launch(launch_for(self.n)) }?;
        Ok(())
    }

    /// The grid update of `grid` in place.
    pub(crate) fn grid_update(&self, grid: &mut CudaSlice<T>) -> Result<(), CudaError> {
        let mut launch = self.stream.launch_builder(&self.kernels.grid_update);
        launch.arg(self.k).arg(grid);
        // SAFETY: as above, for grid_update (one thread per node).
        unsafe { launch.launch(launch_for(self.res.pow(3))) }?;
        Ok(())
    }

    /// G2P from `grid` into `p`, failures keyed by `substep`.
    pub(crate) fn g2p(
        &self,
        substep: usize,
        grid: &CudaSlice<T>,
        p: &mut ParticleBuffers<T>,
        failure: &mut CudaSlice<u64>,
    ) -> Result<(), CudaError> {
        let (substep, n) = (substep as i32, self.n_i32());
        let mut launch = self.stream.launch_builder(&self.kernels.g2p);
        launch
            .arg(self.k)
            .arg(&n)
            .arg(&substep)
            .arg(grid)
            .arg(&mut p.x)
            .arg(&mut p.v)
            .arg(&mut p.f)
            .arg(&mut p.c)
            .arg(failure);
        // SAFETY: as above, for g2p.
        unsafe { launch.launch(launch_for(self.n)) }?;
        Ok(())
    }

    /// G2P's adjoint pass 2: scatters ū_i += w (ṽ̄ + B̄ (x_i − x_p)) of
    /// the particles at `x` (sorted by `sort`) into `grad_u` (cleared first).
    pub(crate) fn scatter_velocity_adjoint(
        &self,
        sort: &SortBuffers,
        x: &CudaSlice<T>,
        bar_v: &CudaSlice<T>,
        bar_b: &CudaSlice<T>,
        grad_u: &mut CudaSlice<T>,
    ) -> Result<(), CudaError> {
        self.stream.memset_zeros(grad_u)?;
        let n = self.n_i32();
        let mut launch = self
            .stream
            .launch_builder(&self.kernels.g2p_backward_scatter);
        launch
            .arg(self.k)
            .arg(&n)
            .arg(&sort.order)
            .arg(&sort.keys)
            .arg(x)
            .arg(bar_v)
            .arg(bar_b)
            .arg(grad_u);
        // SAFETY: as above, for g2p_backward_scatter.
        unsafe { launch.launch(launch_for(self.n)) }?;
        Ok(())
    }
}

/// A stopwatch adding each stage's time when timing is on (waiting for
/// the GPU at each lap).
pub(crate) struct Laps<'a, S> {
    stream: &'a CudaStream,
    totals: Option<&'a mut S>,
    clock: Instant,
}

impl<'a, S> Laps<'a, S> {
    pub(crate) fn new(stream: &'a CudaStream, totals: Option<&'a mut S>) -> Self {
        if totals.is_some() {
            // Earlier work is not this substep's.
            let _ = stream.synchronize();
        }
        Self {
            stream,
            totals,
            clock: Instant::now(),
        }
    }

    pub(crate) fn lap(&mut self, stage: fn(&mut S) -> &mut f64) -> Result<(), CudaError> {
        if let Some(totals) = self.totals.as_deref_mut() {
            self.stream.synchronize()?;
            let now = Instant::now();
            *stage(totals) += (now - self.clock).as_secs_f64();
            self.clock = now;
        }
        Ok(())
    }
}
