//! Where a world model's MPM world runs: on the CPU (the default) or on
//! an NVIDIA GPU through `dm-cuda`.

use crate::ModelError;
pub use dm_cuda::DeviceReal;
use dm_cuda::{CudaDevice, CudaWorld, DeviceFrameTape};
use dm_mpm::actuators::Actuators;
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::state::Particles;
use dm_mpm::tape::{FrameGrads, FrameTape};
use dm_mpm::{PhysicsConfig, World};
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex};

/// The device the MPM world runs on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Device {
    /// The CPU, on all cores.
    #[default]
    Cpu,
    /// The first NVIDIA GPU, through CUDA (driver and NVRTC loaded at run time).
    Cuda,
}

impl Device {
    /// `self`, or the CPU where `world` needs what only the CPU has (the
    /// implicit viscous solve, a body force): for tools that step many
    /// variants of a model and keep the GPU for those it can run.
    pub fn for_world<T: dm_mpm::Real>(self, world: &World<T>) -> Device {
        match self {
            Device::Cuda if dm_cuda::unsupported(world).is_some() => Device::Cpu,
            device => device,
        }
    }

    /// [`Device::for_world`] for `model`'s world.
    pub fn for_model(self, model: &crate::WorldModel) -> Result<Device, ModelError> {
        Ok(match self {
            Device::Cpu => Device::Cpu,
            Device::Cuda => self.for_world(&model.world()?),
        })
    }
}

impl std::fmt::Display for Device {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Device::Cpu => "cpu",
            Device::Cuda => "cuda",
        })
    }
}

/// The process's GPU: opened, and its kernels compiled, once.
pub(crate) fn shared_gpu() -> Result<Arc<CudaDevice>, ModelError> {
    static GPU: Mutex<Option<Arc<CudaDevice>>> = Mutex::new(None);
    let mut gpu = GPU
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    if let Some(device) = gpu.as_ref() {
        return Ok(device.clone());
    }
    let device = CudaDevice::open(0)?;
    *gpu = Some(device.clone());
    Ok(device)
}

/// What a frame's backward pass needs, on the world's device.
#[derive(Debug)]
pub enum DeviceTape<T: DeviceReal = f32> {
    Cpu(FrameTape<T>),
    Cuda(DeviceFrameTape<T>),
}

impl<T: DeviceReal> DeviceTape<T> {
    /// Substeps recorded (the differentiated window).
    pub fn len(&self) -> usize {
        match self {
            DeviceTape::Cpu(tape) => tape.len(),
            DeviceTape::Cuda(tape) => tape.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// An MPM world on the CPU or on the GPU, stepped the same way.
#[derive(Debug)]
pub enum DeviceWorld<T: DeviceReal = f32> {
    Cpu(Box<World<T>>),
    Cuda(Box<CudaWorld<T>>),
}

impl DeviceWorld<f32> {
    /// `model`'s world at its first frame on `device`.
    pub fn of_model(model: &crate::WorldModel, device: Device) -> Result<Self, ModelError> {
        Self::new(model.world()?, device)
    }
}

impl<T: DeviceReal> DeviceWorld<T> {
    /// `world` moved to `device`; on the GPU with a stream of its own, so
    /// that worlds stepped from several threads (the gain search's
    /// candidates, MPPI's samples, the probes' moves) run there at once.
    pub fn new(world: World<T>, device: Device) -> Result<Self, ModelError> {
        Ok(match device {
            Device::Cpu => DeviceWorld::Cpu(Box::new(world)),
            Device::Cuda => DeviceWorld::Cuda(Box::new(CudaWorld::new(
                world,
                shared_gpu()?.with_own_stream()?,
            )?)),
        })
    }

    pub fn device(&self) -> Device {
        match self {
            DeviceWorld::Cpu(_) => Device::Cpu,
            DeviceWorld::Cuda(_) => Device::Cuda,
        }
    }

    /// As [`World::step_frame`].
    pub fn step_frame(
        &mut self,
        from: &[[f64; 3]],
        to: &[[f64; 3]],
        active: &[bool],
    ) -> Result<(), ModelError> {
        match self {
            DeviceWorld::Cpu(world) => Ok(world.step_frame(from, to, active)?),
            DeviceWorld::Cuda(world) => Ok(world.step_frame(from, to, active)?),
        }
    }

    /// As [`World::step_frame_taped`].
    pub fn step_frame_taped(
        &mut self,
        from: &[[f64; 3]],
        to: &[[f64; 3]],
        active: &[bool],
        window: usize,
    ) -> Result<DeviceTape<T>, ModelError> {
        match self {
            DeviceWorld::Cpu(world) => Ok(DeviceTape::Cpu(
                world.step_frame_taped(from, to, active, window)?,
            )),
            DeviceWorld::Cuda(world) => Ok(DeviceTape::Cuda(
                world.step_frame_taped(from, to, active, window)?,
            )),
        }
    }

    /// As [`World::step_frame_keeping`].
    pub fn step_frame_keeping(
        &mut self,
        from: &[[f64; 3]],
        to: &[[f64; 3]],
        active: &[bool],
        at: usize,
    ) -> Result<Particles<T>, ModelError> {
        match self {
            DeviceWorld::Cpu(world) => Ok(world.step_frame_keeping(from, to, active, at)?),
            DeviceWorld::Cuda(world) => Ok(world.step_frame_keeping(from, to, active, at)?),
        }
    }

    /// As [`World::step_frame_rest_taped`].
    pub fn step_frame_rest_taped(
        &mut self,
        from: &[[f64; 3]],
        to: &[[f64; 3]],
        window: usize,
    ) -> Result<DeviceTape<T>, ModelError> {
        match self {
            DeviceWorld::Cpu(world) => Ok(DeviceTape::Cpu(
                world.step_frame_rest_taped(from, to, window)?,
            )),
            DeviceWorld::Cuda(world) => Ok(DeviceTape::Cuda(
                world.step_frame_rest_taped(from, to, window)?,
            )),
        }
    }

    /// As [`World::backward_frame`]; `tape` must come from this world.
    pub fn backward_frame(
        &mut self,
        tape: &DeviceTape<T>,
        grad_after: &ParticleGrads<T>,
    ) -> Result<FrameGrads<T>, ModelError> {
        match (self, tape) {
            (DeviceWorld::Cpu(world), DeviceTape::Cpu(tape)) => {
                Ok(world.backward_frame(tape, grad_after)?)
            }
            (DeviceWorld::Cuda(world), DeviceTape::Cuda(tape)) => {
                Ok(world.backward_frame(tape, grad_after)?)
            }
            _ => Err(ModelError::InvalidOption {
                option: "device".into(),
                problem: "a frame's tape was replayed on another device".into(),
            }),
        }
    }

    /// Replaces the particle state (caller's order).
    pub fn set_state(&mut self, state: &Particles<T>) -> Result<(), ModelError> {
        match self {
            DeviceWorld::Cpu(world) => Ok(world.set_state(state)?),
            DeviceWorld::Cuda(world) => Ok(world.set_state(state)?),
        }
    }

    /// Starts again from `world` (of the same particle count and grid); on
    /// the GPU in the same buffers, so its captured graphs replay again.
    pub fn restart_from(&mut self, world: World<T>) -> Result<(), ModelError> {
        match self {
            DeviceWorld::Cpu(current) => {
                **current = world;
                Ok(())
            }
            DeviceWorld::Cuda(current) => Ok(current.restart_from(world)?),
        }
    }

    /// The world with its particle state up to date (fetched from the GPU).
    pub fn host(&mut self) -> Result<&World<T>, ModelError> {
        match self {
            DeviceWorld::Cpu(world) => Ok(world),
            DeviceWorld::Cuda(world) => Ok(world.host()?),
        }
    }

    /// Changes the world on the host and, on the GPU, sends it back.
    pub fn edit<R>(&mut self, change: impl FnOnce(&mut World<T>) -> R) -> Result<R, ModelError> {
        match self {
            DeviceWorld::Cpu(world) => Ok(change(world)),
            DeviceWorld::Cuda(world) => Ok(world.edit(change)?),
        }
    }

    /// Positions in the caller's particle order, metres.
    pub fn positions(&mut self) -> Result<Vec<[f64; 3]>, ModelError> {
        match self {
            DeviceWorld::Cpu(world) => Ok(world.positions()),
            DeviceWorld::Cuda(world) => Ok(world.positions()?),
        }
    }

    /// The particle state in the caller's order.
    pub fn state(&mut self) -> Result<Particles<T>, ModelError> {
        match self {
            DeviceWorld::Cpu(world) => Ok(world.state()),
            DeviceWorld::Cuda(world) => Ok(world.state()?),
        }
    }

    /// The configuration in force (no transfer).
    pub fn config(&self) -> &PhysicsConfig {
        match self {
            DeviceWorld::Cpu(world) => world.config(),
            DeviceWorld::Cuda(world) => world.config(),
        }
    }

    /// The actuator couplings (kept on the host; no transfer).
    pub fn actuators(&self) -> &Actuators<T> {
        match self {
            DeviceWorld::Cpu(world) => world.actuators(),
            DeviceWorld::Cuda(world) => world.actuators(),
        }
    }

    pub fn particle_count(&self) -> usize {
        match self {
            DeviceWorld::Cpu(world) => world.particle_count(),
            DeviceWorld::Cuda(world) => world.particle_count(),
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::ModelError;
    use dm_mpm::SimError;

    /// A divergence reported by the GPU world is the simulation's error,
    /// as the CPU world's is.
    #[test]
    fn a_divergence_on_either_device_is_the_simulations_error() {
        let diverged = || SimError::Diverged {
            frame: 1,
            substep: 2,
            particle: 3,
            reason: "non-finite position".into(),
        };
        let on_gpu = ModelError::Device(dm_cuda::CudaError::Sim(diverged()));
        assert!(matches!(
            on_gpu.simulation(),
            Some(SimError::Diverged { particle: 3, .. })
        ));
        assert!(ModelError::Simulation(diverged()).simulation().is_some());
        let driver = ModelError::Device(dm_cuda::CudaError::NoDriver);
        assert!(driver.simulation().is_none());
    }
}
