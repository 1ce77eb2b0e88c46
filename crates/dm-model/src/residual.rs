//! The neural residual inside the world model (method.md §5): its
//! weights saved with the model, its per-frame correction after the MPM
//! substeps, and the backward pass through correction and network that the
//! fit chains with the physics adjoint.

use crate::ModelError;
use crate::device::{Device, shared_gpu};
use dm_cuda::CudaResidual;
use dm_mpm::World;
use dm_mpm::correction::CorrectionTape;
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::real::{Real, Vec3};
use dm_residual::features::history_of;
use dm_residual::{
    FrameInputs, NetworkSize, Precision, Residual, ResidualGrads, ResidualKind, ResidualSpec,
};
use serde::{Deserialize, Serialize};

/// Bound on |Δv| (method.md §5: α = 1.0 m/s).
pub const RESIDUAL_ALPHA: f64 = 1.0;

/// A residual network's description and weights, saved in model.json.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResidualState {
    pub spec: ResidualSpec,
    /// All weights in `Residual::parameters` order.
    pub parameters: Vec<f64>,
}

impl ResidualState {
    /// A fresh network of `kind` on the model's grid (its last layer zero:
    /// the untrained residual changes nothing).
    pub fn fresh(
        kind: ResidualKind,
        physics: &dm_mpm::PhysicsConfig,
        size: NetworkSize,
        seed: u64,
    ) -> Result<Option<Self>, ModelError> {
        if kind == ResidualKind::None {
            return Ok(None);
        }
        let spec = ResidualSpec {
            kind,
            size,
            alpha: RESIDUAL_ALPHA,
            grid_origin: physics.domain_origin,
            grid_dx: physics.dx(),
            domain_size: physics.domain_size,
            seed,
        };
        let network = Residual::new(spec.clone(), dm_residual::Precision::F32)?;
        Ok(Some(Self {
            spec,
            parameters: network.parameters()?,
        }))
    }

    /// The network with these weights, in f32 (rollouts, training) or f64
    /// (gradient checks).
    pub fn network(&self, precision: dm_residual::Precision) -> Result<Residual, ModelError> {
        let mut network = Residual::new(self.spec.clone(), precision)?;
        network.set_parameters(&self.parameters)?;
        Ok(network)
    }
}

/// A residual network on the device its world runs on: the CPU, or the
/// GPU (dm-cuda's kernels; inputs and results still pass through the host).
#[derive(Debug)]
pub enum ResidualNetwork {
    Cpu(Residual),
    Cuda(Box<CudaResidual<f32>>),
    CudaF64(Box<CudaResidual<f64>>),
}

impl ResidualNetwork {
    /// `network` on `device`, in its own precision.
    pub fn new(network: Residual, device: Device) -> Result<Self, ModelError> {
        Ok(match (device, network.precision()) {
            (Device::Cpu, _) => Self::Cpu(network),
            (Device::Cuda, Precision::F32) => {
                Self::Cuda(Box::new(CudaResidual::new(shared_gpu()?, &network)?))
            }
            (Device::Cuda, Precision::F64) => {
                Self::CudaF64(Box::new(CudaResidual::new(shared_gpu()?, &network)?))
            }
        })
    }

    /// Δv for one frame (see `Residual::predict`).
    pub fn predict(&self, inputs: &FrameInputs) -> Result<Vec<[f64; 3]>, ModelError> {
        Ok(match self {
            Self::Cpu(network) => network.predict(inputs)?,
            Self::Cuda(network) => network.predict(inputs)?,
            Self::CudaF64(network) => network.predict(inputs)?,
        })
    }

    /// The vector-Jacobian product (see `Residual::vjp`).
    pub fn vjp(
        &self,
        inputs: &FrameInputs,
        grad_dv: &[[f64; 3]],
    ) -> Result<ResidualGrads, ModelError> {
        Ok(match self {
            Self::Cpu(network) => network.vjp(inputs, grad_dv)?,
            Self::Cuda(network) => network.vjp(inputs, grad_dv)?,
            Self::CudaF64(network) => network.vjp(inputs, grad_dv)?,
        })
    }

    pub fn parameter_count(&self) -> usize {
        match self {
            Self::Cpu(network) => network.parameter_count(),
            Self::Cuda(network) => network.parameter_count(),
            Self::CudaF64(network) => network.parameter_count(),
        }
    }
}

/// Positions and velocities at the start of a frame (caller's order).
pub type FrameStart = (Vec<[f64; 3]>, Vec<[f64; 3]>);

/// The start of the frame the world is about to step.
pub fn frame_start<T: Real>(world: &World<T>) -> FrameStart {
    (world.positions(), world.velocities())
}

/// The residual's inputs after the substeps of frame `t`; `starts[0..=t]`
/// are the frame starts so far.
pub fn frame_inputs<T: Real>(world: &World<T>, starts: &[FrameStart], t: usize) -> FrameInputs {
    FrameInputs {
        x_tilde: world.positions(),
        v_tilde: world.velocities(),
        x_start: starts[t].0.clone(),
        history: history_of(starts, t, |s| s.clone()),
    }
}

/// Predicts Δv for the frame just stepped and applies it.
pub fn apply_residual<T: Real>(
    world: &mut World<T>,
    network: &ResidualNetwork,
    starts: &[FrameStart],
    t: usize,
) -> Result<(Vec<[f64; 3]>, CorrectionTape), ModelError> {
    let dv = network.predict(&frame_inputs(world, starts, t))?;
    let tape = world.apply_velocity_correction(&dv)?;
    Ok((dv, tape))
}

/// What [`residual_backward`] hands back besides the updated adjoint.
#[derive(Clone, Debug, PartialEq)]
pub struct ResidualFrameGrads {
    /// Gradient of the network's weights.
    pub parameters: Vec<f64>,
    /// Adjoint of the frame's start positions (through x̃ − x_t).
    pub x_start: Vec<[f64; 3]>,
    /// Adjoints (x, v) of the history frames' starts, newest first (the
    /// fit treats the history as data and leaves them).
    pub history: Vec<dm_residual::features::ParticleState>,
}

/// Backward through one frame's correction and network. `carried` enters as
/// the adjoint of the corrected state and leaves as that of the state after
/// the substeps (x̃, ṽ; F and C pass through). `regulariser` is the
/// weight of Σ_p |Δv_p|² in the loss (its gradient is added to Δv's).
pub fn residual_backward<T: Real>(
    network: &ResidualNetwork,
    inputs: &FrameInputs,
    dv: &[[f64; 3]],
    tape: &CorrectionTape,
    carried: &mut ParticleGrads<T>,
    regulariser: f64,
) -> Result<ResidualFrameGrads, ModelError> {
    let grad_dv: Vec<[f64; 3]> = tape
        .backward(carried)
        .iter()
        .zip(dv)
        .map(|(g, d)| [0, 1, 2].map(|a| g[a].to_f64() + 2.0 * regulariser * d[a]))
        .collect();
    let grads = network.vjp(inputs, &grad_dv)?;
    let to_t = |g: &[f64; 3]| Vec3::new(T::lit(g[0]), T::lit(g[1]), T::lit(g[2]));
    for (c, g) in carried.x.iter_mut().zip(&grads.x_tilde) {
        *c += to_t(g);
    }
    for (c, g) in carried.v.iter_mut().zip(&grads.v_tilde) {
        *c += to_t(g);
    }
    Ok(ResidualFrameGrads {
        parameters: grads.parameters,
        x_start: grads.x_start,
        history: grads.history,
    })
}
