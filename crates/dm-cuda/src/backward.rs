//! The adjoint of the substep on the device: each substep's forward grids
//! recomputed from its input state, then the backward twins of G2P, the
//! grid update and P2G with the stress (`kernels/*_backward.cu`).

use crate::error::CudaError;
use crate::launch::{Laps, Launcher, ParticleBuffers, launch_for};
use crate::world::{CudaWorld, DeviceReal, flat, unflat};
use cudarc::driver::{CudaSlice, CudaStream, PushKernelArg};
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::real::{Mat3, Vec3};
use dm_mpm::state::Particles;
use dm_mpm::substep::SubstepGrads;
use std::sync::Arc;

/// A state (or its adjoint) sent to the device; an all-zero array (a
/// loss on positions alone leaves v, F and C's adjoints zero) is cleared
/// there instead of copied.
fn upload<T: DeviceReal>(
    stream: &Arc<CudaStream>,
    x: &[Vec3<T>],
    v: &[Vec3<T>],
    f: &[Mat3<T>],
    c: &[Mat3<T>],
) -> Result<ParticleBuffers<T>, CudaError> {
    fn send<T: DeviceReal, const R: usize, const C: usize>(
        stream: &Arc<CudaStream>,
        values: &[nalgebra::SMatrix<T, R, C>],
    ) -> Result<CudaSlice<T>, CudaError> {
        if values.iter().all(|m| m.iter().all(|c| *c == T::zero())) {
            return Ok(stream.alloc_zeros(R * C * values.len())?);
        }
        Ok(stream.clone_htod(&flat(values))?)
    }
    Ok(ParticleBuffers {
        x: send(stream, x)?,
        v: send(stream, v)?,
        f: send(stream, f)?,
        c: send(stream, c)?,
    })
}

/// An adjoint (slot order) sent to the device.
pub(crate) fn upload_grads<T: DeviceReal>(
    stream: &Arc<CudaStream>,
    grad: &ParticleGrads<T>,
) -> Result<ParticleBuffers<T>, CudaError> {
    upload(stream, &grad.x, &grad.v, &grad.f, &grad.c)
}

/// An adjoint brought back from the device.
pub(crate) fn download_grads<T: DeviceReal>(
    stream: &Arc<CudaStream>,
    grad: &ParticleBuffers<T>,
) -> Result<ParticleGrads<T>, CudaError> {
    download(stream, grad)
}

/// An adjoint brought back from the device.
fn download<T: DeviceReal>(
    stream: &Arc<CudaStream>,
    grad: &ParticleBuffers<T>,
) -> Result<ParticleGrads<T>, CudaError> {
    Ok(ParticleGrads {
        x: unflat::<T, 3, 1>(&stream.clone_dtoh(&grad.x)?),
        v: unflat::<T, 3, 1>(&stream.clone_dtoh(&grad.v)?),
        f: unflat::<T, 3, 3>(&stream.clone_dtoh(&grad.f)?),
        c: unflat::<T, 3, 3>(&stream.clone_dtoh(&grad.c)?),
    })
}

/// The adjoint's buffers: the grids, what G2P's adjoint scatters, and the
/// parameters' adjoints summed over the substeps run backward.
#[derive(Debug)]
pub(crate) struct AdjointBuffers<T> {
    grid_pre: CudaSlice<T>,
    grad_u: CudaSlice<T>,
    grad_pre: CudaSlice<T>,
    bar_v: CudaSlice<T>,
    bar_b: CudaSlice<T>,
    /// Adjoint of the state entering the substep being run backward.
    pub(crate) grad_in: ParticleBuffers<T>,
    mu: CudaSlice<T>,
    lambda: CudaSlice<T>,
    weights: CudaSlice<T>,
    /// Adjoint of the substep's actuator acceleration.
    pub(crate) accel: CudaSlice<T>,
    effects: CudaSlice<T>,
    mass: CudaSlice<T>,
    damping: CudaSlice<T>,
    /// Gravity xyz and floor friction.
    params: CudaSlice<T>,
}

impl<T: DeviceReal> AdjointBuffers<T> {
    fn new(stream: &Arc<CudaStream>, n: usize, res: usize) -> Result<Self, CudaError> {
        let nodes = 4 * res * res * res;
        Ok(Self {
            grid_pre: stream.alloc_zeros(nodes)?,
            grad_u: stream.alloc_zeros(nodes)?,
            grad_pre: stream.alloc_zeros(nodes)?,
            bar_v: stream.alloc_zeros(3 * n)?,
            bar_b: stream.alloc_zeros(9 * n)?,
            grad_in: ParticleBuffers::zeros(stream, n)?,
            mu: stream.alloc_zeros(n)?,
            lambda: stream.alloc_zeros(n)?,
            weights: stream.alloc_zeros(3 * n)?,
            accel: stream.alloc_zeros(3 * n)?,
            effects: stream.alloc_zeros(2 * n)?,
            mass: stream.alloc_zeros(n)?,
            damping: stream.alloc_zeros(n)?,
            params: stream.alloc_zeros(4)?,
        })
    }

    /// The parameters' sums brought back from the device.
    pub(crate) fn download_sums(
        &self,
        stream: &Arc<CudaStream>,
    ) -> Result<ParameterSums<T>, CudaError> {
        let params = stream.clone_dtoh(&self.params)?;
        let effects = stream.clone_dtoh(&self.effects)?;
        let weights = stream.clone_dtoh(&self.weights)?;
        let total = |values: Vec<T>| values.iter().map(|v| v.to_f64()).sum::<f64>();
        Ok(ParameterSums {
            mu: stream.clone_dtoh(&self.mu)?,
            lambda: stream.clone_dtoh(&self.lambda)?,
            weights: weights
                .chunks_exact(3)
                .map(|w| [w[0], w[1], w[2]])
                .collect(),
            mass: stream.clone_dtoh(&self.mass)?,
            drag: [0, 1].map(|e| effects.iter().skip(e).step_by(2).map(|v| v.to_f64()).sum()),
            gravity: [0, 1, 2].map(|a| params[a].to_f64()),
            friction: params[3].to_f64(),
            damping: total(stream.clone_dtoh(&self.damping)?),
        })
    }

    /// Zeroes the parameters' sums (the start of a window).
    pub(crate) fn clear_sums(&mut self, stream: &Arc<CudaStream>) -> Result<(), CudaError> {
        stream.memset_zeros(&mut self.mu)?;
        stream.memset_zeros(&mut self.lambda)?;
        stream.memset_zeros(&mut self.weights)?;
        stream.memset_zeros(&mut self.effects)?;
        stream.memset_zeros(&mut self.mass)?;
        stream.memset_zeros(&mut self.damping)?;
        stream.memset_zeros(&mut self.params)?;
        Ok(())
    }
}

/// The parameters' adjoints summed over the substeps run backward (slot
/// order; the per-particle drag and damping shares summed).
#[derive(Clone, Debug)]
pub(crate) struct ParameterSums<T> {
    pub mu: Vec<T>,
    pub lambda: Vec<T>,
    pub weights: Vec<[T; 3]>,
    pub mass: Vec<T>,
    pub drag: [f64; 2],
    pub gravity: [f64; 3],
    pub friction: f64,
    pub damping: f64,
}

/// Seconds per stage of the adjoint (each stage waited for).
#[derive(Clone, Copy, Debug, Default)]
pub struct AdjointSeconds {
    /// The substep's forward grids recomputed: sort, P2G, grid update.
    pub recompute: f64,
    /// G2P's adjoint, pass 1 (per particle).
    pub g2p_gather: f64,
    /// G2P's adjoint, pass 2 (the scatter of ū).
    pub g2p_scatter: f64,
    pub grid_update: f64,
    /// P2G's and the stress's adjoint.
    pub p2g: f64,
}

/// The states entering each recorded substep, on the device.
#[derive(Debug)]
pub struct DeviceTape<T> {
    states: Vec<ParticleBuffers<T>>,
}

impl<T> DeviceTape<T> {
    /// Substeps recorded.
    pub fn len(&self) -> usize {
        self.states.len()
    }

    pub fn is_empty(&self) -> bool {
        self.states.is_empty()
    }
}

/// Adjoints of a window of free substeps with respect to the per-particle
/// Lamé parameters and, when asked for, the state that entered it (slot
/// order).
#[derive(Clone, Debug)]
pub struct WindowGrads<T> {
    pub state: Option<ParticleGrads<T>>,
    pub mu: Vec<T>,
    pub lambda: Vec<T>,
}

impl<T: DeviceReal> CudaWorld<T> {
    /// Runs `body` with the adjoint's buffers, their sums cleared; the
    /// buffers are kept for the next backward pass whatever `body` returns.
    pub(crate) fn with_adjoint<R>(
        &mut self,
        body: impl FnOnce(&mut Self, &mut AdjointBuffers<T>) -> Result<R, CudaError>,
    ) -> Result<R, CudaError> {
        let stream = self.device().stream().clone();
        let mut buffers = self.take_adjoint_buffers()?;
        let out = buffers
            .clear_sums(&stream)
            .and_then(|()| body(self, &mut buffers));
        self.adjoint = Some(buffers);
        out
    }

    fn take_adjoint_buffers(&mut self) -> Result<AdjointBuffers<T>, CudaError> {
        match self.adjoint.take() {
            Some(buffers) => Ok(buffers),
            None => AdjointBuffers::new(
                self.device().stream(),
                self.particle_count(),
                self.config().grid_res,
            ),
        }
    }

    /// Adjoint of one substep at the state `before` (slot order, as the
    /// world stores it) with the actuator accelerations `external_accel`,
    /// given the adjoint of the state after it: the device's
    /// [`dm_mpm::substep::substep_backward`].
    pub fn substep_backward(
        &mut self,
        before: &Particles<T>,
        external_accel: Option<&[Vec3<T>]>,
        grad_after: &ParticleGrads<T>,
    ) -> Result<SubstepGrads<T>, CudaError> {
        let stream = self.device().stream().clone();
        let n = self.particle_count();
        let state = upload(&stream, &before.x, &before.v, &before.f, &before.c)?;
        let mut grad = upload(
            &stream,
            &grad_after.x,
            &grad_after.v,
            &grad_after.f,
            &grad_after.c,
        )?;
        let accel = match external_accel {
            Some(a) => Some(stream.clone_htod(&flat(a))?),
            None => None,
        };
        self.with_adjoint(|world, buffers| {
            world.run_substep_backward(&state, accel.as_ref(), &grad, buffers)?;
            std::mem::swap(&mut grad, &mut buffers.grad_in);
            let state = download(&stream, &grad)?;
            let params = stream.clone_dtoh(&buffers.params)?;
            let sum = |values: Vec<T>| values.into_iter().fold(T::zero(), |a, b| a + b);
            let weights = stream.clone_dtoh(&buffers.weights)?;
            let effects = stream.clone_dtoh(&buffers.effects)?;
            Ok(SubstepGrads {
                state,
                mu: stream.clone_dtoh(&buffers.mu)?,
                lambda: stream.clone_dtoh(&buffers.lambda)?,
                weights: weights
                    .chunks_exact(3)
                    .map(|w| [w[0], w[1], w[2]])
                    .collect(),
                external_accel: if accel.is_some() {
                    unflat::<T, 3, 1>(&stream.clone_dtoh(&buffers.accel)?)
                } else {
                    vec![Vec3::zeros(); n]
                },
                effects: effects.chunks_exact(2).map(|e| [e[0], e[1]]).collect(),
                viscosity: T::zero(),
                gravity: Vec3::new(params[0], params[1], params[2]),
                friction: params[3],
                force_field: Default::default(),
                damping_factor: sum(stream.clone_dtoh(&buffers.damping)?),
                mass: stream.clone_dtoh(&buffers.mass)?,
            })
        })
    }

    /// Runs `count` free substeps (no anchors), recording the state
    /// entering each on the device.
    pub fn taped_substeps(&mut self, count: usize) -> Result<DeviceTape<T>, CudaError> {
        let stream = self.device().stream().clone();
        let mut states = Vec::with_capacity(count);
        for _ in 0..count {
            states.push(self.particles.duplicate(&stream)?);
            self.substeps_unchecked(1)?;
        }
        self.finish()?;
        Ok(DeviceTape { states })
    }

    /// Adjoint of the substeps recorded in `tape`, given the adjoint of
    /// the state after the last (slot order); the state's adjoint comes
    /// back from the device only `with_state`.
    pub fn backward_tape(
        &mut self,
        tape: &DeviceTape<T>,
        grad_after: &ParticleGrads<T>,
        with_state: bool,
    ) -> Result<WindowGrads<T>, CudaError> {
        let stream = self.device().stream().clone();
        ParticleBuffers::check_taped_on(&tape.states, &stream)?;
        let mut grad = upload(
            &stream,
            &grad_after.x,
            &grad_after.v,
            &grad_after.f,
            &grad_after.c,
        )?;
        self.with_adjoint(|world, buffers| {
            for state in tape.states.iter().rev() {
                world.run_substep_backward(state, None, &grad, buffers)?;
                std::mem::swap(&mut grad, &mut buffers.grad_in);
            }
            Ok(WindowGrads {
                state: if with_state {
                    Some(download(&stream, &grad)?)
                } else {
                    None
                },
                mu: stream.clone_dtoh(&buffers.mu)?,
                lambda: stream.clone_dtoh(&buffers.lambda)?,
            })
        })
    }

    /// Launches the adjoint of one substep entered at `state`: writes the
    /// adjoint of `state` into `buffers.grad_in` given `grad_after`, and
    /// adds the parameters' adjoints to the sums.
    pub(crate) fn run_substep_backward(
        &mut self,
        state: &ParticleBuffers<T>,
        accel: Option<&CudaSlice<T>>,
        grad_after: &ParticleBuffers<T>,
        b: &mut AdjointBuffers<T>,
    ) -> Result<(), CudaError> {
        let stream = self.device().stream().clone();
        let k = self.kernel_consts();
        let n = self.particle_count();
        let n_i32 = n as i32;
        let res = self.config().grid_res;
        let kernels = self.kernels().clone();
        let launcher = Launcher {
            stream: &stream,
            kernels: &kernels,
            k: &k,
            n,
            res,
        };
        let mut laps = Laps::new(&stream, self.adjoint_seconds.as_mut());
        // The forward grids of this substep, recomputed.
        launcher.sort(&state.x, &mut self.sort)?;
        launcher.p2g(&self.sort, state, &self.material, accel, &mut b.grid_pre)?;
        stream.memcpy_dtod(&b.grid_pre, &mut self.grid)?;
        launcher.grid_update(&mut self.grid)?;
        laps.lap(|s| &mut s.recompute)?;
        let per_particle = launch_for(n);
        let mut launch = stream.launch_builder(&kernels.g2p_backward_gather);
        launch
            .arg(&k)
            .arg(&n_i32)
            .arg(&self.grid)
            .arg(&state.x)
            .arg(&state.f)
            .arg(&grad_after.x)
            .arg(&grad_after.v)
            .arg(&grad_after.f)
            .arg(&grad_after.c)
            .arg(&mut b.grad_in.x)
            .arg(&mut b.grad_in.f)
            .arg(&mut b.bar_v)
            .arg(&mut b.bar_b)
            .arg(&mut b.damping);
        // SAFETY: the arguments match g2p_backward_gather's signature; every
        // per-particle buffer holds n entries, the grid res³ nodes.
        unsafe { launch.launch(per_particle) }?;
        laps.lap(|s| &mut s.g2p_gather)?;
        launcher.scatter_velocity_adjoint(
            &self.sort,
            &state.x,
            &b.bar_v,
            &b.bar_b,
            &mut b.grad_u,
        )?;
        laps.lap(|s| &mut s.g2p_scatter)?;
        let mut launch = stream.launch_builder(&kernels.grid_update_backward);
        launch
            .arg(&k)
            .arg(&b.grid_pre)
            .arg(&b.grad_u)
            .arg(&mut b.grad_pre)
            .arg(&mut b.params);
        // SAFETY: as above, one thread per node.
        unsafe { launch.launch(launch_for(res * res * res)) }?;
        laps.lap(|s| &mut s.grid_update)?;
        let has_accel = accel.is_some() as i32;
        // Never read without an acceleration.
        let accel = accel.unwrap_or(&state.x);
        let m = &self.material;
        let mut launch = stream.launch_builder(&kernels.p2g_backward);
        launch
            .arg(&k)
            .arg(&n_i32)
            .arg(&state.x)
            .arg(&state.v)
            .arg(&state.f)
            .arg(&state.c)
            .arg(&m.mass)
            .arg(&m.volume)
            .arg(&m.mu)
            .arg(&m.lambda)
            .arg(&m.weights)
            .arg(&has_accel)
            .arg(accel)
            .arg(&b.grad_pre)
            .arg(&mut b.grad_in.x)
            .arg(&mut b.grad_in.v)
            .arg(&mut b.grad_in.f)
            .arg(&mut b.grad_in.c)
            .arg(&mut b.mu)
            .arg(&mut b.lambda)
            .arg(&mut b.weights)
            .arg(&mut b.accel)
            .arg(&mut b.effects)
            .arg(&mut b.mass);
        // SAFETY: as above, for p2g_backward.
        unsafe { launch.launch(per_particle) }?;
        laps.lap(|s| &mut s.p2g)?;
        Ok(())
    }
}
