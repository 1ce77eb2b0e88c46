//! The MPM world with its particle state on a GPU.

use crate::backward::{AdjointBuffers, AdjointSeconds};
use crate::consts::KernelConsts;
use crate::device::{CudaDevice, Kernels};
use crate::error::CudaError;
use crate::frame::DeviceFrameTape;
use crate::kernels::Precision;
use crate::launch::{Laps, Launcher, MaterialBuffers, ParticleBuffers, SortBuffers, launch_for};
use cudarc::driver::sys::{self, CUgraphInstantiate_flags, CUresult, CUstreamCaptureMode};
use cudarc::driver::{
    CudaSlice, CudaStream, DeviceRepr, DriverError, PushKernelArg, ValidAsZeroBits, result,
};
use dm_mpm::real::Vec3;
use dm_mpm::state::Particles;
use dm_mpm::substep::StageSeconds;
use dm_mpm::{ActuatorMode, Real, SimError, World};
use std::ops::Range;
use std::sync::Arc;

/// A float type the kernels are compiled for.
pub trait DeviceReal: Real + DeviceRepr + ValidAsZeroBits {
    const PRECISION: Precision;
}
impl DeviceReal for f32 {
    const PRECISION: Precision = Precision::F32;
}
impl DeviceReal for f64 {
    const PRECISION: Precision = Precision::F64;
}

/// No failure recorded (the kernels keep the lowest failing key).
const NO_FAILURE: u64 = u64::MAX;
/// The failure key's bit telling a non-finite position or velocity from
/// a collapsed F.
const NOT_FINITE_BIT: u64 = 1 << 31;

/// Flattens vectors or matrices into their scalars (nalgebra's
/// column-major layout for matrices, which the kernels read).
pub(crate) fn flat<T: Real, const R: usize, const C: usize>(
    values: &[nalgebra::SMatrix<T, R, C>],
) -> Vec<T> {
    values.iter().flat_map(|m| m.iter().copied()).collect()
}

pub(crate) fn unflat<T: Real, const R: usize, const C: usize>(
    scalars: &[T],
) -> Vec<nalgebra::SMatrix<T, R, C>> {
    scalars
        .chunks_exact(R * C)
        .map(nalgebra::SMatrix::<T, R, C>::from_column_slice)
        .collect()
}

/// The actuator couplings and the anchors of the current frame.
#[derive(Debug)]
pub(crate) struct CouplingBuffers<T> {
    pub row_start: CudaSlice<u32>,
    pub anchor: CudaSlice<u32>,
    pub rest_offset: CudaSlice<T>,
    /// Anchor positions at the start of each substep of the frame, then
    /// at its end (rigid mode), and their velocities.
    anchor_x: CudaSlice<T>,
    anchor_end: CudaSlice<T>,
    anchor_v: CudaSlice<T>,
}

/// An MPM world advanced on a GPU: [`World`]'s frames and substeps with
/// the state kept on the device.
#[derive(Debug)]
pub struct CudaWorld<T: DeviceReal> {
    host: World<T>,
    device: Arc<CudaDevice>,
    kernels: Kernels,
    pub(crate) particles: ParticleBuffers<T>,
    pub(crate) material: MaterialBuffers<T>,
    pub(crate) sort: SortBuffers,
    accel: CudaSlice<T>,
    pub(crate) grid: CudaSlice<T>,
    couplings: CouplingBuffers<T>,
    failure: CudaSlice<u64>,
    /// Couplings on the device (the host's count when uploaded).
    couplings_on_device: usize,
    /// Whether the host world's particle state lags the device's.
    host_stale: bool,
    /// Seconds per stage, when timing is on (each launch then waits for
    /// the GPU, so the substep runs slower than untimed).
    stage_seconds: Option<StageSeconds>,
    /// The same for the adjoint's stages.
    pub(crate) adjoint_seconds: Option<AdjointSeconds>,
    /// The adjoint's buffers, once a backward pass has run.
    pub(crate) adjoint: Option<AdjointBuffers<T>>,
    /// Frames' untaped substeps as CUDA graphs, the latest last (at most
    /// [`GRAPHS_KEPT`]: a fit alternates taped and untaped rollouts).
    substep_graphs: Vec<SubstepGraph<T>>,
    /// Graphs captured since construction.
    graph_captures: usize,
}

/// Graphs a world keeps.
const GRAPHS_KEPT: usize = 2;

/// Substeps captured as a CUDA graph and what the capture baked in: the
/// constants passed by value, the substep indices and the stride of the
/// anchors. The buffers it reads keep their addresses; a buffer that is
/// reallocated drops the graphs.
#[derive(Debug)]
struct SubstepGraph<T> {
    consts: KernelConsts<T>,
    substeps: Range<usize>,
    anchor_stride: Option<usize>,
    graph: OwnedGraph,
}

/// A captured graph and its executable, owned by one world.
struct OwnedGraph {
    graph: sys::CUgraph,
    exec: sys::CUgraphExec,
    stream: Arc<CudaStream>,
}

// SAFETY: the graph is reached only through `&mut CudaWorld`, so calls on
// it are serialised, which is all the driver asks of a graph used from
// several threads; no `&self` method of the world touches it.
unsafe impl Send for OwnedGraph {}
unsafe impl Sync for OwnedGraph {}

impl OwnedGraph {
    /// Instantiates `graph`, which it then owns (destroyed on failure).
    fn instantiate(graph: sys::CUgraph, stream: Arc<CudaStream>) -> Result<Self, DriverError> {
        // SAFETY: `graph` is a live graph just captured and owned here.
        match unsafe { result::graph::instantiate(graph, CUgraphInstantiate_flags(0)) } {
            Ok(exec) => Ok(Self {
                graph,
                exec,
                stream,
            }),
            Err(error) => {
                // SAFETY: as above; nothing else holds it.
                let _ = unsafe { result::graph::destroy(graph) };
                Err(error)
            }
        }
    }

    fn launch(&self) -> Result<(), CudaError> {
        self.stream.context().bind_to_thread()?;
        // SAFETY: the executable is alive and its nodes read buffers of the
        // world that owns it, at the addresses they had when captured.
        unsafe { result::graph::launch(self.exec, self.stream.cu_stream()) }?;
        Ok(())
    }
}

impl Drop for OwnedGraph {
    fn drop(&mut self) {
        // SAFETY: both handles are owned here and destroyed once; an
        // executable still running is freed by the driver when it ends.
        unsafe {
            let _ = result::graph::exec_destroy(self.exec);
            let _ = result::graph::destroy(self.graph);
        }
    }
}

impl std::fmt::Debug for OwnedGraph {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("CudaGraph")
    }
}

/// An open capture on a stream, ended when dropped: an error or a panic
/// while capturing must not leave the stream capturing.
struct Capture<'a> {
    stream: &'a CudaStream,
    open: bool,
}

impl<'a> Capture<'a> {
    /// Starts capturing `stream`'s work from this thread (thread-local
    /// mode: other threads' worlds go on meanwhile).
    fn begin(stream: &'a CudaStream) -> Result<Self, DriverError> {
        stream.context().bind_to_thread()?;
        let mode = CUstreamCaptureMode::CU_STREAM_CAPTURE_MODE_THREAD_LOCAL;
        // SAFETY: the stream is alive and this thread's context is its own.
        unsafe { result::stream::begin_capture(stream.cu_stream(), mode) }?;
        Ok(Self { stream, open: true })
    }

    /// Ends the capture and returns the graph. Calls the driver directly:
    /// cudarc's `end_capture` first reports a pending error of the
    /// context and would then leave the capture open.
    fn end(mut self) -> Result<sys::CUgraph, DriverError> {
        self.open = false;
        // SAFETY: the stream is capturing, begun on this thread.
        let graph = unsafe { result::stream::end_capture(self.stream.cu_stream()) }?;
        if graph.is_null() {
            return Err(DriverError(CUresult::CUDA_ERROR_STREAM_CAPTURE_INVALIDATED));
        }
        Ok(graph)
    }
}

impl Drop for Capture<'_> {
    fn drop(&mut self) {
        if self.open {
            // SAFETY: as in `end`; the partial graph is destroyed unused.
            if let Ok(graph) = unsafe { result::stream::end_capture(self.stream.cu_stream()) }
                && !graph.is_null()
            {
                let _ = unsafe { result::graph::destroy(graph) };
            }
        }
    }
}

/// Whether `error` is the driver refusing a capture or a graph, rather
/// than a failure the substeps' launches would meet anyway.
fn capture_refused(error: &CudaError) -> bool {
    use CUresult::*;
    match error {
        CudaError::Driver(DriverError(code)) => matches!(
            code,
            CUDA_ERROR_STREAM_CAPTURE_UNSUPPORTED
                | CUDA_ERROR_STREAM_CAPTURE_INVALIDATED
                | CUDA_ERROR_STREAM_CAPTURE_MERGE
                | CUDA_ERROR_STREAM_CAPTURE_UNMATCHED
                | CUDA_ERROR_STREAM_CAPTURE_UNJOINED
                | CUDA_ERROR_STREAM_CAPTURE_ISOLATION
                | CUDA_ERROR_STREAM_CAPTURE_IMPLICIT
                | CUDA_ERROR_STREAM_CAPTURE_WRONG_THREAD
                | CUDA_ERROR_NOT_SUPPORTED
                | CUDA_ERROR_ILLEGAL_STATE
        ),
        _ => false,
    }
}

impl<T: DeviceReal> CudaWorld<T> {
    /// Moves `world` onto `device`. Refuses what the kernels do not
    /// have: the implicit viscous solve.
    pub fn new(world: World<T>, device: Arc<CudaDevice>) -> Result<Self, CudaError> {
        check_supported(&world)?;
        let kernels = device.kernels(T::PRECISION)?;
        let stream = device.stream().clone();
        let n = world.particle_count();
        let res = world.config().grid_res;
        let p = world.slot_particles();
        let m = world.slot_material();
        let particles = ParticleBuffers {
            x: stream.clone_htod(&flat(&p.x))?,
            v: stream.clone_htod(&flat(&p.v))?,
            f: stream.clone_htod(&flat(&p.f))?,
            c: stream.clone_htod(&flat(&p.c))?,
        };
        let material = MaterialBuffers {
            mass: stream.clone_htod(&p.mass)?,
            volume: stream.clone_htod(&p.volume)?,
            mu: stream.clone_htod(&m.mu)?,
            lambda: stream.clone_htod(&m.lambda)?,
            weights: stream.clone_htod(&flat_weights(&m.expert_weights))?,
        };
        let couplings = CouplingBuffers {
            row_start: stream.alloc_zeros(n + 1)?,
            anchor: stream.alloc_zeros(1)?,
            rest_offset: stream.alloc_zeros(3)?,
            anchor_x: stream.alloc_zeros(3)?,
            anchor_end: stream.alloc_zeros(3)?,
            anchor_v: stream.alloc_zeros(3)?,
        };
        let mut world = Self {
            host: world,
            kernels,
            particles,
            material,
            sort: SortBuffers::new(&stream, n, res)?,
            accel: stream.alloc_zeros(3 * n)?,
            grid: stream.alloc_zeros(4 * res * res * res)?,
            couplings,
            failure: stream.clone_htod(&[NO_FAILURE])?,
            device,
            couplings_on_device: 0,
            host_stale: false,
            stage_seconds: None,
            adjoint_seconds: None,
            adjoint: None,
            substep_graphs: Vec::new(),
            graph_captures: 0,
        };
        world.upload_couplings()?;
        Ok(world)
    }

    /// Starts (or stops) timing each stage: every launch then waits for
    /// the GPU. P2G's time includes the stress and the clearing of the
    /// grid; the sort's is `schedule`.
    pub fn time_stages(&mut self, on: bool) {
        self.stage_seconds = on.then(StageSeconds::default);
        self.adjoint_seconds = on.then(AdjointSeconds::default);
    }

    /// Seconds per stage of the adjoint since timing was turned on.
    pub fn adjoint_seconds(&self) -> Option<AdjointSeconds> {
        self.adjoint_seconds
    }

    /// Seconds per stage since timing was turned on.
    pub fn stage_seconds(&self) -> Option<StageSeconds> {
        self.stage_seconds
    }

    pub fn device(&self) -> &Arc<CudaDevice> {
        &self.device
    }

    fn stream(&self) -> &Arc<CudaStream> {
        self.device.stream()
    }

    pub fn particle_count(&self) -> usize {
        self.host.particle_count()
    }

    /// The configuration in force.
    pub fn config(&self) -> &dm_mpm::PhysicsConfig {
        self.host.config()
    }

    /// The actuator couplings (kept on the host).
    pub fn actuators(&self) -> &dm_mpm::actuators::Actuators<T> {
        self.host.actuators()
    }

    /// The host world (configuration, material, actuators); its particle
    /// state is brought up to date first.
    pub fn host(&mut self) -> Result<&World<T>, CudaError> {
        self.download_state()?;
        Ok(&self.host)
    }

    /// Changes the world on the host (material, effects, gravity, state…)
    /// and sends the result back to the device.
    pub fn edit<R>(&mut self, change: impl FnOnce(&mut World<T>) -> R) -> Result<R, CudaError> {
        self.download_state()?;
        let result = change(&mut self.host);
        check_supported(&self.host)?;
        self.upload_state()?;
        self.upload_couplings()?;
        Ok(result)
    }

    /// Replaces the particle state (caller's order) on the host and the
    /// device; the device's state is not fetched first.
    pub fn set_state(&mut self, state: &Particles<T>) -> Result<(), CudaError> {
        self.host.set_state(state)?;
        self.host_stale = false;
        self.upload_particles()
    }

    /// Gives the world back to the host, its state up to date.
    pub fn into_host(mut self) -> Result<World<T>, CudaError> {
        self.download_state()?;
        Ok(self.host)
    }

    /// Positions in the caller's particle order, metres.
    pub fn positions(&mut self) -> Result<Vec<[f64; 3]>, CudaError> {
        let x = self.slot_positions()?;
        Ok(self
            .host
            .to_caller_order(&x)
            .iter()
            .map(|p| [p.x.to_f64(), p.y.to_f64(), p.z.to_f64()])
            .collect())
    }

    /// Positions in slot order (the world's internal order), from the
    /// device alone.
    pub fn slot_positions(&mut self) -> Result<Vec<Vec3<T>>, CudaError> {
        Ok(unflat::<T, 3, 1>(
            &self.stream().clone_dtoh(&self.particles.x)?,
        ))
    }

    /// The full particle state in the caller's order.
    pub fn state(&mut self) -> Result<Particles<T>, CudaError> {
        self.download_state()?;
        Ok(self.host.state())
    }

    fn download_state(&mut self) -> Result<(), CudaError> {
        if !self.host_stale {
            return Ok(());
        }
        let stream = self.device.stream().clone();
        let s = &self.particles;
        let (x, v, f, c) = (
            stream.clone_dtoh(&s.x)?,
            stream.clone_dtoh(&s.v)?,
            stream.clone_dtoh(&s.f)?,
            stream.clone_dtoh(&s.c)?,
        );
        let p = self.host.slot_particles_mut();
        p.x = unflat::<T, 3, 1>(&x);
        p.v = unflat::<T, 3, 1>(&v);
        p.f = unflat::<T, 3, 3>(&f);
        p.c = unflat::<T, 3, 3>(&c);
        self.host_stale = false;
        Ok(())
    }

    /// Sends the host's particle state and material.
    fn upload_state(&mut self) -> Result<(), CudaError> {
        self.upload_particles()?;
        let stream = self.device.stream().clone();
        let m = self.host.slot_material();
        let mb = &mut self.material;
        stream.memcpy_htod(&m.mu, &mut mb.mu)?;
        stream.memcpy_htod(&m.lambda, &mut mb.lambda)?;
        stream.memcpy_htod(&flat_weights(&m.expert_weights), &mut mb.weights)?;
        Ok(())
    }

    /// Sends the host's particle state (positions, velocities, F, C, mass
    /// and volume), not the material.
    fn upload_particles(&mut self) -> Result<(), CudaError> {
        let stream = self.device.stream().clone();
        let p = self.host.slot_particles();
        let (s, mb) = (&mut self.particles, &mut self.material);
        stream.memcpy_htod(&flat(&p.x), &mut s.x)?;
        stream.memcpy_htod(&flat(&p.v), &mut s.v)?;
        stream.memcpy_htod(&flat(&p.f), &mut s.f)?;
        stream.memcpy_htod(&flat(&p.c), &mut s.c)?;
        stream.memcpy_htod(&p.mass, &mut mb.mass)?;
        stream.memcpy_htod(&p.volume, &mut mb.volume)?;
        Ok(())
    }

    /// Sends the actuator couplings when the host's have changed (a grasp
    /// only adds couplings, so their count tells).
    fn upload_couplings(&mut self) -> Result<(), CudaError> {
        if self.host.actuators().coupling_count() == self.couplings_on_device {
            return Ok(());
        }
        self.send_couplings()
    }

    /// Sends the host's couplings into the device's buffers, reallocating
    /// (and so dropping the graphs) only a buffer whose length differs;
    /// with no couplings the buffers keep their old, unread contents.
    fn send_couplings(&mut self) -> Result<(), CudaError> {
        let (row_start, anchor, rest) = self.host.actuators().coupling_arrays();
        let stream = self.device.stream().clone();
        let c = &mut self.couplings;
        let mut moved = overwrite(&stream, &mut c.row_start, row_start)?;
        if !anchor.is_empty() {
            moved |= overwrite(&stream, &mut c.anchor, anchor)?;
            moved |= overwrite(&stream, &mut c.rest_offset, &flat(rest))?;
        }
        self.couplings_on_device = anchor.len();
        if moved {
            self.substep_graphs.clear();
        }
        Ok(())
    }

    /// Starts again from `world`, a world of the same particle count and
    /// grid (typically the one this world was made from): its state,
    /// material and couplings are sent into the buffers in place, so the
    /// graphs captured for those buffers replay again (a planner's
    /// rollouts, each from the same start).
    pub fn restart_from(&mut self, world: World<T>) -> Result<(), CudaError> {
        if world.particle_count() != self.particle_count()
            || world.config().grid_res != self.config().grid_res
        {
            return Err(CudaError::Unsupported(format!(
                "restarting a world of {} particles on a {}³ grid from one of {} on a {}³ grid",
                self.particle_count(),
                self.config().grid_res,
                world.particle_count(),
                world.config().grid_res
            )));
        }
        check_supported(&world)?;
        self.host = world;
        self.host_stale = false;
        self.upload_state()?;
        self.send_couplings()
    }

    /// CUDA graphs this world has captured (each capture also instantiates).
    pub fn graph_captures(&self) -> usize {
        self.graph_captures
    }

    pub(crate) fn kernel_consts(&self) -> KernelConsts<T> {
        KernelConsts::new(
            self.host.consts(),
            self.host.is_pure_neo_hookean(),
            &self.host.actuators().config,
            self.couplings_on_device > 0,
        )
    }

    pub(crate) fn kernels(&self) -> &Kernels {
        &self.kernels
    }

    pub(crate) fn coupling_buffers(&self) -> &CouplingBuffers<T> {
        &self.couplings
    }

    /// The host world as it is (its particle state may lag the device's).
    pub(crate) fn host_world(&self) -> &World<T> {
        &self.host
    }

    pub(crate) fn consts(&self) -> &dm_mpm::state::Consts<T> {
        self.host.consts()
    }

    /// Advances one video frame while the anchors move linearly from
    /// `anchors_from` to `anchors_to` (as [`World::step_frame`]).
    pub fn step_frame(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        active: &[bool],
    ) -> Result<(), CudaError> {
        self.advance_frame(anchors_from, anchors_to, active, FrameRun::Whole)
            .map(|_| ())
    }

    /// Like [`CudaWorld::step_frame`], returning the state entering the
    /// frame's substep `at` (as [`World::step_frame_keeping`]).
    pub fn step_frame_keeping(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        active: &[bool],
        at: usize,
    ) -> Result<Particles<T>, CudaError> {
        self.advance_frame(anchors_from, anchors_to, active, FrameRun::Keeping(at))?
            .kept
            .ok_or_else(|| CudaError::Unsupported("a frame kept no state".into()))
    }

    /// Like [`CudaWorld::step_frame`], recording on the device what the
    /// backward pass ([`CudaWorld::backward_frame`]) needs for the last
    /// `window` substeps of the frame.
    pub fn step_frame_taped(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        active: &[bool],
        window: usize,
    ) -> Result<DeviceFrameTape<T>, CudaError> {
        self.taped_frame(anchors_from, anchors_to, active, window, 0)
    }

    /// The last `window` substeps of a frame, taped, from the state
    /// entering them; grasps nothing (as [`World::step_frame_rest_taped`]).
    pub fn step_frame_rest_taped(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        window: usize,
    ) -> Result<DeviceFrameTape<T>, CudaError> {
        let steps = self.host.config().substeps_per_frame;
        let no_grasp = vec![false; anchors_from.len()];
        self.taped_frame(
            anchors_from,
            anchors_to,
            &no_grasp,
            window,
            steps - window.min(steps),
        )
    }

    /// A frame whose last `window` substeps are taped, run from substep
    /// `first` on.
    fn taped_frame(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        active: &[bool],
        window: usize,
        first: usize,
    ) -> Result<DeviceFrameTape<T>, CudaError> {
        let run = FrameRun::Taped { window, first };
        self.advance_frame(anchors_from, anchors_to, active, run)?
            .tape
            .ok_or_else(|| CudaError::Unsupported("a taped frame recorded nothing".into()))
    }

    fn advance_frame(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        active: &[bool],
        run: FrameRun,
    ) -> Result<FrameOutcome<T>, CudaError> {
        let grasp_positions = if self.host.actuators().grasp_pending(active) {
            let x = self.stream().clone_dtoh(&self.particles.x)?;
            Some(unflat::<T, 3, 1>(&x))
        } else {
            None
        };
        let path =
            self.host
                .begin_frame(anchors_from, anchors_to, active, grasp_positions.as_deref())?;
        self.upload_couplings()?;
        let steps = self.host.config().substeps_per_frame;
        let coupled = self.couplings_on_device > 0;
        if coupled {
            let dt = self.host.consts().dt;
            let mut starts = Vec::new();
            let mut ends = Vec::new();
            for s in 0..steps {
                let at = path.at_substep(s);
                ends.extend(at.iter().zip(&path.velocity).flat_map(|(x, v)| {
                    let end: Vec3<T> = x + v * dt;
                    [end.x, end.y, end.z]
                }));
                starts.extend(flat(&at));
            }
            let stream = self.device.stream().clone();
            let c = &mut self.couplings;
            let mut moved = overwrite(&stream, &mut c.anchor_x, &starts)?;
            moved |= overwrite(&stream, &mut c.anchor_end, &ends)?;
            moved |= overwrite(&stream, &mut c.anchor_v, &flat(&path.velocity))?;
            if moved {
                self.substep_graphs.clear();
            }
        }
        let k = self.kernel_consts();
        let anchors = anchors_from.len();
        let anchor_stride = coupled.then_some(anchors * 3);
        let stream = self.device.stream().clone();
        // Untaped substeps run as graphs, in two stretches around the
        // state kept; the taped ones copy the state before each and are
        // launched one by one.
        let (first, taped_from, keep_at) = match run {
            FrameRun::Whole => (0, steps, None),
            FrameRun::Keeping(at) => (0, steps, Some(at.min(steps))),
            FrameRun::Taped { window, first } => (first, steps - window.min(steps), None),
        };
        let split = keep_at.unwrap_or(taped_from);
        self.run_untaped(&k, first..split, anchor_stride)?;
        let kept = match keep_at {
            Some(_) => {
                self.host_stale = true;
                Some(self.state()?)
            }
            None => None,
        };
        self.run_untaped(&k, split..taped_from, anchor_stride)?;
        let taped = matches!(run, FrameRun::Taped { .. });
        let mut states = Vec::new();
        for s in taped_from..steps {
            states.push(self.particles.duplicate(&stream)?);
            self.launch_substep(&k, s, anchor_stride.map(|a| s * a))?;
        }
        self.host_stale = true;
        self.check_failure()?;
        self.host.count_frame();
        if !taped {
            return Ok(FrameOutcome { tape: None, kept });
        }
        let anchors_taped = if coupled {
            Some((
                stream.clone_dtod(&self.couplings.anchor_x)?,
                stream.clone_dtod(&self.couplings.anchor_v)?,
            ))
        } else {
            None
        };
        let tape = DeviceFrameTape {
            states,
            anchors: anchors_taped,
            anchor_count: anchors,
            substeps: steps,
            frame_dt: self.host.config().dt * steps as f64,
        };
        Ok(FrameOutcome {
            tape: Some(tape),
            kept,
        })
    }

    /// Runs `substeps` untaped: as one graph launch where graphs are on,
    /// else launched one by one.
    fn run_untaped(
        &mut self,
        k: &KernelConsts<T>,
        substeps: Range<usize>,
        anchor_stride: Option<usize>,
    ) -> Result<(), CudaError> {
        if self.replay_substeps(k, substeps.clone(), anchor_stride)? {
            return Ok(());
        }
        for s in substeps {
            self.launch_substep(k, s, anchor_stride.map(|a| s * a))?;
        }
        Ok(())
    }

    /// Advances one frame with no anchors.
    pub fn step_frame_free(&mut self) -> Result<(), CudaError> {
        self.step_frame(&[], &[], &[])
    }

    /// Runs `count` substeps with no anchors and no divergence check
    /// until [`CudaWorld::finish`] (for benchmarks: nothing waits on
    /// the GPU in between).
    pub fn substeps_unchecked(&mut self, count: usize) -> Result<(), CudaError> {
        let k = self.kernel_consts();
        for s in 0..count {
            self.launch_substep(&k, s, None)?;
        }
        self.host_stale = true;
        Ok(())
    }

    /// Waits for the GPU and reports a divergence since the last check.
    pub fn finish(&mut self) -> Result<(), CudaError> {
        self.check_failure()
    }

    /// Launches one substep; `anchor_offset` is the offset of this
    /// substep's anchor positions when particles are coupled.
    fn launch_substep(
        &mut self,
        k: &KernelConsts<T>,
        substep: usize,
        anchor_offset: Option<usize>,
    ) -> Result<(), CudaError> {
        let stream = self.device.stream().clone();
        let n = self.particle_count();
        let n_i32 = n as i32;
        let launcher = Launcher {
            stream: &stream,
            kernels: &self.kernels,
            k,
            n,
            res: self.host.config().grid_res,
        };
        let c = &self.couplings;
        let p = &mut self.particles;
        let mut laps = Laps::new(&stream, self.stage_seconds.as_mut());
        if let Some(offset) = anchor_offset {
            let anchor_x = c.anchor_x.slice(offset..);
            launcher.actuator_accel(c, p, &anchor_x, &c.anchor_v, &mut self.accel)?;
            laps.lap(|s| &mut s.actuators)?;
        }
        launcher.sort(&p.x, &mut self.sort)?;
        laps.lap(|s| &mut s.schedule)?;
        let accel = anchor_offset.map(|_| &self.accel);
        launcher.p2g(&self.sort, p, &self.material, accel, &mut self.grid)?;
        laps.lap(|s| &mut s.p2g)?;
        launcher.grid_update(&mut self.grid)?;
        laps.lap(|s| &mut s.grid_update)?;
        launcher.g2p(substep, &self.grid, p, &mut self.failure)?;
        laps.lap(|s| &mut s.g2p)?;
        if let Some(offset) = anchor_offset
            && self.host.actuators().config.mode == ActuatorMode::Rigid
        {
            let anchor_end = c.anchor_end.slice(offset..);
            let mut launch = stream.launch_builder(&self.kernels.enforce_rigid);
            launch
                .arg(&n_i32)
                .arg(&c.row_start)
                .arg(&c.anchor)
                .arg(&c.rest_offset)
                .arg(&anchor_end)
                .arg(&c.anchor_v)
                .arg(&mut p.x)
                .arg(&mut p.v);
            // SAFETY: as above, for enforce_rigid.
            unsafe { launch.launch(launch_for(n)) }?;
            laps.lap(|s| &mut s.actuators)?;
        }
        Ok(())
    }

    /// Runs `substeps` of a frame as one CUDA graph launch, capturing the
    /// graph first where none kept baked in these constants, substeps and
    /// anchors. Returns false, having run nothing, where graphs are off
    /// (also while stages are timed: timing waits between launches) or
    /// the driver refused the capture (graphs are then given up).
    fn replay_substeps(
        &mut self,
        k: &KernelConsts<T>,
        substeps: Range<usize>,
        anchor_stride: Option<usize>,
    ) -> Result<bool, CudaError> {
        if substeps.is_empty() || self.stage_seconds.is_some() || !self.device.graphs_enabled() {
            return Ok(false);
        }
        let kept = self.substep_graphs.iter().position(|g| {
            g.consts.same_bits(k) && g.substeps == substeps && g.anchor_stride == anchor_stride
        });
        let index = match kept {
            Some(index) => index,
            None => match self.capture_substeps(k, substeps.clone(), anchor_stride) {
                Ok(graph) => {
                    if self.substep_graphs.len() == GRAPHS_KEPT {
                        self.substep_graphs.remove(0);
                    }
                    self.substep_graphs.push(SubstepGraph {
                        consts: *k,
                        substeps,
                        anchor_stride,
                        graph,
                    });
                    self.substep_graphs.len() - 1
                }
                Err(error) if capture_refused(&error) => {
                    self.device.give_up_graphs(&error);
                    return Ok(false);
                }
                Err(error) => return Err(error),
            },
        };
        self.substep_graphs[index].graph.launch()?;
        Ok(true)
    }

    /// Records the launches of `substeps` on the world's stream as a graph
    /// (nothing runs); the capture is ended whatever happens.
    fn capture_substeps(
        &mut self,
        k: &KernelConsts<T>,
        substeps: Range<usize>,
        anchor_stride: Option<usize>,
    ) -> Result<OwnedGraph, CudaError> {
        let stream = self.device.stream().clone();
        let capture = Capture::begin(&stream)?;
        for s in substeps {
            self.launch_substep(k, s, anchor_stride.map(|a| s * a))?;
        }
        let graph = capture.end()?;
        self.graph_captures += 1;
        Ok(OwnedGraph::instantiate(graph, stream)?)
    }

    /// Reads the failure key (waiting for the GPU) and turns a recorded
    /// failure into [`SimError::Diverged`].
    fn check_failure(&mut self) -> Result<(), CudaError> {
        let stream = self.device.stream().clone();
        let key = stream.clone_dtoh(&self.failure)?[0];
        if key == NO_FAILURE {
            return Ok(());
        }
        stream.memcpy_htod(&[NO_FAILURE], &mut self.failure)?;
        let slot = (key & (NOT_FINITE_BIT - 1)) as usize;
        let reason = if key & NOT_FINITE_BIT != 0 {
            "position or velocity not finite"
        } else {
            "det F <= 0 or not finite"
        };
        Err(SimError::Diverged {
            frame: self.host.frame(),
            substep: (key >> 32) as usize,
            particle: self.host.id_of_slot().get(slot).copied().unwrap_or(0) as usize,
            reason: reason.into(),
        }
        .into())
    }
}

/// What [`CudaWorld::advance_frame`] recorded besides the frame.
struct FrameOutcome<T> {
    tape: Option<DeviceFrameTape<T>>,
    kept: Option<Particles<T>>,
}

/// What [`CudaWorld::advance_frame`] does besides stepping the frame.
#[derive(Clone, Copy, Debug)]
enum FrameRun {
    Whole,
    /// Keep the state entering this substep.
    Keeping(usize),
    /// Tape the last `window` substeps, running the substeps from `first` on.
    Taped {
        window: usize,
        first: usize,
    },
}

/// Copies `values` into `buffer`, reallocating it where the length
/// differs; returns whether the buffer moved.
fn overwrite<V: DeviceRepr>(
    stream: &Arc<CudaStream>,
    buffer: &mut CudaSlice<V>,
    values: &[V],
) -> Result<bool, CudaError> {
    if buffer.len() == values.len() {
        stream.memcpy_htod(values, buffer)?;
        Ok(false)
    } else {
        *buffer = stream.clone_htod(values)?;
        Ok(true)
    }
}

/// Expert weights as 3 scalars per particle.
fn flat_weights<T: Real>(weights: &[[T; 3]]) -> Vec<T> {
    weights.iter().flatten().copied().collect()
}

/// Refuses worlds using what the kernels do not have.
fn check_supported<T: Real>(world: &World<T>) -> Result<(), CudaError> {
    match unsupported(world) {
        Some(problem) => Err(CudaError::Unsupported(format!(
            "{problem}; use --device cpu"
        ))),
        None => Ok(()),
    }
}

/// What of `world` the kernels do not have, if anything.
pub fn unsupported<T: Real>(world: &World<T>) -> Option<&'static str> {
    if world.config().effects.viscosity != 0.0 {
        return Some("viscosity (the grid's implicit viscous solve runs on the CPU only)");
    }
    if !world.config().effects.force_field.is_zero() {
        return Some("a body force (effects.force_field runs on the CPU only)");
    }
    None
}
