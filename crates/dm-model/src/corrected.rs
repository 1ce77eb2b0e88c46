//! An MPM world whose frames a residual network corrects, with the frame
//! starts the network reads as history: stepped as the world model steps
//! ([`crate::Simulation`]), or taped and differentiated frame by frame
//! (dm-plan's gradients), back through each correction to the frame
//! starts it saw.

use std::sync::Arc;

use dm_mpm::World;
use dm_mpm::correction::CorrectionTape;
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::real::Vec3;
use dm_mpm::state::Particles;
use dm_mpm::tape::FrameGrads;
use dm_residual::FrameInputs;
use dm_residual::features::ParticleState;

use crate::ModelError;
use crate::device::{DeviceReal, DeviceTape, DeviceWorld};
use crate::residual::{
    FrameStart, ResidualNetwork, apply_residual, frame_inputs, frame_start, residual_backward,
};

/// The MPM world and, with a network, the frame starts since the state
/// was last set.
#[derive(Debug)]
pub struct CorrectedWorld<T: DeviceReal = f32> {
    world: DeviceWorld<T>,
    network: Option<Arc<ResidualNetwork>>,
    /// Kept only with a network.
    starts: Vec<FrameStart>,
}

/// What the adjoint of one frame needs: the substeps' tape and, with the
/// network, the correction's inputs, Δv and tape.
#[derive(Debug)]
pub struct FrameRecord<T: DeviceReal = f32> {
    /// The frame's index since the state was last set.
    frame: usize,
    substeps: DeviceTape<T>,
    correction: Option<(FrameInputs, Vec<[f64; 3]>, CorrectionTape)>,
}

impl<T: DeviceReal> FrameRecord<T> {
    /// Substeps differentiated exactly.
    pub fn taped_substeps(&self) -> usize {
        self.substeps.len()
    }
}

/// The adjoint of one frame: back to its start, and, with the network, to
/// the earlier frame starts it saw as history.
#[derive(Debug)]
pub struct FrameAdjoint<T> {
    pub frame: FrameGrads<T>,
    /// (frame whose start it is, (∂x, ∂v)), caller's particle order.
    pub history: Vec<(usize, ParticleState)>,
}

impl<T: DeviceReal> CorrectedWorld<T> {
    pub fn new(world: DeviceWorld<T>, network: Option<Arc<ResidualNetwork>>) -> Self {
        Self {
            world,
            network,
            starts: Vec::new(),
        }
    }

    pub fn device(&self) -> crate::device::Device {
        self.world.device()
    }

    /// The MPM world (its state is on the device it runs on).
    pub fn world(&mut self) -> &mut DeviceWorld<T> {
        &mut self.world
    }

    /// Replaces the MPM world; the network's history goes on.
    pub fn replace_world(&mut self, world: DeviceWorld<T>) {
        self.world = world;
    }

    /// Starts from `state`; the network's history starts again there.
    pub fn set_state(&mut self, state: &Particles<T>) -> Result<(), ModelError> {
        self.world.set_state(state)?;
        self.starts.clear();
        Ok(())
    }

    /// Starts again from `world` (see [`DeviceWorld::restart_from`]); the
    /// network's history starts again too.
    pub fn restart_from(&mut self, world: World<T>) -> Result<(), ModelError> {
        self.world.restart_from(world)?;
        self.starts.clear();
        Ok(())
    }

    pub fn state(&mut self) -> Result<Particles<T>, ModelError> {
        self.world.state()
    }

    pub fn positions(&mut self) -> Result<Vec<[f64; 3]>, ModelError> {
        self.world.positions()
    }

    pub fn config(&self) -> &dm_mpm::PhysicsConfig {
        self.world.config()
    }

    /// Lets go of the object (see [`World::release_grasps`]).
    pub fn release_grasps(&mut self) -> Result<(), ModelError> {
        self.world.edit(World::release_grasps)
    }

    /// One frame with the hands moving from `from` to `to` (grasping where
    /// `grasp`), then the network's correction; returns the Δv it applied.
    pub fn step_frame(
        &mut self,
        from: &[[f64; 3]],
        to: &[[f64; 3]],
        grasp: &[bool],
    ) -> Result<Option<Vec<[f64; 3]>>, ModelError> {
        let Some(network) = &self.network else {
            self.world.step_frame(from, to, grasp)?;
            return Ok(None);
        };
        self.starts.push(frame_start(self.world.host()?));
        let t = self.starts.len() - 1;
        if let Err(error) = self.world.step_frame(from, to, grasp) {
            self.starts.pop();
            return Err(error);
        }
        let starts = &self.starts;
        let (dv, _) = self
            .world
            .edit(|world| apply_residual(world, network, starts, t))??;
        Ok(Some(dv))
    }

    /// One frame without hands.
    pub fn step_frame_free(&mut self) -> Result<(), ModelError> {
        self.step_frame(&[], &[], &[]).map(drop)
    }

    /// [`Self::step_frame`], recording its last `window` substeps and the
    /// correction for [`Self::backward_frame`].
    pub fn step_frame_taped(
        &mut self,
        from: &[[f64; 3]],
        to: &[[f64; 3]],
        grasp: &[bool],
        window: usize,
    ) -> Result<FrameRecord<T>, ModelError> {
        let Some(network) = &self.network else {
            return Ok(FrameRecord {
                frame: self.starts.len(),
                substeps: self.world.step_frame_taped(from, to, grasp, window)?,
                correction: None,
            });
        };
        self.starts.push(frame_start(self.world.host()?));
        let t = self.starts.len() - 1;
        let substeps = match self.world.step_frame_taped(from, to, grasp, window) {
            Ok(tape) => tape,
            Err(error) => {
                self.starts.pop();
                return Err(error);
            }
        };
        // The inputs once, for the correction and for its adjoint.
        let inputs = frame_inputs(self.world.host()?, &self.starts, t);
        let dv = network.predict(&inputs)?;
        let tape = self
            .world
            .edit(|world| world.apply_velocity_correction(&dv))??;
        Ok(FrameRecord {
            frame: t,
            substeps,
            correction: Some((inputs, dv, tape)),
        })
    }

    /// Carries `carried` (the adjoint of the state after the frame) back
    /// through the correction and the substeps to the frame's start, and
    /// to the history frames' starts the correction saw.
    pub fn backward_frame(
        &mut self,
        record: &FrameRecord<T>,
        carried: &ParticleGrads<T>,
    ) -> Result<FrameAdjoint<T>, ModelError> {
        let (Some(network), Some((inputs, dv, tape))) = (&self.network, &record.correction) else {
            return Ok(FrameAdjoint {
                frame: self.world.backward_frame(&record.substeps, carried)?,
                history: Vec::new(),
            });
        };
        let mut after_substeps = carried.clone();
        let grads = residual_backward(network, inputs, dv, tape, &mut after_substeps, 0.0)?;
        let mut frame = self
            .world
            .backward_frame(&record.substeps, &after_substeps)?;
        for (c, g) in frame.state.x.iter_mut().zip(&grads.x_start) {
            *c += Vec3::new(T::lit(g[0]), T::lit(g[1]), T::lit(g[2]));
        }
        // History k is the start of frame t − 1 − k, clamped at 0 (`history_of`).
        let history = grads
            .history
            .into_iter()
            .enumerate()
            .map(|(k, adjoint)| (record.frame.saturating_sub(k + 1), adjoint))
            .collect();
        Ok(FrameAdjoint { frame, history })
    }
}
