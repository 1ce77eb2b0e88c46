//! Where a plan is carried out: the fitted model itself (its own
//! particles, grid, substeps and residual), or a world the model did not
//! fit — dm-synth's truth world of the scene, hidden effects included,
//! rebuilt from its truth file, or, for a foreign-physics scene, its
//! MuJoCo simulation. Each planned hand is one anchor in the model; in the
//! truth world it is a cluster of anchors (a centre and a ring, as
//! dm-synth's scripted hands hold the object); in MuJoCo one mocap hand
//! gripping the flex vertices near it. Every plant can also replay the
//! clip's own hands, to start a plan where the clip leaves the object.

use dm_model::device::{Device, DeviceWorld};
use dm_model::{Simulation, WorldModel};
use dm_mpm::World;
use dm_synth::foreign_plant::{MujocoPlant, PlantState};

use crate::PlanError;

use dm_synth::actions::GRIP_RING_RADIUS_M as TRUTH_RING_M;

/// Anchors on the ring.
const TRUTH_RING_ANCHORS: usize = 4;

/// A world that carries out hand motions.
#[derive(Debug)]
pub enum Plant {
    /// The fitted model at full resolution; `clip_hands` are the bundle's
    /// recorded hand anchors per frame.
    Model {
        simulation: Box<Simulation>,
        surface_count: usize,
        clip_hands: Vec<Vec<[f64; 3]>>,
    },
    /// dm-synth's truth world (on the planning device where it can run
    /// there), which of its particles are on the surface, and the true
    /// hands' anchors per frame of the clip.
    Truth {
        world: Box<DeviceWorld<f32>>,
        surface: Vec<bool>,
        clip_hands: Vec<Vec<[f64; 3]>>,
    },
    /// A foreign-physics scene's MuJoCo simulation (each planned hand one
    /// mocap hand gripping the flex vertices near it) and the clip's hand
    /// anchors per frame (the simulation replays its own scripted hands).
    Foreign {
        plant: Box<MujocoPlant>,
        clip_hands: Vec<Vec<[f64; 3]>>,
    },
}

impl Plant {
    pub fn model(
        model: &WorldModel,
        clip_hands: Vec<Vec<[f64; 3]>>,
        device: Device,
    ) -> Result<Self, PlanError> {
        Ok(Plant::Model {
            simulation: Box::new(model.simulation_on(device)?),
            surface_count: model.surface_count,
            clip_hands,
        })
    }

    /// The truth `world` on `device`, or on the CPU where it holds what only
    /// the CPU runs (viscosity, a body force).
    pub fn truth(
        world: World<f32>,
        surface: Vec<bool>,
        clip_hands: Vec<Vec<[f64; 3]>>,
        device: Device,
    ) -> Result<Self, PlanError> {
        let device = device.for_world(&world);
        Ok(Plant::Truth {
            world: Box::new(DeviceWorld::new(world, device)?),
            surface,
            clip_hands,
        })
    }

    pub fn foreign(plant: MujocoPlant, clip_hands: Vec<Vec<[f64; 3]>>) -> Self {
        Plant::Foreign {
            plant: Box::new(plant),
            clip_hands,
        }
    }

    pub fn positions(&mut self) -> Result<Vec<[f64; 3]>, PlanError> {
        // Read every frame: on the GPU, the positions alone come back.
        if let Plant::Truth { world, .. } = self {
            return Ok(world.positions()?);
        }
        Ok(self.state()?.x.iter().map(|p| p.map(f64::from)).collect())
    }

    /// Positions and velocities of the plant's particles.
    pub fn state(&mut self) -> Result<PlantState, PlanError> {
        let of_world = |world: &World<f32>| {
            let state = world.state();
            let point = |p: &dm_mpm::real::Vec3<f32>| [p[0], p[1], p[2]];
            PlantState {
                x: state.x.iter().map(point).collect(),
                v: state.v.iter().map(point).collect(),
            }
        };
        Ok(match self {
            Plant::Model { simulation, .. } => of_world(simulation.world()?),
            Plant::Truth { world, .. } => of_world(world.host()?),
            Plant::Foreign { plant, .. } => plant.state()?,
        })
    }

    /// The surface particles, which a goal is compared with.
    pub fn outline(&mut self) -> Result<Vec<[f64; 3]>, PlanError> {
        let positions = self.positions()?;
        let surface: &[bool] = match self {
            Plant::Model { surface_count, .. } => return Ok(positions[..*surface_count].to_vec()),
            Plant::Truth { surface, .. } => surface,
            Plant::Foreign { plant, .. } => &plant.surface,
        };
        Ok(positions
            .iter()
            .zip(surface)
            .filter(|(_, s)| **s)
            .map(|(p, _)| *p)
            .collect())
    }

    /// The anchors that stand for the planned hands at `hands`.
    pub fn anchors(&self, hands: &[[f64; 3]]) -> Vec<[f64; 3]> {
        match self {
            Plant::Model { .. } | Plant::Foreign { .. } => hands.to_vec(),
            Plant::Truth { .. } => hands
                .iter()
                .flat_map(|h| {
                    let ring = (0..TRUTH_RING_ANCHORS).map(move |i| {
                        let a = std::f64::consts::TAU * i as f64 / TRUTH_RING_ANCHORS as f64;
                        [
                            h[0] + TRUTH_RING_M * a.cos(),
                            h[1] + TRUTH_RING_M * a.sin(),
                            h[2],
                        ]
                    });
                    std::iter::once(*h).chain(ring)
                })
                .collect(),
        }
    }

    /// Frames of the clip whose hands the plant can replay.
    pub fn clip_frames(&self) -> usize {
        match self {
            Plant::Model { clip_hands, .. }
            | Plant::Truth { clip_hands, .. }
            | Plant::Foreign { clip_hands, .. } => clip_hands.len(),
        }
    }

    /// The clip's frame `t` → `t + 1` with its own hands, which grasp as
    /// they reach the object (as the clip was made).
    pub fn replay(&mut self, t: usize) -> Result<(), PlanError> {
        let hands = match self {
            Plant::Model { clip_hands, .. } | Plant::Truth { clip_hands, .. } => clip_hands,
            Plant::Foreign { plant, clip_hands } => {
                if t + 1 >= clip_hands.len() {
                    return Err(crate::invalid(
                        "--start-frame",
                        format!("the clip has no frame {}", t + 1),
                    ));
                }
                plant.replay(t)?;
                return Ok(());
            }
        };
        let (Some(from), Some(to)) = (hands.get(t).cloned(), hands.get(t + 1).cloned()) else {
            return Err(crate::invalid(
                "--start-frame",
                format!("the clip has no frame {}", t + 1),
            ));
        };
        let grasp = vec![true; from.len()];
        self.advance(&from, &to, &grasp)
    }

    /// Lets go of the object; the next plan's hands grasp afresh.
    pub fn release(&mut self) -> Result<(), PlanError> {
        match self {
            Plant::Model { simulation, .. } => simulation.release_grasps()?,
            Plant::Truth { world, .. } => world.edit(World::release_grasps)?,
            Plant::Foreign { plant, .. } => plant.release()?,
        }
        Ok(())
    }

    /// One frame with no hand on the object.
    pub fn step_free(&mut self) -> Result<(), PlanError> {
        self.advance(&[], &[], &[])
    }

    /// One frame while the hands move from `from` to `to`; they grasp at
    /// the first frame carried out.
    pub fn step(
        &mut self,
        from: &[[f64; 3]],
        to: &[[f64; 3]],
        first: bool,
    ) -> Result<(), PlanError> {
        let (a, b) = (self.anchors(from), self.anchors(to));
        let grasp = vec![first; a.len()];
        self.advance(&a, &b, &grasp)
    }

    fn advance(
        &mut self,
        from: &[[f64; 3]],
        to: &[[f64; 3]],
        grasp: &[bool],
    ) -> Result<(), PlanError> {
        match self {
            Plant::Model { simulation, .. } => simulation.step(from, to, grasp)?,
            Plant::Truth { world, .. } => world.step_frame(from, to, grasp)?,
            Plant::Foreign { plant, .. } if from.is_empty() => plant.step_free()?,
            Plant::Foreign { plant, .. } => plant.step(from, to, grasp)?,
        }
        Ok(())
    }
}
