//! The world a plan is optimised in: the fitted model simulated as the
//! playground simulates it (dm-play's coarse simulation: farthest-point
//! samples of the particles, a coarser grid, the CFL-bounded substep),
//! the hands held by the model's compliant actuators. `--exact` plans in
//! the model's own particles, grid and substeps instead. With `--residual`
//! the model's residual network corrects every frame of the planning world
//! as it corrects the fitted model's (its grid and weights; the particles
//! are the planning world's).

use std::sync::Arc;

use dm_model::WorldModel;
use dm_model::device::{Device, DeviceReal, DeviceTape, DeviceWorld};
use dm_model::residual::{
    FrameStart, apply_residual, frame_inputs, frame_start, residual_backward,
};
use dm_mpm::correction::CorrectionTape;
use dm_mpm::g2p_backward::ParticleGrads;
use dm_mpm::neighbors::PointIndex;
use dm_mpm::real::Vec3;
use dm_mpm::state::Particles;
use dm_mpm::tape::FrameGrads;
use dm_mpm::{ActuatorConfig, ActuatorMode, World};
use dm_play::PlayOptions;
use dm_play::session::CoarseModel;
use dm_residual::features::ParticleState;
use dm_residual::{FrameInputs, Precision, Residual};

use crate::PlanError;
use crate::actions::ActionPlan;

/// The planning world's setup, shared by every rollout.
#[derive(Debug, Clone)]
pub struct PlanningModel {
    coarse: CoarseModel,
    actuator: ActuatorConfig,
    experts: dm_model::ExpertChoice,
    residual: Option<Arc<Residual>>,
    device: Device,
}

impl PlanningModel {
    pub fn new(model: &WorldModel, options: &PlayOptions) -> Result<Self, PlanError> {
        let coarse = CoarseModel::new(model, options)?;
        // Fewer particles sit farther apart: keep a few inside each grasp.
        let spacing = coarse.body.particle_volume.cbrt();
        let actuator = ActuatorConfig {
            mode: match model.actuator.mode {
                // Rigid hands have no adjoint for their anchors.
                ActuatorMode::Rigid => ActuatorMode::Distributed,
                mode => mode,
            },
            grasp_radius: model.actuator.grasp_radius.max(1.5 * spacing),
            ..model.actuator
        };
        Ok(Self {
            coarse,
            actuator,
            experts: model.options.experts,
            residual: None,
            device: Device::Cpu,
        })
    }

    /// The same world stepped on `device`.
    pub fn on_device(mut self, device: Device) -> Self {
        self.device = device;
        self
    }

    pub fn device(&self) -> Device {
        self.device
    }

    /// The same world with `model`'s residual network correcting every
    /// frame (`precision`: f32 for planning, f64 for gradient checks); an
    /// error when the model has none.
    pub fn with_residual(
        mut self,
        model: &WorldModel,
        precision: Precision,
    ) -> Result<Self, PlanError> {
        let state = model.residual.as_ref().ok_or_else(|| {
            crate::invalid(
                "--residual",
                "the model has no residual network (fitted with `--residual none`)",
            )
        })?;
        self.residual = Some(Arc::new(state.network(precision)?));
        Ok(self)
    }

    /// First-frame particles of the planning world (surface first).
    pub fn particles(&self) -> &[[f64; 3]] {
        &self.coarse.body.particles
    }

    pub fn surface_count(&self) -> usize {
        self.coarse.body.surface_count
    }

    /// Seconds per video frame.
    pub fn frame_dt(&self) -> f64 {
        self.coarse.physics.dt * self.coarse.physics.substeps_per_frame as f64
    }

    pub fn grasp_radius(&self) -> f64 {
        self.actuator.grasp_radius
    }

    /// A fresh world at the first frame, on the planning device (on the
    /// GPU with a stream of its own, so that rollouts run concurrently).
    pub fn world<T: DeviceReal>(&self) -> Result<PlanningWorld<T>, PlanError> {
        let mut material = self.coarse.material::<T>(1.0, None);
        self.experts.apply_to(&mut material);
        let world = World::new(
            self.coarse.physics.clone(),
            &self.coarse.body.particles,
            self.coarse.body.particle_volume,
            material,
            self.actuator,
        )?;
        Ok(PlanningWorld {
            world: DeviceWorld::new_on_own_stream(world, self.device)?,
            residual: self.residual.clone(),
            starts: Vec::new(),
        })
    }

    /// The planning-world particle nearest each of `points` at the first frame.
    pub fn nearest_particles(&self, points: &[[f64; 3]]) -> Vec<usize> {
        let index = PointIndex::new(self.particles());
        points
            .iter()
            .map(|p| index.nearest(p, 1).first().map_or(0, |n| n.0))
            .collect()
    }
}

/// The MPM world of a plan and, with the residual, the frame starts its
/// network sees as history (since the state was last set).
#[derive(Debug)]
pub struct PlanningWorld<T: DeviceReal> {
    world: DeviceWorld<T>,
    residual: Option<Arc<Residual>>,
    starts: Vec<FrameStart>,
}

/// What the adjoint of one frame needs: the substeps' tape and, with the
/// residual, the correction's inputs, Δv and tape.
#[derive(Debug)]
pub struct FrameRecord<T: DeviceReal> {
    /// The frame's index since the state was last set.
    frame: usize,
    substeps: DeviceTape<T>,
    correction: Option<(FrameInputs, Vec<[f64; 3]>, CorrectionTape)>,
}

/// The adjoint of one frame: back to its start, and, with the residual, to
/// the earlier frame starts its network saw as history.
#[derive(Debug)]
pub struct FrameAdjoint<T> {
    pub frame: FrameGrads<T>,
    /// (frame whose start it is, (∂x, ∂v)), caller's particle order.
    pub history: Vec<(usize, ParticleState)>,
}

impl<T: DeviceReal> FrameRecord<T> {
    /// Substeps differentiated exactly.
    pub fn taped_substeps(&self) -> usize {
        self.substeps.len()
    }
}

impl<T: DeviceReal> PlanningWorld<T> {
    /// Starts from `state`; the residual's history starts again there.
    pub fn set_state(&mut self, state: &Particles<T>) -> Result<(), PlanError> {
        self.world.set_state(state)?;
        self.starts.clear();
        Ok(())
    }

    pub fn state(&mut self) -> Result<Particles<T>, PlanError> {
        Ok(self.world.state()?)
    }

    pub fn positions(&mut self) -> Result<Vec<[f64; 3]>, PlanError> {
        Ok(self.world.positions()?)
    }

    pub fn config(&self) -> &dm_mpm::PhysicsConfig {
        self.world.config()
    }

    pub fn release_grasps(&mut self) -> Result<(), PlanError> {
        Ok(self.world.edit(World::release_grasps)?)
    }

    /// One frame with the hands moving from `from` to `to` (grasping where
    /// `grasp`), then the residual's correction.
    pub fn step_frame(
        &mut self,
        from: &[[f64; 3]],
        to: &[[f64; 3]],
        grasp: &[bool],
    ) -> Result<(), PlanError> {
        let Some(network) = &self.residual else {
            self.world.step_frame(from, to, grasp)?;
            return Ok(());
        };
        self.starts.push(frame_start(self.world.host()?));
        let t = self.starts.len() - 1;
        self.world.step_frame(from, to, grasp)?;
        let starts = &self.starts;
        self.world
            .edit(|world| apply_residual(world, network, starts, t))??;
        Ok(())
    }

    /// One frame without hands.
    pub fn step_frame_free(&mut self) -> Result<(), PlanError> {
        self.step_frame(&[], &[], &[])
    }

    /// [`Self::step_frame`], recording its last `window` substeps and the
    /// correction for [`Self::backward_frame`].
    pub fn step_frame_taped(
        &mut self,
        from: &[[f64; 3]],
        to: &[[f64; 3]],
        grasp: &[bool],
        window: usize,
    ) -> Result<FrameRecord<T>, PlanError> {
        let Some(network) = &self.residual else {
            return Ok(FrameRecord {
                frame: self.starts.len(),
                substeps: self.world.step_frame_taped(from, to, grasp, window)?,
                correction: None,
            });
        };
        self.starts.push(frame_start(self.world.host()?));
        let t = self.starts.len() - 1;
        let substeps = self.world.step_frame_taped(from, to, grasp, window)?;
        // The inputs once, for the correction and for its adjoint.
        let inputs = frame_inputs(self.world.host()?, &self.starts, t);
        let dv = network
            .predict(&inputs)
            .map_err(dm_model::ModelError::from)?;
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
    ) -> Result<FrameAdjoint<T>, PlanError> {
        let (Some(network), Some((inputs, dv, tape))) = (&self.residual, &record.correction) else {
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

/// Steps `world` through `plan` from its frame 0 (where the hands grasp
/// when `grasp_first`) to its horizon; positions of every frame, frame 0
/// first.
pub fn rollout<T: DeviceReal>(
    world: &mut PlanningWorld<T>,
    plan: &ActionPlan,
    grasp_first: bool,
) -> Result<Vec<Vec<[f64; 3]>>, PlanError> {
    let path = plan.path();
    let hands = plan.hands.len();
    let mut frames = vec![world.positions()?];
    for t in 0..plan.horizon {
        let grasp = vec![grasp_first && t == 0; hands];
        world.step_frame(&path[t], &path[t + 1], &grasp)?;
        frames.push(world.positions()?);
    }
    Ok(frames)
}
