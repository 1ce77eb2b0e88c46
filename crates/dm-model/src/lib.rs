//! The world model of one scene: the MPM world of `dm-mpm` set up from a
//! scene bundle (domain around the object and the hand motion, floor and
//! up axis from the bundle, material patches on the first-frame
//! particles, actuators driven by the hand tracks), and open-loop rollouts.

pub mod corrected;
pub mod device;
pub mod extension;
pub mod hand_filter;
pub mod metrics;
pub mod preview;
pub mod residual;

pub use dm_residual::ResidualKind;
pub use extension::ModelExtension;
pub use residual::ResidualState;

use dm_bundle::{Bundle, Category};
use dm_mpm::domain::cube_domain_containing;
use dm_mpm::{
    ActuatorConfig, ActuatorMode, MaterialBounds, MaterialPatches, ParticleMaterial, PatchParams,
    PhysicsConfig, SimError, World,
};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Why a model could not be built or rolled out.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error(transparent)]
    Bundle(#[from] dm_bundle::BundleError),
    #[error(transparent)]
    Simulation(#[from] SimError),
    #[error(transparent)]
    Residual(#[from] dm_residual::ResidualError),
    #[error(transparent)]
    Device(#[from] dm_cuda::CudaError),
    #[error("invalid model option `{option}`: {problem}")]
    InvalidOption { option: String, problem: String },
}

impl ModelError {
    /// The simulation's own error (a divergence, a step it refused), on
    /// either device.
    pub fn simulation(&self) -> Option<&SimError> {
        match self {
            ModelError::Simulation(e) | ModelError::Device(dm_cuda::CudaError::Sim(e)) => Some(e),
            _ => None,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ExpertChoice {
    /// Mixture of Constitutive Experts (the method).
    Moce,
    /// A single Neo-Hookean expert (the paper's ablation).
    Nh,
}

impl ExpertChoice {
    /// Makes `material` what this choice simulates: the fitted mixture, or
    /// for the `nh` ablation every particle purely Neo-Hookean.
    pub fn apply_to<T: dm_mpm::Real>(self, material: &mut ParticleMaterial<T>) {
        if self == ExpertChoice::Nh {
            material
                .expert_weights
                .iter_mut()
                .for_each(|w| *w = [T::one(), T::zero(), T::zero()]);
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ActuatorChoice {
    /// Distributed Compliant Actuators (the method).
    Dca,
    /// One actuator per particle.
    Single,
    /// Hard Dirichlet constraints.
    Rigid,
}

/// Model options: CLI arguments of the tools and part of their run records.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, clap::Args)]
pub struct ModelOptions {
    /// Constitutive model.
    #[arg(long, value_enum, default_value_t = ExpertChoice::Moce)]
    pub experts: ExpertChoice,
    /// Actuator model.
    #[arg(long, value_enum, default_value_t = ActuatorChoice::Dca)]
    pub actuators: ActuatorChoice,
    /// Grid cells per axis.
    #[arg(long, default_value_t = 32)]
    pub grid: usize,
    /// Material patches (farthest-point samples of the first frame).
    #[arg(long, default_value_t = 64)]
    pub patches: usize,
    /// Neural residual after each frame (method.md §5): the particle-grid
    /// network, a per-particle MLP (ablation) or none.
    #[arg(long, value_enum, default_value_t = ResidualKind::Pgnd)]
    #[serde(default = "default_residual")]
    pub residual: ResidualKind,
    /// Smooth the recorded hand track before it drives the actuators: a
    /// local linear fit in time with Gaussian weights of this σ, in frames
    /// (0: the raw track; docs/fit.md).
    #[arg(long, default_value_t = 0.0)]
    #[serde(default)]
    pub hand_smoothing: f64,
    /// Grasp radius of each hand anchor, metres: the particles within it
    /// are held (default 0.03, a fingertip pad and its neighbourhood).
    #[arg(long, value_name = "METRES")]
    #[serde(default)]
    pub grasp_radius: Option<f64>,
}

fn default_residual() -> ResidualKind {
    ResidualKind::None
}

impl Default for ModelOptions {
    fn default() -> Self {
        Self {
            experts: ExpertChoice::Moce,
            actuators: ActuatorChoice::Dca,
            grid: 32,
            patches: 64,
            residual: ResidualKind::Pgnd,
            hand_smoothing: 0.0,
            grasp_radius: None,
        }
    }
}

/// Beyond a second at 30 fps the kernel would flatten the hands' motion
/// itself.
const MAX_HAND_SMOOTHING_FRAMES: f64 = 30.0;
/// A grasp radius outside these holds no particle of a typical bundle or
/// holds a whole object (metres).
const MIN_GRASP_RADIUS_M: f64 = 0.001;
const MAX_GRASP_RADIUS_M: f64 = 0.2;

/// method.md §2's physics defaults of a category (unit domain at the origin).
fn category_physics(category: Category, up: [f64; 3]) -> PhysicsConfig {
    match category {
        Category::Volumetric => PhysicsConfig::volumetric([0.0; 3], 1.0, up),
        _ => PhysicsConfig::thin_object([0.0; 3], 1.0, up),
    }
}

/// The particle damping rate (1/s) a model of `category` starts with.
pub fn default_particle_damping(category: Category) -> f64 {
    category_physics(category, [0.0, 0.0, 1.0]).particle_damping
}

/// A world model ready to roll out.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorldModel {
    pub options: ModelOptions,
    pub physics: PhysicsConfig,
    pub bounds: MaterialBounds,
    pub patches: MaterialPatches,
    pub params: PatchParams,
    pub actuator: ActuatorConfig,
    /// First-frame particles: the surface ones first, then the interior.
    pub particles: Vec<[f64; 3]>,
    pub colors: Vec<[f32; 3]>,
    pub surface_count: usize,
    pub particle_volume: f64,
    /// The neural residual with its weights (absent: physics only; models
    /// saved before the residual existed have none).
    #[serde(default)]
    pub residual: Option<ResidualState>,
    /// Physics added by a diagnosis beyond `physics.effects`.
    #[serde(default, skip_serializing_if = "ModelExtension::is_empty")]
    pub extension: ModelExtension,
}

/// Initial material of a category before any fitting: in the soft part of
/// the bounds (a stiff start costs many CFL-limited substeps per frame
/// before the fit has even learnt anything) with a moderate Poisson ratio.
pub fn default_material(category: Category) -> (f64, f64) {
    match category {
        Category::Linear | Category::Planar => (4e4, 0.2),
        Category::Volumetric => (2e5, 0.3),
    }
}

/// Per-particle volume from occupancy: the cloud is voxelised at twice
/// its median nearest-neighbour spacing.
fn particle_volume(points: &[[f64; 3]]) -> f64 {
    let index = dm_mpm::neighbors::PointIndex::new(points);
    let mut nn: Vec<f64> = points
        .iter()
        .step_by((points.len() / 2000).max(1))
        .filter_map(|p| index.nearest(p, 2).get(1).map(|n| n.1))
        .collect();
    nn.sort_by(f64::total_cmp);
    let h = 2.0 * nn.get(nn.len() / 2).copied().unwrap_or(0.01).max(1e-4);
    let mut cells: Vec<[i64; 3]> = points
        .iter()
        .map(|p| p.map(|c| (c / h).floor() as i64))
        .collect();
    cells.sort_unstable();
    cells.dedup();
    cells.len() as f64 * h.powi(3) / points.len() as f64
}

impl ModelOptions {
    /// The ranges `from_bundle` needs: a grid of at least 16, a patch, the
    /// hand smoothing and grasp radius within their bounds.
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.grid < 16 || self.patches == 0 {
            return Err(ModelError::InvalidOption {
                option: "--grid/--patches".into(),
                problem: "need a grid of at least 16 and at least one patch".into(),
            });
        }
        if !(self.hand_smoothing.is_finite()
            && (0.0..=MAX_HAND_SMOOTHING_FRAMES).contains(&self.hand_smoothing))
        {
            return Err(ModelError::InvalidOption {
                option: "--hand-smoothing".into(),
                problem: format!(
                    "σ must be between 0 and {MAX_HAND_SMOOTHING_FRAMES} frames, got {}",
                    self.hand_smoothing
                ),
            });
        }
        if let Some(r) = self.grasp_radius
            && !(r.is_finite() && (MIN_GRASP_RADIUS_M..=MAX_GRASP_RADIUS_M).contains(&r))
        {
            return Err(ModelError::InvalidOption {
                option: "--grasp-radius".into(),
                problem: format!(
                    "must be between {MIN_GRASP_RADIUS_M} and {MAX_GRASP_RADIUS_M} m, got {r}"
                ),
            });
        }
        Ok(())
    }
}

impl WorldModel {
    /// Reads a model file (`model.json`) and checks that its parts agree
    /// ([`Self::check_consistent`]); errors name the file and the field.
    pub fn load(path: &Path) -> Result<Self, ModelError> {
        let model: Self = dm_bundle::read_json(path)?;
        model
            .check_consistent()
            .map_err(|(field, problem)| dm_bundle::BundleError::new(path, field, problem))?;
        Ok(model)
    }

    /// Whether the parts of a model read from a file agree, so that no
    /// later index or allocation trusts a length it never checked: the
    /// options in range, one colour, patch weighting and patch triple per
    /// particle, patch indices inside the patch parameters, the physics
    /// valid, and a residual network whose weights fit its spec. Returns
    /// the field and the problem.
    pub fn check_consistent(&self) -> Result<(), (String, String)> {
        let field = |name: &str, problem: String| Err((name.to_string(), problem));
        if let Err(e) = self.options.validate() {
            return field("options", e.to_string());
        }
        if let Err(e) = self.physics.validate() {
            return field("physics", e.to_string());
        }
        let n = self.particles.len();
        if n == 0 {
            return field("particles", "no particles".into());
        }
        if self.particles.iter().flatten().any(|c| !c.is_finite()) {
            return field("particles", "a coordinate is not finite".into());
        }
        if self.surface_count > n {
            return field(
                "surface_count",
                format!("{} surface particles of {n}", self.surface_count),
            );
        }
        if !(self.particle_volume.is_finite() && self.particle_volume > 0.0) {
            return field("particle_volume", "must be positive".into());
        }
        for (name, len) in [
            ("colors", self.colors.len()),
            ("patches.neighbours", self.patches.neighbours.len()),
            ("patches.beta", self.patches.beta.len()),
        ] {
            if len != n {
                return field(name, format!("{len} entries for {n} particles"));
            }
        }
        let patches = self.patches.centres.len();
        if patches == 0 {
            return field("patches.centres", "no patches".into());
        }
        if let Some(i) = self
            .patches
            .neighbours
            .iter()
            .flatten()
            .find(|&&i| i as usize >= patches)
        {
            return field(
                "patches.neighbours",
                format!("patch {i} of {patches} patches"),
            );
        }
        for (name, len) in [
            ("params.youngs_raw", self.params.youngs_raw.len()),
            ("params.poisson_raw", self.params.poisson_raw.len()),
            ("params.logits", self.params.logits.len()),
        ] {
            if len != patches {
                return field(name, format!("{len} entries for {patches} patches"));
            }
        }
        if let Some(residual) = &self.residual {
            let expected = match residual.spec.parameter_count() {
                Ok(count) => count,
                Err(e) => return field("residual.spec", e.to_string()),
            };
            if residual.parameters.len() != expected {
                return field(
                    "residual.parameters",
                    format!(
                        "{} weights for a network of {expected}",
                        residual.parameters.len()
                    ),
                );
            }
        }
        Ok(())
    }

    /// The untrained model of a bundle's scene.
    pub fn from_bundle(bundle: &Bundle, options: &ModelOptions) -> Result<Self, ModelError> {
        options.validate()?;
        let p = &bundle.particles;
        let mut particles = Vec::new();
        let mut colors = Vec::new();
        for (pts, cols) in [
            (&p.surface_points, &p.surface_colors),
            (&p.interior_points, &p.interior_colors),
        ] {
            for (row, col) in pts.outer_iter().zip(cols.outer_iter()) {
                particles.push([row[0] as f64, row[1] as f64, row[2] as f64]);
                colors.push([col[0], col[1], col[2]]);
            }
        }
        let surface_count = p.surface_points.nrows();
        let meta = &bundle.meta;
        let up = meta.up_axis.unit_vector();

        // Domain: the object, every hand position and the floor.
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        let hands = bundle.tracks.hand_points.outer_iter().flat_map(|f| {
            f.outer_iter()
                .map(|r| [r[0] as f64, r[1] as f64, r[2] as f64])
                .collect::<Vec<_>>()
        });
        for q in particles.iter().copied().chain(hands) {
            for a in 0..3 {
                lo[a] = lo[a].min(q[a] - 0.05);
                hi[a] = hi[a].max(q[a] + 0.05);
            }
        }
        for a in 0..3 {
            // Keep a little room below the floor along the up axis.
            let floor_coord = meta.floor_height_m * up[a];
            if up[a] != 0.0 {
                lo[a] = lo[a].min(floor_coord - 0.02 * up[a].abs());
                hi[a] = hi[a].max(floor_coord + 0.02 * up[a].abs());
            }
        }
        let mut physics = category_physics(meta.category, up);
        physics.grid_res = options.grid;
        let (origin, size) = cube_domain_containing(
            lo,
            hi,
            options.grid,
            physics.wall_cells,
            physics.position_clip,
        );
        physics.domain_origin = origin;
        physics.domain_size = size;
        let dx = physics.dx();
        if let Some(floor) = physics.floor.as_mut() {
            floor.height = meta.floor_height_m;
            floor.margin = if meta.category == Category::Volumetric {
                0.05 * dx
            } else {
                0.0
            };
        }
        physics.substeps_per_frame = ((1.0 / meta.fps) / physics.dt).round().max(1.0) as usize;

        let bounds = match meta.category {
            Category::Volumetric => MaterialBounds::VOLUMETRIC,
            _ => MaterialBounds::THIN,
        };
        let patches = MaterialPatches::build(&particles, options.patches);
        let (e0, nu0) = default_material(meta.category);
        let params = PatchParams::uniform(patches.patch_count(), &bounds, e0, nu0, [0.0; 3]);
        let default_grip = ActuatorConfig::default();
        let actuator = ActuatorConfig {
            mode: match options.actuators {
                ActuatorChoice::Dca => ActuatorMode::Distributed,
                ActuatorChoice::Single => ActuatorMode::Single,
                ActuatorChoice::Rigid => ActuatorMode::Rigid,
            },
            grasp_radius: options.grasp_radius.unwrap_or(default_grip.grasp_radius),
            ..default_grip
        };
        let residual = ResidualState::fresh(
            options.residual,
            &physics,
            dm_residual::NetworkSize::default(),
            0,
        )?;
        Ok(Self {
            options: options.clone(),
            residual,
            physics,
            bounds,
            patches,
            params,
            actuator,
            particle_volume: particle_volume(&particles),
            particles,
            colors,
            surface_count,
            extension: ModelExtension::default(),
        })
    }

    /// Per-particle material of the current parameters.
    pub fn particle_material(&self) -> ParticleMaterial<f32> {
        let mut m = self
            .patches
            .particle_material::<f32>(&self.params, &self.bounds);
        self.apply_expert_choice(&mut m);
        m
    }

    fn apply_expert_choice(&self, material: &mut ParticleMaterial<f32>) {
        self.options.experts.apply_to(material);
    }

    /// Median Young's modulus (Pa) and Poisson ratio over particles.
    pub fn material_medians(&self) -> (f64, f64) {
        let (mut e, mut nu, _) = self.patches.particle_fields(&self.params, &self.bounds);
        e.sort_by(f64::total_cmp);
        nu.sort_by(f64::total_cmp);
        (e[e.len() / 2], nu[nu.len() / 2])
    }

    /// Radius at which particles are drawn as splats (previews and
    /// dm-eval's renders): 0.9 of the particle spacing, so neighbouring
    /// splats overlap into a closed surface.
    pub fn splat_radius(&self) -> f32 {
        (0.9 * self.particle_volume.cbrt()) as f32
    }

    /// The residual network (f32) of this model, if it has one.
    pub fn residual_network(&self) -> Result<Option<dm_residual::Residual>, ModelError> {
        self.residual
            .as_ref()
            .map(|r| r.network(dm_residual::Precision::F32))
            .transpose()
    }

    /// [`WorldModel::residual_network`] on `device`.
    pub fn residual_network_on(
        &self,
        device: device::Device,
    ) -> Result<Option<residual::ResidualNetwork>, ModelError> {
        self.residual_network()?
            .map(|network| residual::ResidualNetwork::new(network, device))
            .transpose()
    }

    /// A fresh MPM world of this model at the first frame (with its
    /// extension's stiff ball and density gradient).
    pub fn world(&self) -> Result<World<f32>, ModelError> {
        self.world_in::<f32>()
    }

    /// [`WorldModel::world`] in the precision `T`: the tools run f32; f64
    /// is the reference that tests hold the f32 world and its gradients to.
    pub fn world_in<T: dm_mpm::Real>(&self) -> Result<World<T>, ModelError> {
        let mut material = self
            .patches
            .particle_material::<T>(&self.params, &self.bounds);
        self.options.experts.apply_to(&mut material);
        self.extension
            .apply_to_material(&self.particles, &mut material);
        let mut world = World::new(
            self.physics.clone(),
            &self.particles,
            self.particle_volume,
            material,
            self.actuator,
        )?;
        if let Some(factors) = self.extension.density_factors(&self.particles) {
            world.set_density_factors(&factors)?;
        }
        Ok(world)
    }

    /// The actuator input of the frame step t → t + 1 for this model:
    /// [`hand_step`] on the smoothed hand track (`--hand-smoothing`) with
    /// the extension's hand-track shift.
    pub fn hand_step(
        &self,
        bundle: &Bundle,
        t: usize,
    ) -> (Vec<[f64; 3]>, Vec<[f64; 3]>, Vec<bool>) {
        let sigma = self.options.hand_smoothing;
        if self.extension.hand_lag_frames == 0.0 && sigma == 0.0 {
            return hand_step(bundle, t);
        }
        let from = self.extension.hand_anchors(bundle, t, sigma);
        let grasp = vec![t == 0; from.len()];
        (
            from,
            self.extension.hand_anchors(bundle, t + 1, sigma),
            grasp,
        )
    }

    /// Open-loop rollout from the first frame, driven by the observed hand
    /// track, for `frames` frames (positions per frame, frame 0 included).
    /// `on_frame` is called after each simulated frame (progress).
    pub fn rollout(
        &self,
        bundle: &Bundle,
        frames: usize,
        on_frame: &mut dyn FnMut(usize),
    ) -> Result<Vec<Vec<[f32; 3]>>, ModelError> {
        self.rollout_on(bundle, frames, device::Device::Cpu, on_frame)
    }

    /// [`WorldModel::rollout`] with the MPM world on `device`.
    pub fn rollout_on(
        &self,
        bundle: &Bundle,
        frames: usize,
        device: device::Device,
        on_frame: &mut dyn FnMut(usize),
    ) -> Result<Vec<Vec<[f32; 3]>>, ModelError> {
        self.rollout_while(bundle, frames, device, &mut |t| {
            on_frame(t);
            std::ops::ControlFlow::Continue(())
        })
    }

    /// [`WorldModel::rollout_on`] that stops early, with the frames so far,
    /// where `on_frame` (called after each frame with the frames done)
    /// breaks.
    pub fn rollout_while(
        &self,
        bundle: &Bundle,
        frames: usize,
        device: device::Device,
        on_frame: &mut dyn FnMut(usize) -> std::ops::ControlFlow<()>,
    ) -> Result<Vec<Vec<[f32; 3]>>, ModelError> {
        let frames = frames.min(bundle.frame_count());
        let mut simulation = self.simulation_on(device)?;
        let mut out = vec![simulation.positions_f32()?];
        for t in 0..frames.saturating_sub(1) {
            let (from, to, grasp) = self.hand_step(bundle, t);
            simulation.step(&from, &to, &grasp)?;
            out.push(simulation.positions_f32()?);
            if on_frame(t + 1).is_break() {
                break;
            }
        }
        Ok(out)
    }

    /// This model in a cube domain that also holds `points` (hands that
    /// will move beyond the recorded clip's reach): the same grid, so
    /// coarser cells where the domain grows; the model itself when the
    /// domain already holds them.
    pub fn with_domain_containing(&self, points: &[[f64; 3]]) -> Self {
        let mut out = self.clone();
        out.physics = self.physics.with_domain_containing(points);
        out
    }

    /// A simulation of this model at its first frame: its world and, when
    /// it has one, its residual network.
    pub fn simulation(&self) -> Result<Simulation, ModelError> {
        self.simulation_on(device::Device::Cpu)
    }

    /// [`WorldModel::simulation`] with the MPM world and the residual
    /// network on `device`.
    pub fn simulation_on(&self, device: device::Device) -> Result<Simulation, ModelError> {
        Ok(Simulation {
            world: corrected::CorrectedWorld::new(
                device::DeviceWorld::new(self.world()?, device)?,
                self.residual_network_on(device)?.map(std::sync::Arc::new),
            ),
            frames: 0,
        })
    }

    /// Per-particle material with every fitted Young's modulus multiplied
    /// by `e_scale` and, when given, one Poisson ratio `nu` for all (the
    /// extension's stiff ball included).
    pub fn scaled_material(&self, e_scale: f64, nu: Option<f64>) -> ParticleMaterial<f32> {
        let (e, fitted_nu, weights) = self.patches.particle_fields(&self.params, &self.bounds);
        let e: Vec<f64> = e.iter().map(|e| e * e_scale).collect();
        let nu = nu.map_or(fitted_nu, |nu| vec![nu; e.len()]);
        let mut material = ParticleMaterial::from_fields(&e, &nu, &weights);
        self.apply_expert_choice(&mut material);
        self.extension
            .apply_to_material(&self.particles, &mut material);
        material
    }
}

/// A world model being stepped frame by frame: the MPM world, the residual
/// network, and the frame starts the network reads. [`WorldModel::rollout`]
/// is a loop over [`Simulation::step`], so stepping by hand gives bitwise
/// the same frames.
#[derive(Debug)]
pub struct Simulation {
    world: corrected::CorrectedWorld,
    frames: usize,
}

impl Simulation {
    /// The MPM world (particle state, configuration), its state fetched
    /// from the GPU first when it runs there.
    pub fn world(&mut self) -> Result<&World<f32>, ModelError> {
        self.world.world().host()
    }

    /// The device the MPM world runs on.
    pub fn device(&self) -> device::Device {
        self.world.device()
    }

    /// The configuration in force.
    pub fn config(&self) -> &PhysicsConfig {
        self.world.config()
    }

    /// Frames stepped since the first frame.
    pub fn frame(&self) -> usize {
        self.frames
    }

    /// Particle positions in the model's order.
    pub fn positions_f32(&mut self) -> Result<Vec<[f32; 3]>, ModelError> {
        Ok(self
            .world
            .positions()?
            .iter()
            .map(|p| p.map(|c| c as f32))
            .collect())
    }

    /// Advances one frame while the hand anchors move linearly from `from`
    /// to `to`; anchors marked in `grasp` tie the particles within the
    /// grasp radius at the frame's start. The residual, if any, corrects
    /// the frame's velocities.
    pub fn step(
        &mut self,
        from: &[[f64; 3]],
        to: &[[f64; 3]],
        grasp: &[bool],
    ) -> Result<(), ModelError> {
        self.world.step_frame(from, to, grasp)?;
        self.frames += 1;
        Ok(())
    }

    /// Lets go of the object (see [`World::release_grasps`]).
    pub fn release_grasps(&mut self) -> Result<(), ModelError> {
        self.world.release_grasps()
    }

    /// Replaces the world by one built from `physics` and `material` (the
    /// substep is chosen again for the new stiffness) that continues from
    /// the current particle state, on the same device. Grasps are not
    /// carried over: anchors marked in the next step's `grasp` capture
    /// them again.
    pub fn rebuild(
        &mut self,
        model: &WorldModel,
        physics: PhysicsConfig,
        material: ParticleMaterial<f32>,
    ) -> Result<(), ModelError> {
        let state = self.world.state()?;
        let mut world = World::new(
            physics,
            &model.particles,
            model.particle_volume,
            material,
            model.actuator,
        )?;
        world.set_state(&state)?;
        let device = self.world.device();
        self.world
            .replace_world(device::DeviceWorld::new(world, device)?);
        Ok(())
    }
}

/// Hand anchor positions of frame `t` (metres).
pub fn hand_anchors(bundle: &Bundle, t: usize) -> Vec<[f64; 3]> {
    bundle
        .tracks
        .hand_points
        .index_axis(ndarray::Axis(0), t)
        .outer_iter()
        .map(|r| [r[0] as f64, r[1] as f64, r[2] as f64])
        .collect()
}

/// The actuator input of the frame step t → t + 1: anchors at both ends and
/// which anchors may grasp. Grasps are captured at frame 0 only, from every
/// anchor (the hands hold the object when the clip starts), so a rollout
/// replayed frame by frame — as the fitting's backward pass does — sees the
/// same couplings as the forward pass.
pub fn hand_step(bundle: &Bundle, t: usize) -> (Vec<[f64; 3]>, Vec<[f64; 3]>, Vec<bool>) {
    let from = hand_anchors(bundle, t);
    let grasp = vec![t == 0; from.len()];
    (from, hand_anchors(bundle, t + 1), grasp)
}
