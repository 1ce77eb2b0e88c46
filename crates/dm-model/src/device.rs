//! Where a world model's MPM world runs: on the CPU (the default) or on
//! an NVIDIA GPU through `dm-cuda`.

use crate::ModelError;
use dm_cuda::{CudaDevice, CudaWorld};
use dm_mpm::actuators::Actuators;
use dm_mpm::state::Particles;
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

/// The process's GPU: opened, and its kernels compiled, once.
fn shared_gpu() -> Result<Arc<CudaDevice>, ModelError> {
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

/// An MPM world on the CPU or on the GPU, stepped the same way.
#[derive(Debug)]
pub enum DeviceWorld {
    Cpu(Box<World<f32>>),
    Cuda(Box<CudaWorld<f32>>),
}

impl DeviceWorld {
    /// `world` moved to `device`.
    pub fn new(world: World<f32>, device: Device) -> Result<Self, ModelError> {
        Ok(match device {
            Device::Cpu => DeviceWorld::Cpu(Box::new(world)),
            Device::Cuda => DeviceWorld::Cuda(Box::new(CudaWorld::new(world, shared_gpu()?)?)),
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

    /// The world with its particle state up to date (fetched from the GPU).
    pub fn host(&mut self) -> Result<&World<f32>, ModelError> {
        match self {
            DeviceWorld::Cpu(world) => Ok(world),
            DeviceWorld::Cuda(world) => Ok(world.host()?),
        }
    }

    /// Changes the world on the host and, on the GPU, sends it back.
    pub fn edit<R>(&mut self, change: impl FnOnce(&mut World<f32>) -> R) -> Result<R, ModelError> {
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
    pub fn state(&mut self) -> Result<Particles<f32>, ModelError> {
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
    pub fn actuators(&self) -> &Actuators<f32> {
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
