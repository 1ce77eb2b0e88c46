//! A video frame's tape and its adjoint on the device, the twin of
//! `dm_mpm::tape`: the frame's substeps with the actuators, the last
//! `window` of them recorded, and the backward pass through them with
//! the actuators' and the anchors' adjoints.

use crate::error::CudaError;
use crate::launch::{Launcher, ParticleBuffers, launch_for};
use crate::world::{CudaWorld, DeviceReal};
use cudarc::driver::{CudaSlice, PushKernelArg};
use dm_mpm::ActuatorMode;
use dm_mpm::actuators_backward::GainGrads;
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::tape::{EffectGrads, FrameGrads};

/// What a frame's backward pass needs: the states entering its last
/// `window` substeps and, with coupled particles, the anchors of every
/// substep of the frame.
#[derive(Debug)]
pub struct DeviceFrameTape<T> {
    pub(crate) states: Vec<ParticleBuffers<T>>,
    /// Anchor positions at each substep's start (substeps × anchors × 3)
    /// and the anchors' velocities, when particles are coupled.
    pub(crate) anchors: Option<(CudaSlice<T>, CudaSlice<T>)>,
    pub(crate) anchor_count: usize,
    pub(crate) substeps: usize,
    pub(crate) frame_dt: f64,
}

impl<T> DeviceFrameTape<T> {
    /// Substeps recorded (the differentiated window).
    pub fn len(&self) -> usize {
        self.states.len()
    }

    pub fn is_empty(&self) -> bool {
        self.states.is_empty()
    }
}

impl<T: DeviceReal> CudaWorld<T> {
    /// Adjoint of the frame recorded in `tape` (as
    /// [`dm_mpm::World::backward_frame`]), given the adjoint of the state
    /// after it, both in the caller's particle order.
    pub fn backward_frame(
        &mut self,
        tape: &DeviceFrameTape<T>,
        grad_after: &ParticleGrads<T>,
    ) -> Result<FrameGrads<T>, CudaError> {
        let n = self.particle_count();
        if grad_after.x.len() != n {
            return Err(CudaError::Sim(dm_mpm::SimError::InvalidInput(
                "gradient size does not match particles".into(),
            )));
        }
        let stream = self.device().stream().clone();
        ParticleBuffers::check_taped_on(&tape.states, &stream)?;
        let host = self.host_world();
        let slot_grad = ParticleGrads {
            x: host.to_slot_order(&grad_after.x),
            v: host.to_slot_order(&grad_after.v),
            f: host.to_slot_order(&grad_after.f),
            c: host.to_slot_order(&grad_after.c),
        };
        let mut grad = crate::backward::upload_grads(&stream, &slot_grad)?;
        let m = tape.anchor_count;
        let mut gains: CudaSlice<T> = stream.alloc_zeros(2)?;
        let mut anchor_ends: CudaSlice<T> = stream.alloc_zeros((6 * m).max(1))?;
        let mut forward_accel: CudaSlice<T> = stream.alloc_zeros(3 * n)?;
        let k = self.kernel_consts();
        let n_i32 = n as i32;
        let rigid = self.actuators().config.mode == ActuatorMode::Rigid;
        let first = tape.substeps - tape.states.len();
        let frame_dt = T::lit(tape.frame_dt);
        let kernels = self.kernels().clone();
        self.with_adjoint(|world, buffers| {
            for r in (0..tape.states.len()).rev() {
                let state = &tape.states[r];
                let s = first + r;
                let couplings = world.coupling_buffers();
                if let Some((anchor_x, anchor_v)) = &tape.anchors {
                    if rigid {
                        let mut launch = stream.launch_builder(&kernels.zero_coupled);
                        launch
                            .arg(&n_i32)
                            .arg(&couplings.row_start)
                            .arg(&mut grad.x)
                            .arg(&mut grad.v);
                        // SAFETY: the arguments match zero_coupled's signature.
                        unsafe { launch.launch(launch_for(n)) }?;
                    }
                    let at = anchor_x.slice(s * m * 3..);
                    let launcher = Launcher {
                        stream: &stream,
                        kernels: &kernels,
                        k: &k,
                        n,
                        res: world.config().grid_res,
                    };
                    launcher.actuator_accel(couplings, state, &at, anchor_v, &mut forward_accel)?;
                }
                let accel = tape.anchors.as_ref().map(|_| &forward_accel);
                world.run_substep_backward(state, accel, &grad, buffers)?;
                if let (Some((anchor_x, anchor_v)), false) = (&tape.anchors, rigid) {
                    let couplings = world.coupling_buffers();
                    let at = anchor_x.slice(s * m * 3..);
                    let along = T::lit(s as f64 / tape.substeps as f64);
                    let b = &mut *buffers;
                    let mut launch = stream.launch_builder(&kernels.actuator_accel_backward);
                    launch
                        .arg(&k)
                        .arg(&n_i32)
                        .arg(&state.x)
                        .arg(&state.v)
                        .arg(&couplings.row_start)
                        .arg(&couplings.anchor)
                        .arg(&couplings.rest_offset)
                        .arg(&at)
                        .arg(anchor_v)
                        .arg(&b.accel)
                        .arg(&along)
                        .arg(&frame_dt)
                        .arg(&mut b.grad_in.x)
                        .arg(&mut b.grad_in.v)
                        .arg(&mut gains)
                        .arg(&mut anchor_ends);
                    // SAFETY: as above, for actuator_accel_backward.
                    unsafe { launch.launch(launch_for(n)) }?;
                }
                std::mem::swap(&mut grad, &mut buffers.grad_in);
            }
            let sums = buffers.download_sums(&stream)?;
            let state = crate::backward::download_grads(&stream, &grad)?;
            let gains = stream.clone_dtoh(&gains)?;
            let ends = stream.clone_dtoh(&anchor_ends)?;
            let host = world.host_world();
            let (dt, kappa) = (world.consts().dt, world.consts().particle_damping_factor);
            Ok(FrameGrads {
                state: ParticleGrads {
                    x: host.to_caller_order(&state.x),
                    v: host.to_caller_order(&state.v),
                    f: host.to_caller_order(&state.f),
                    c: host.to_caller_order(&state.c),
                },
                mu: host.to_caller_order(&sums.mu),
                lambda: host.to_caller_order(&sums.lambda),
                weights: host.to_caller_order(&sums.weights),
                gains: GainGrads {
                    kp: gains[0].to_f64(),
                    kd: gains[1].to_f64(),
                },
                effects: EffectGrads {
                    air_drag_linear: sums.drag[0],
                    air_drag_quadratic: sums.drag[1],
                    viscosity: 0.0,
                    gravity: sums.gravity,
                    floor_friction: sums.friction,
                    particle_damping: -sums.damping * (dt * kappa).to_f64(),
                    force_field: Default::default(),
                },
                mass: host.to_caller_order(&sums.mass),
                anchors_from: (0..m)
                    .map(|c| [0, 1, 2].map(|a| ends[6 * c + a].to_f64()))
                    .collect(),
                anchors_to: (0..m)
                    .map(|c| [0, 1, 2].map(|a| ends[6 * c + 3 + a].to_f64()))
                    .collect(),
            })
        })
    }
}
