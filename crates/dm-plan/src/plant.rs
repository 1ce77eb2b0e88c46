//! Where a plan is carried out: the fitted model itself (its own
//! particles, grid, substeps and residual), or a world the model did not
//! fit — dm-synth's truth world of the scene, hidden effects included,
//! rebuilt from its truth file. Each planned hand is one anchor in the
//! model; in the truth world it is a cluster of anchors (a centre and a
//! ring, as dm-synth's scripted hands hold the object).

use dm_model::{Simulation, WorldModel};
use dm_mpm::World;
use dm_mpm::state::Particles;

use crate::PlanError;

use dm_synth::actions::GRIP_RING_RADIUS_M as TRUTH_RING_M;

/// Anchors on the ring.
const TRUTH_RING_ANCHORS: usize = 4;

/// A world that carries out hand motions.
#[derive(Debug)]
pub enum Plant {
    /// The fitted model at full resolution.
    Model {
        simulation: Box<Simulation>,
        surface_count: usize,
    },
    /// dm-synth's truth world, and which of its particles are on the surface.
    Truth {
        world: Box<World<f32>>,
        surface: Vec<bool>,
    },
}

impl Plant {
    pub fn model(model: &WorldModel) -> Result<Self, PlanError> {
        Ok(Plant::Model {
            simulation: Box::new(model.simulation()?),
            surface_count: model.surface_count,
        })
    }

    pub fn truth(world: World<f32>, surface: Vec<bool>) -> Self {
        Plant::Truth {
            world: Box::new(world),
            surface,
        }
    }

    fn world(&mut self) -> Result<&World<f32>, PlanError> {
        match self {
            Plant::Model { simulation, .. } => Ok(simulation.world()?),
            Plant::Truth { world, .. } => Ok(world),
        }
    }

    pub fn positions(&mut self) -> Result<Vec<[f64; 3]>, PlanError> {
        Ok(self.world()?.positions())
    }

    pub fn state(&mut self) -> Result<Particles<f32>, PlanError> {
        Ok(self.world()?.state())
    }

    /// The surface particles, which a goal is compared with.
    pub fn outline(&mut self) -> Result<Vec<[f64; 3]>, PlanError> {
        let positions = self.positions()?;
        Ok(match self {
            Plant::Model { surface_count, .. } => positions[..*surface_count].to_vec(),
            Plant::Truth { surface, .. } => positions
                .iter()
                .zip(surface)
                .filter(|(_, s)| **s)
                .map(|(p, _)| *p)
                .collect(),
        })
    }

    /// The anchors that stand for the planned hands at `hands`.
    pub fn anchors(&self, hands: &[[f64; 3]]) -> Vec<[f64; 3]> {
        match self {
            Plant::Model { .. } => hands.to_vec(),
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
        match self {
            Plant::Model { simulation, .. } => simulation.step(&a, &b, &grasp)?,
            Plant::Truth { world, .. } => world.step_frame(&a, &b, &grasp)?,
        }
        Ok(())
    }
}
