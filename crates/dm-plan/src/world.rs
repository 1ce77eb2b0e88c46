//! The world a plan is optimised in: the fitted model simulated as the
//! playground simulates it (dm-play's coarse simulation: farthest-point
//! samples of the particles, a coarser grid, the CFL-bounded substep),
//! the hands held by the model's compliant actuators. `--exact` plans in
//! the model's own particles, grid and substeps instead. With `--residual`
//! the model's residual network corrects every frame of the planning world
//! as it corrects the fitted model's (its grid and weights; the particles
//! are the planning world's).

use std::sync::{Arc, Mutex};

use dm_model::WorldModel;
use dm_model::corrected::CorrectedWorld;
use dm_model::device::{Device, DeviceReal, DeviceWorld};
use dm_model::residual::ResidualNetwork;
use dm_mpm::World;
use dm_mpm::actuators::Grip;
use dm_mpm::neighbors::PointIndex;
use dm_mpm::{ActuatorConfig, ActuatorMode};
use dm_play::PlayOptions;
use dm_play::session::{CoarseModel, MaterialControl};
use dm_residual::Precision;

use crate::PlanError;
use crate::actions::ActionPlan;

/// The planning world's setup, shared by every rollout.
#[derive(Debug, Clone)]
pub struct PlanningModel {
    coarse: CoarseModel,
    actuator: ActuatorConfig,
    experts: dm_model::ExpertChoice,
    /// Scale on the fitted Young's moduli, and one Poisson ratio for all
    /// when given (a simulation's changed material).
    e_scale: f64,
    nu: Option<f64>,
    /// The hands' hold every world starts with (none: they grasp at the
    /// first frame).
    grip: Option<Arc<Grip>>,
    residual: Option<Arc<ResidualNetwork>>,
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
            e_scale: 1.0,
            nu: None,
            grip: None,
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

    /// The same world in `control`'s material: its scale on the fitted
    /// Young's moduli, its Poisson ratio and particle damping.
    pub fn with_material(mut self, control: &MaterialControl) -> Self {
        self.e_scale = control.e_scale;
        self.nu = control.nu;
        self.coarse.physics.particle_damping = control.damping;
        self
    }

    /// The same world with the hands holding the object as `grip` says
    /// (one entry per planning-world particle) from its first frame.
    pub fn with_grip(mut self, grip: Grip) -> Self {
        self.grip = Some(Arc::new(grip));
        self
    }

    /// The same world in a domain that also holds `points` (an object
    /// that has moved beyond the first frame's domain).
    pub fn with_domain_containing(mut self, points: &[[f64; 3]]) -> Self {
        self.coarse.physics = self.coarse.physics.with_domain_containing(points);
        self
    }

    /// The box particles and hands stay in (`PhysicsConfig::interior`).
    pub fn interior(&self) -> ([f64; 3], [f64; 3]) {
        self.coarse.physics.interior()
    }

    /// The model particle each planning-world particle stands for.
    pub fn model_index(&self) -> &[usize] {
        &self.coarse.body.model_index
    }

    /// The same world with `model`'s residual network correcting every
    /// frame (`precision`: f32 for planning, f64 for gradient checks), on
    /// the planning device (set that first); an error when the model has
    /// none.
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
        let network = ResidualNetwork::new(state.network(precision)?, self.device)?;
        self.residual = Some(Arc::new(network));
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
        self.world_from(self.host_world()?)
    }

    /// The first frame's world on the host.
    fn host_world<T: DeviceReal>(&self) -> Result<World<T>, PlanError> {
        let mut material = self.coarse.material::<T>(self.e_scale, self.nu);
        self.experts.apply_to(&mut material);
        let mut world = self
            .coarse
            .world(self.coarse.physics.clone(), material, self.actuator)?;
        if let Some(grip) = &self.grip {
            world.set_grip(grip)?;
        }
        Ok(world)
    }

    /// `world` on the planning device, with the residual network if any.
    fn world_from<T: DeviceReal>(&self, world: World<T>) -> Result<PlanningWorld<T>, PlanError> {
        Ok(CorrectedWorld::new(
            DeviceWorld::new(world, self.device)?,
            self.residual.clone(),
        ))
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

/// Planning worlds kept between rollouts: each rollout takes one, started
/// again from the first frame, and gives it back when it ends well. On the
/// GPU a kept world keeps its buffers, so the substeps' graphs it captured
/// replay in later rollouts instead of being captured again.
#[derive(Debug)]
pub struct WorldPool<'a, T: DeviceReal = f32> {
    planning: &'a PlanningModel,
    first_frame: World<T>,
    idle: Mutex<Vec<PlanningWorld<T>>>,
}

impl<'a, T: DeviceReal> WorldPool<'a, T> {
    pub fn new(planning: &'a PlanningModel) -> Result<Self, PlanError> {
        Ok(Self {
            planning,
            first_frame: planning.host_world()?,
            idle: Mutex::new(Vec::new()),
        })
    }

    /// The planning model the worlds are of.
    pub fn planning(&self) -> &'a PlanningModel {
        self.planning
    }

    /// `run` in a world at the first frame, which is kept for later when
    /// `run` succeeds (one that failed is dropped: its device state is not
    /// trusted).
    pub fn with_world<R>(
        &self,
        run: impl FnOnce(&mut PlanningWorld<T>) -> Result<R, PlanError>,
    ) -> Result<R, PlanError> {
        let mut world = self.take()?;
        let outcome = run(&mut world);
        if outcome.is_ok() {
            self.give_back(world);
        }
        outcome
    }

    /// A world at the first frame: a kept one started again, or a new one.
    pub fn take(&self) -> Result<PlanningWorld<T>, PlanError> {
        let kept = self
            .idle
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .pop();
        match kept {
            Some(mut world) => {
                world.restart_from(self.first_frame.clone())?;
                Ok(world)
            }
            None => self.planning.world_from(self.first_frame.clone()),
        }
    }

    /// Keeps `world`, taken from this pool, for a later rollout.
    pub fn give_back(&self, world: PlanningWorld<T>) {
        self.idle
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push(world);
    }
}

/// The MPM world of a plan and, with the residual, the frame starts its
/// network sees as history (since the state was last set).
pub type PlanningWorld<T> = CorrectedWorld<T>;

/// Steps `world` through `plan` from its frame 0 (where the hands grasp
/// when `grasp_first`) to its horizon; positions of every frame, frame 0
/// first.
pub fn rollout<T: DeviceReal>(
    world: &mut PlanningWorld<T>,
    plan: &ActionPlan,
    grasp_first: bool,
) -> Result<Vec<Vec<[f64; 3]>>, PlanError> {
    let mut frames = vec![world.positions()?];
    step_through(world, plan, grasp_first, |world| {
        frames.push(world.positions()?);
        Ok(())
    })?;
    Ok(frames)
}

/// [`rollout`]'s last frame alone (on the GPU, nothing is copied back
/// before it).
pub fn rollout_last<T: DeviceReal>(
    world: &mut PlanningWorld<T>,
    plan: &ActionPlan,
    grasp_first: bool,
) -> Result<Vec<[f64; 3]>, PlanError> {
    step_through(world, plan, grasp_first, |_| Ok(()))?;
    Ok(world.positions()?)
}

/// Steps `world` through `plan`, calling `after_frame` after each frame.
fn step_through<T: DeviceReal>(
    world: &mut PlanningWorld<T>,
    plan: &ActionPlan,
    grasp_first: bool,
    mut after_frame: impl FnMut(&mut PlanningWorld<T>) -> Result<(), PlanError>,
) -> Result<(), PlanError> {
    let path = plan.path();
    let hands = plan.anchor_count();
    for t in 0..plan.horizon {
        let grasp = vec![grasp_first && t == 0; hands];
        world.step_frame(&path[t], &path[t + 1], &grasp)?;
        after_frame(world)?;
    }
    Ok(())
}
