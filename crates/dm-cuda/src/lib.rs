//! CUDA backend of the MLS-MPM world (`dm-mpm`): the same substep —
//! stress and P2G, grid update, G2P, actuators — as CUDA C kernels
//! (`kernels/`, one file per stage), compiled by NVRTC when the backend
//! starts. The driver and NVRTC are loaded at run time, so every build
//! has the backend and a machine without a GPU gets a clear error.
//!
//! [`CudaWorld`] holds the particle state on the device and a host
//! [`dm_mpm::World`] for everything else (configuration, material,
//! grasping); the state comes back to the host when asked for.

mod backward;
pub mod consts;
mod device;
pub mod emulator;
mod error;
mod frame;
pub mod kernels;
mod launch;
mod residual;
mod world;

pub use backward::{AdjointSeconds, DeviceTape, WindowGrads};
pub use device::CudaDevice;
pub use error::CudaError;
pub use frame::DeviceFrameTape;
pub use kernels::Precision;
pub use residual::CudaResidual;
pub use world::{CudaWorld, DeviceReal, unsupported};
