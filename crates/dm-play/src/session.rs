//! One playground session: the fitted model's MPM world driven live by two
//! hands (DCA anchors) the user moves, with material and damping the user
//! changes. Everything here is synchronous; the server owns the session
//! behind a mutex and steps it from its simulation thread.

use std::time::Instant;

#[cfg(feature = "cli")]
use clap::builder::ArgPredicate;
use dm_appearance::SplatFollower;
use dm_model::device::{Device, DeviceWorld};
use dm_model::{ModelExtension, WorldModel};
use dm_mpm::neighbors::PointIndex;
use dm_mpm::{ActuatorConfig, ActuatorMode, ParticleMaterial, PhysicsConfig, World};
use serde::{Deserialize, Serialize};

use crate::PlayError;
use crate::scene::{SceneView, Sprites};
use dm_splat::Gaussians;

/// Number of hands the page drives (WASD+QE and IJKL+UO).
pub const HAND_COUNT: usize = 2;
/// Range of the Young's-modulus scale slider.
pub const E_SCALE_RANGE: [f64; 2] = [0.1, 10.0];
/// Range of the Poisson-ratio slider (the material bounds stop short of 0.5).
pub const NU_RANGE: [f64; 2] = [0.0, 0.45];
/// Range of the particle damping slider, 1/s.
pub const DAMPING_RANGE: [f64; 2] = [0.0, 50.0];
/// Fastest hand speed accepted from the page, m/s.
pub const MAX_HAND_SPEED: f64 = 2.0;

/// How the playground simulates (may be coarser than the fit); with the
/// feature `cli`, also the command-line flags of the live simulation
/// (dm-play, dm-bench play), whose defaults are
/// [`PlayOptions::interactive`]'s, or the model's own with `--exact`.
///
/// `None` takes the model's value: `grid`, the model's grid and domain
/// (otherwise a cube domain is chosen around the object for this grid);
/// `particles`, all of them (otherwise farthest-point samples of the
/// model's, each carrying the volume of the ones left out); `substeps`, the
/// model's (the frame time stays the model's video frame time); `cfl`, the
/// model's, 0.3. `exact` records that the command line asked for the
/// model's own simulation; the other fields already hold its result.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::Args), command(about = None, long_about = None))]
pub struct PlayOptions {
    /// Grid cells per axis of the live simulation (default: 20, coarser
    /// than the fit so it runs in real time; see --exact).
    #[cfg_attr(
        feature = "cli",
        arg(
            long,
            default_value = "20",
            hide_default_value = true,
            default_value_if("exact", ArgPredicate::IsPresent, None)
        )
    )]
    pub grid: Option<usize>,
    /// Simulated particles (default: 1500 farthest-point samples of the model's).
    #[cfg_attr(
        feature = "cli",
        arg(
            long,
            default_value = "1500",
            hide_default_value = true,
            default_value_if("exact", ArgPredicate::IsPresent, None)
        )
    )]
    pub particles: Option<usize>,
    /// Substeps per frame before the CFL refinement (default: 1, as few as
    /// the CFL bound allows; with --exact the model's).
    #[cfg_attr(
        feature = "cli",
        arg(
            long,
            default_value = "1",
            hide_default_value = true,
            default_value_if("exact", ArgPredicate::IsPresent, None)
        )
    )]
    pub substeps: Option<usize>,
    /// CFL number of the substep bound, dt ≤ cfl·dx/c (default: 0.5, as the
    /// fit's).
    #[cfg_attr(
        feature = "cli",
        arg(
            long,
            default_value = "0.5",
            hide_default_value = true,
            default_value_if("exact", ArgPredicate::IsPresent, None)
        )
    )]
    #[serde(default)]
    pub cfl: Option<f64>,
    /// Simulate exactly as the fit did (the model's grid, domain, particles
    /// and substeps): slower than real time on small machines.
    #[cfg_attr(feature = "cli", arg(long, conflicts_with_all = ["grid", "particles"]))]
    #[serde(default)]
    pub exact: bool,
    /// Where the MPM world runs (cuda: the first NVIDIA GPU).
    #[cfg_attr(feature = "cli", arg(long, value_enum, default_value_t = Device::Cpu))]
    #[serde(default)]
    pub device: Device,
}

/// Grid of [`PlayOptions::interactive`].
pub const INTERACTIVE_GRID: usize = 20;
/// CFL number of [`PlayOptions::interactive`].
pub const INTERACTIVE_CFL: f64 = 0.5;
/// Particles of [`PlayOptions::interactive`].
pub const INTERACTIVE_PARTICLES: usize = 1500;
/// Substeps per frame of [`PlayOptions::interactive`]: as few as the CFL
/// bound allows.
pub const INTERACTIVE_SUBSTEPS: usize = 1;

impl PlayOptions {
    /// The playground's defaults (dm-play, dm-bench play): a coarser grid,
    /// fewer particles and a longer CFL-bounded substep than the fit, so a
    /// frame simulates in real time on two cores (measured in
    /// docs/BENCHMARKS.md; the splats keep their full count and follow the
    /// fewer particles by LBS).
    pub fn interactive() -> Self {
        Self {
            grid: Some(INTERACTIVE_GRID),
            particles: Some(INTERACTIVE_PARTICLES),
            substeps: Some(INTERACTIVE_SUBSTEPS),
            cfl: Some(INTERACTIVE_CFL),
            exact: false,
            device: Device::Cpu,
        }
    }
}

/// The simulated particles: all of the model's or a subset.
#[derive(Clone, Debug)]
pub struct Body {
    /// First-frame positions, surface particles first.
    pub particles: Vec<[f64; 3]>,
    pub colors: Vec<[f32; 3]>,
    pub surface_count: usize,
    /// m³ per particle.
    pub particle_volume: f64,
    /// Radius particles are drawn with (0.9 of their spacing).
    pub splat_radius: f32,
    /// Index of each particle in the model.
    pub model_index: Vec<usize>,
}

impl Body {
    fn new(model: &WorldModel, limit: Option<usize>) -> Result<Self, PlayError> {
        let n = model.particles.len();
        let keep = limit.unwrap_or(n).min(n);
        if keep < 8 {
            return Err(PlayError::InvalidOption {
                option: "--particles".into(),
                problem: format!("needs at least 8 particles, got {keep}"),
            });
        }
        let mut chosen = if keep == n {
            (0..n).collect()
        } else {
            dm_mpm::neighbors::farthest_point_sampling(&model.particles, keep)
        };
        chosen.sort_unstable();
        let particle_volume = model.particle_volume * n as f64 / keep as f64;
        Ok(Self {
            particles: chosen.iter().map(|&i| model.particles[i]).collect(),
            colors: chosen.iter().map(|&i| model.colors[i]).collect(),
            surface_count: chosen.iter().filter(|&&i| i < model.surface_count).count(),
            particle_volume,
            splat_radius: (0.9 * particle_volume.cbrt()) as f32,
            model_index: chosen,
        })
    }
}

/// The material the user set: a scale on the fitted E field, and ν.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaterialControl {
    /// Multiplies every particle's fitted Young's modulus.
    pub e_scale: f64,
    /// Poisson ratio of every particle; `None` keeps the fitted field.
    pub nu: Option<f64>,
    /// Particle velocity damping rate, 1/s.
    pub damping: f64,
}

/// One hand: an anchor the keyboard moves, attached when the user clicked a
/// grab point for it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Hand {
    pub position: [f64; 3],
    /// Commanded velocity (m/s) from the keys held.
    pub velocity: [f64; 3],
    /// Whether the hand holds the object (its anchor may grasp).
    pub attached: bool,
}

/// The JSON state of `GET /api/state` (keys documented in docs/playground.md).
#[derive(Clone, Debug, Serialize)]
pub struct SessionState {
    pub frame: usize,
    pub particle_count: usize,
    /// Mean particle position, metres.
    pub centroid: [f64; 3],
    pub hands: Vec<Hand>,
    /// Particles tied to each hand.
    pub grasped_particles: Vec<usize>,
    pub material: MaterialControl,
    /// Wall time of the last simulated frame, milliseconds.
    pub sim_ms: f64,
    pub substeps_per_frame: usize,
    pub grid: usize,
    /// Simulated seconds per frame.
    pub frame_dt: f64,
    /// Frames held by the recording in progress (`None`: not recording).
    pub recording_frames: Option<usize>,
    /// Last simulation error (the session was reset after it).
    pub last_error: Option<String>,
}

/// A recording: particle positions and hand anchors per frame since it started.
#[derive(Clone, Debug, Default)]
pub struct Recording {
    pub positions: Vec<Vec<[f32; 3]>>,
    pub hands: Vec<[[f64; 3]; HAND_COUNT]>,
}

/// The live simulation of one model.
#[derive(Debug)]
pub struct Session {
    model: WorldModel,
    coarse: CoarseModel,
    world: DeviceWorld,
    device: Device,
    hands: [Hand; HAND_COUNT],
    material: MaterialControl,
    /// Particles positions of the last frame (model order).
    positions: Vec<[f32; 3]>,
    sim_ms: f64,
    /// Frames simulated since the first frame (the world restarts its own
    /// count on every rebuild).
    frame: usize,
    recording: Option<Recording>,
    last_error: Option<String>,
    view: SceneView,
    /// Fitted splats as loaded, and their LBS follower (moved every frame).
    splats: Option<(Gaussians<f32>, SplatFollower)>,
}

/// The simulation the playground runs of a model (and dm-plan plans in):
/// the chosen particles, the physics for the chosen grid, substep and CFL
/// number, the particles' fitted material fields and the model's extension
/// (a stiff ball, a density gradient, as dm-diagnose adds them).
#[derive(Clone, Debug)]
pub struct CoarseModel {
    pub body: Body,
    pub physics: PhysicsConfig,
    /// Fitted per-particle E (Pa), ν and expert weights.
    pub youngs: Vec<f64>,
    pub poisson: Vec<f64>,
    pub expert_weights: Vec<[f64; 3]>,
    pub extension: ModelExtension,
    /// The extension's density factor of each body particle, graded over
    /// the whole model's extent.
    pub density_factors: Option<Vec<f64>>,
}

impl CoarseModel {
    pub fn new(model: &WorldModel, options: &PlayOptions) -> Result<Self, PlayError> {
        let mut physics = model.physics.clone();
        let body = Body::new(model, options.particles)?;
        if let Some(grid) = options.grid {
            if grid < 12 {
                return Err(PlayError::InvalidOption {
                    option: "--grid".into(),
                    problem: format!("needs at least 12 cells, got {grid}"),
                });
            }
            playground_domain(&mut physics, &body.particles, grid);
        }
        if let Some(cfl) = options.cfl {
            if !(cfl > 0.0 && cfl <= 1.0) {
                return Err(PlayError::InvalidOption {
                    option: "--cfl".into(),
                    problem: format!("needs 0 < cfl <= 1, got {cfl}"),
                });
            }
            physics.cfl = Some(cfl);
        }
        if let Some(substeps) = options.substeps {
            if substeps == 0 {
                return Err(PlayError::InvalidOption {
                    option: "--substeps".into(),
                    problem: "needs at least 1".into(),
                });
            }
            // Keep the frame time, lengthen the substep (CFL still refines).
            let frame_dt = physics.dt * physics.substeps_per_frame as f64;
            physics.substeps_per_frame = substeps;
            physics.dt = frame_dt / substeps as f64;
        }
        let (youngs, poisson, expert_weights) =
            model.patches.particle_fields(&model.params, &model.bounds);
        let ids = &body.model_index;
        Ok(Self {
            youngs: ids.iter().map(|&i| youngs[i]).collect(),
            poisson: ids.iter().map(|&i| poisson[i]).collect(),
            expert_weights: ids.iter().map(|&i| expert_weights[i]).collect(),
            extension: model.extension.clone(),
            density_factors: model
                .extension
                .density_factors(&model.particles)
                .map(|factors| ids.iter().map(|&i| factors[i]).collect()),
            body,
            physics,
        })
    }

    /// A world of the body at its first frame in `physics` (this model's,
    /// possibly changed) and `material`, with the extension's density
    /// gradient.
    pub fn world<T: dm_mpm::Real>(
        &self,
        physics: PhysicsConfig,
        material: ParticleMaterial<T>,
        actuator: ActuatorConfig,
    ) -> Result<World<T>, dm_mpm::SimError> {
        let mut world = World::new(
            physics,
            &self.body.particles,
            self.body.particle_volume,
            material,
            actuator,
        )?;
        if let Some(factors) = &self.density_factors {
            world.set_density_factors(factors)?;
        }
        Ok(world)
    }

    /// The fitted material with every E times `e_scale` and, when given,
    /// one Poisson ratio `nu` for all (the extension's stiff ball included).
    pub fn material<T: dm_mpm::Real>(&self, e_scale: f64, nu: Option<f64>) -> ParticleMaterial<T> {
        let e: Vec<f64> = self.youngs.iter().map(|e| e * e_scale).collect();
        let nu: Vec<f64> = match nu {
            Some(nu) => vec![nu; self.poisson.len()],
            None => self.poisson.clone(),
        };
        let mut material = ParticleMaterial::from_fields(&e, &nu, &self.expert_weights);
        self.extension
            .apply_to_material(&self.body.particles, &mut material);
        material
    }
}

impl Session {
    /// A session at the model's first frame.
    pub fn new(model: WorldModel, options: &PlayOptions) -> Result<Self, PlayError> {
        let coarse = CoarseModel::new(&model, options)?;
        let material = MaterialControl {
            e_scale: 1.0,
            nu: None,
            damping: coarse.physics.particle_damping,
        };
        let view = SceneView::new(&coarse.body.particles, &coarse.physics)?;
        // Replaced by `rebuild_world` below (with the material control).
        let world = DeviceWorld::new(
            coarse.world(
                coarse.physics.clone(),
                coarse.material(1.0, None),
                model.actuator,
            )?,
            options.device,
        )?;
        let positions = to_f32(&coarse.body.particles);
        let mut session = Self {
            hands: initial_hands(&coarse.body.particles, &view),
            coarse,
            world,
            device: options.device,
            material,
            positions,
            sim_ms: 0.0,
            frame: 0,
            recording: None,
            last_error: None,
            view,
            model,
            splats: None,
        };
        session.rebuild_world(false)?;
        Ok(session)
    }

    /// Moves fitted splats (bound to the model's first-frame particles)
    /// with the particles from now on; the page draws them instead of the
    /// particles.
    pub fn attach_splats(&mut self, gaussians: Gaussians<f32>) -> Result<(), PlayError> {
        let mut follower = SplatFollower::new(gaussians.clone(), &self.coarse.body.particles)?;
        if self.frame() > 0 {
            follower.advance(&self.positions)?;
        }
        self.splats = Some((gaussians, follower));
        Ok(())
    }

    /// The sprites the page draws (splats when attached, else particles).
    pub fn sprites(&self) -> Sprites {
        match &self.splats {
            Some((gaussians, _)) => Sprites::splats(&self.coarse.body, gaussians),
            None => Sprites::particles(&self.coarse.body),
        }
    }

    /// The splats where they are now (`None`: the model has none).
    pub fn splats(&self) -> Option<&Gaussians<f32>> {
        self.splats
            .as_ref()
            .map(|(_, follower)| follower.gaussians())
    }

    /// Sprite centres now, flat xyz (splat means or particle positions).
    pub fn sprite_positions(&self) -> Vec<f32> {
        match &self.splats {
            Some((_, follower)) => follower
                .gaussians()
                .means
                .iter()
                .flat_map(|m| [m.x, m.y, m.z])
                .collect(),
            None => self.positions.iter().flatten().copied().collect(),
        }
    }

    pub fn model(&self) -> &WorldModel {
        &self.model
    }

    /// The simulated particles.
    pub fn body(&self) -> &Body {
        &self.coarse.body
    }

    pub fn view(&self) -> &SceneView {
        &self.view
    }

    pub fn positions(&self) -> &[[f32; 3]] {
        &self.positions
    }

    pub fn hands(&self) -> &[Hand; HAND_COUNT] {
        &self.hands
    }

    pub fn material(&self) -> MaterialControl {
        self.material
    }

    pub fn sim_ms(&self) -> f64 {
        self.sim_ms
    }

    pub fn frame(&self) -> usize {
        self.frame
    }

    /// Simulated seconds per frame.
    pub fn frame_dt(&self) -> f64 {
        self.coarse.physics.dt * self.coarse.physics.substeps_per_frame as f64
    }

    /// Per-particle material of the current control.
    fn particle_material(&self) -> ParticleMaterial<f32> {
        let mut m = self
            .coarse
            .material(self.material.e_scale, self.material.nu);
        self.model.options.experts.apply_to(&mut m);
        m
    }

    /// Fitted Young's modulus of every simulated particle (Pa, before the scale).
    pub fn fitted_youngs(&self) -> &[f64] {
        &self.coarse.youngs
    }

    /// Index of the largest expert weight per particle.
    pub fn dominant_expert(&self) -> Vec<u8> {
        self.coarse
            .expert_weights
            .iter()
            .map(|w| {
                let mut best = 0;
                for k in 1..3 {
                    if w[k] > w[best] {
                        best = k;
                    }
                }
                best as u8
            })
            .collect()
    }

    /// A new world with the current material, damping and physics; with
    /// `keep_state` it continues from the current particle state (grasps
    /// are captured again at the next frame from the attached hands).
    fn rebuild_world(&mut self, keep_state: bool) -> Result<(), PlayError> {
        let mut physics = self.coarse.physics.clone();
        physics.particle_damping = self.material.damping;
        let state = if keep_state {
            Some(self.world.state()?)
        } else {
            None
        };
        let mut world = self.coarse.world(
            physics,
            self.particle_material(),
            playground_grasp(&self.model, &self.view),
        )?;
        if let Some(state) = state {
            world.set_state(&state)?;
        }
        self.world = DeviceWorld::new(world, self.device)?;
        Ok(())
    }

    /// Sets the material and damping (clamped to the slider ranges).
    pub fn set_material(&mut self, control: MaterialControl) -> Result<(), PlayError> {
        let finite = control.e_scale.is_finite()
            && control.damping.is_finite()
            && control.nu.is_none_or(f64::is_finite);
        if !finite {
            return Err(PlayError::InvalidCommand(
                "material values must be finite".into(),
            ));
        }
        self.material = MaterialControl {
            e_scale: control.e_scale.clamp(E_SCALE_RANGE[0], E_SCALE_RANGE[1]),
            nu: control.nu.map(|nu| nu.clamp(NU_RANGE[0], NU_RANGE[1])),
            damping: control.damping.clamp(DAMPING_RANGE[0], DAMPING_RANGE[1]),
        };
        self.rebuild_world(true)
    }

    /// Sets the commanded velocity of `hand` (m/s, clamped in speed).
    pub fn set_hand_velocity(&mut self, hand: usize, velocity: [f64; 3]) -> Result<(), PlayError> {
        let h = self.hand_mut(hand)?;
        if velocity.iter().any(|c| !c.is_finite()) {
            return Err(PlayError::InvalidCommand(
                "hand velocity must be finite".into(),
            ));
        }
        let speed = velocity.iter().map(|c| c * c).sum::<f64>().sqrt();
        let scale = if speed > MAX_HAND_SPEED {
            MAX_HAND_SPEED / speed
        } else {
            1.0
        };
        h.velocity = velocity.map(|c| c * scale);
        Ok(())
    }

    fn hand_mut(&mut self, hand: usize) -> Result<&mut Hand, PlayError> {
        self.hands
            .get_mut(hand)
            .ok_or_else(|| PlayError::InvalidCommand(format!("no hand {hand} (0 or 1)")))
    }

    /// The particle a ray from `origin` along `direction` hits first: the
    /// nearest along the ray among those within `pick_radius` of it, or
    /// `None` when the ray misses the object.
    pub fn pick(&self, origin: [f64; 3], direction: [f64; 3]) -> Option<usize> {
        let norm = direction.iter().map(|c| c * c).sum::<f64>().sqrt();
        if !(norm > 0.0 && norm.is_finite()) || origin.iter().any(|c| !c.is_finite()) {
            return None;
        }
        let d = direction.map(|c| c / norm);
        let radius = 1.5 * self.view.particle_spacing;
        let mut best: Option<(f64, usize)> = None;
        for (i, p) in self.positions.iter().enumerate() {
            let rel = [0, 1, 2].map(|a| f64::from(p[a]) - origin[a]);
            let along = rel[0] * d[0] + rel[1] * d[1] + rel[2] * d[2];
            if along <= 0.0 {
                continue;
            }
            let off2 = rel.iter().map(|c| c * c).sum::<f64>() - along * along;
            if off2 <= radius * radius && best.is_none_or(|(b, _)| along < b) {
                best = Some((along, i));
            }
        }
        best.map(|(_, i)| i)
    }

    /// Attaches `hand` at particle `particle`: the hand jumps there and
    /// grasps the particles within the grasp radius at the next frame
    /// (a hand already holding lets go first).
    pub fn grab(&mut self, hand: usize, particle: usize) -> Result<(), PlayError> {
        let p = *self
            .positions
            .get(particle)
            .ok_or_else(|| PlayError::InvalidCommand(format!("no particle {particle}")))?;
        let was_attached = self.hand_mut(hand)?.attached;
        let h = self.hand_mut(hand)?;
        h.position = p.map(f64::from);
        h.velocity = [0.0; 3];
        h.attached = true;
        if was_attached {
            self.rebuild_world(true)?;
        }
        Ok(())
    }

    /// Lets go of the object with `hand`.
    pub fn release(&mut self, hand: usize) -> Result<(), PlayError> {
        let h = self.hand_mut(hand)?;
        if h.attached {
            h.attached = false;
            h.velocity = [0.0; 3];
            self.rebuild_world(true)?;
        }
        Ok(())
    }

    /// Back to the first frame: particles at rest, hands released; the
    /// material control is kept.
    pub fn reset(&mut self) -> Result<(), PlayError> {
        self.hands = initial_hands(&self.coarse.body.particles, &self.view);
        self.positions = to_f32(&self.coarse.body.particles);
        if let Some((gaussians, follower)) = &mut self.splats {
            *follower = SplatFollower::new(gaussians.clone(), &self.coarse.body.particles)?;
        }
        self.recording = None;
        self.frame = 0;
        self.rebuild_world(false)
    }

    /// Advances one frame: hands move by their velocity (kept inside the
    /// domain), the attached ones grasp, the world steps. A diverged
    /// simulation is reported and the session reset.
    pub fn step(&mut self) -> Result<(), PlayError> {
        let clock = Instant::now();
        let dt = self.frame_dt();
        let (lo, hi) = self.view.hand_box;
        let from: Vec<[f64; 3]> = self.hands.iter().map(|h| h.position).collect();
        for h in &mut self.hands {
            for a in 0..3 {
                h.position[a] = (h.position[a] + h.velocity[a] * dt).clamp(lo[a], hi[a]);
            }
        }
        let to: Vec<[f64; 3]> = self.hands.iter().map(|h| h.position).collect();
        let active: Vec<bool> = self.hands.iter().map(|h| h.attached).collect();
        if let Err(error) = self.world.step_frame(&from, &to, &active) {
            let message = format!(
                "simulation diverged ({error}); reset to the first frame — lower the pull speed or raise E"
            );
            self.last_error = Some(message.clone());
            self.reset()?;
            return Err(PlayError::Diverged(message));
        }
        self.frame += 1;
        self.positions = self
            .world
            .positions()?
            .iter()
            .map(|p| p.map(|c| c as f32))
            .collect();
        if let Some((_, follower)) = &mut self.splats {
            follower.advance(&self.positions)?;
        }
        if let Some(recording) = &mut self.recording {
            recording.positions.push(self.positions.clone());
            recording.hands.push(self.hands.map(|h| h.position));
        }
        self.sim_ms = clock.elapsed().as_secs_f64() * 1e3;
        Ok(())
    }

    /// Starts recording from the current frame (which becomes the recorded
    /// bundle's first frame).
    pub fn start_recording(&mut self) {
        self.recording = Some(Recording {
            positions: vec![self.positions.clone()],
            hands: vec![self.hands.map(|h| h.position)],
        });
    }

    /// Stops recording and hands over what was recorded.
    pub fn take_recording(&mut self) -> Option<Recording> {
        self.recording.take()
    }

    /// Particles tied to each hand now.
    pub fn grasped_particles(&self) -> Vec<usize> {
        let actuators = self.world.actuators();
        let mut counts = vec![0; HAND_COUNT];
        for p in 0..self.world.particle_count() {
            let mut seen = [false; HAND_COUNT];
            for (anchor, _) in actuators.couplings_of(p) {
                if anchor < HAND_COUNT && !seen[anchor] {
                    seen[anchor] = true;
                    counts[anchor] += 1;
                }
            }
        }
        counts
    }

    pub fn state(&self) -> SessionState {
        let n = self.positions.len().max(1) as f64;
        let centroid =
            [0, 1, 2].map(|a| self.positions.iter().map(|p| f64::from(p[a])).sum::<f64>() / n);
        SessionState {
            frame: self.frame(),
            particle_count: self.positions.len(),
            centroid,
            hands: self.hands.to_vec(),
            grasped_particles: self.grasped_particles(),
            material: self.material,
            sim_ms: self.sim_ms,
            substeps_per_frame: self.world.config().substeps_per_frame,
            grid: self.world.config().grid_res,
            frame_dt: self.frame_dt(),
            recording_frames: self.recording.as_ref().map(|r| r.positions.len()),
            last_error: self.last_error.clone(),
        }
    }
}

/// Hands parked above the object, left and right of its centre.
/// Grasp radius of the playground's hands, in particle spacings: a click
/// holds a small patch of the object, not a single particle.
pub const GRASP_SPACINGS: f64 = 5.0;

/// The playground's hands hold rigidly (the Dirichlet mode of the `rigid`
/// ablation) over at least [`GRASP_SPACINGS`] particle spacings. The fitted
/// DCA gains describe a human grasp over tens of tracked anchors; one
/// clicked point ties about 20 particles, whose spring forces at the fitted
/// k_p cannot carry the object's weight (measured: the hand rose 12 cm, the
/// object 0.8 mm).
fn playground_grasp(model: &WorldModel, view: &SceneView) -> ActuatorConfig {
    ActuatorConfig {
        mode: ActuatorMode::Rigid,
        grasp_radius: model
            .actuator
            .grasp_radius
            .max(GRASP_SPACINGS * view.particle_spacing),
        ..model.actuator
    }
}

fn initial_hands(particles: &[[f64; 3]], view: &SceneView) -> [Hand; HAND_COUNT] {
    let (lo, hi) = bounds(particles);
    let up = view.up;
    let centre = [0, 1, 2].map(|a| 0.5 * (lo[a] + hi[a]));
    let size = view.extent;
    let side = view.main_right();
    let mut hands = [Hand {
        position: centre,
        velocity: [0.0; 3],
        attached: false,
    }; HAND_COUNT];
    for (k, h) in hands.iter_mut().enumerate() {
        let sign = if k == 0 { -1.0 } else { 1.0 };
        h.position =
            [0, 1, 2].map(|a| centre[a] + up[a] * 0.6 * size + side[a] * sign * 0.3 * size);
    }
    hands
}

/// A cube domain for `grid` cells around the object with room for the
/// hands (half the object's extent on every side, the floor included).
fn playground_domain(physics: &mut PhysicsConfig, particles: &[[f64; 3]], grid: usize) {
    let (mut lo, mut hi) = bounds(particles);
    let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
    for a in 0..3 {
        lo[a] -= 0.5 * extent;
        hi[a] += 0.5 * extent;
    }
    if let Some(floor) = &physics.floor {
        for a in 0..3 {
            if floor.up[a] != 0.0 {
                let f = floor.height * floor.up[a];
                lo[a] = lo[a].min(f - 0.02 * floor.up[a].abs());
                hi[a] = hi[a].max(f + 0.02 * floor.up[a].abs());
            }
        }
    }
    // Particles stay 2 cells inside the domain (the stencil needs 1.5).
    let clip = physics.position_clip[0].max(2.0 / grid as f64);
    physics.position_clip = [clip, 1.0 - clip];
    let (origin, size) = dm_mpm::domain::cube_domain_containing(
        lo,
        hi,
        grid,
        physics.wall_cells,
        physics.position_clip,
    );
    let old_dx = physics.dx();
    physics.grid_res = grid;
    physics.domain_origin = origin;
    physics.domain_size = size;
    if let Some(floor) = physics.floor.as_mut() {
        // The collision layer keeps its size in cells.
        floor.margin *= physics.domain_size / grid as f64 / old_dx;
    }
}

/// Axis-aligned bounds of points.
pub fn bounds(points: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    (lo, hi)
}

fn to_f32(points: &[[f64; 3]]) -> Vec<[f32; 3]> {
    points.iter().map(|p| p.map(|c| c as f32)).collect()
}

/// Connected components of the particles' neighbourhood graph: particles
/// closer than `link` are joined. A torn object has more than one large
/// component; components smaller than `min_size` (stray particles) are not
/// counted.
pub fn component_sizes(positions: &[[f32; 3]], link: f64, min_size: usize) -> Vec<usize> {
    let points: Vec<[f64; 3]> = positions.iter().map(|p| p.map(f64::from)).collect();
    let index = PointIndex::new(&points);
    let mut parent: Vec<usize> = (0..points.len()).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    for (i, p) in points.iter().enumerate() {
        for (j, _) in index.within(p, link) {
            let (a, b) = (root(&mut parent, i), root(&mut parent, j));
            if a != b {
                parent[a.max(b)] = a.min(b);
            }
        }
    }
    let mut sizes = std::collections::BTreeMap::<usize, usize>::new();
    for i in 0..points.len() {
        *sizes.entry(root(&mut parent, i)).or_default() += 1;
    }
    let mut out: Vec<usize> = sizes.into_values().filter(|&s| s >= min_size).collect();
    out.sort_unstable_by(|a, b| b.cmp(a));
    out
}

#[cfg(all(test, feature = "cli"))]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        options: PlayOptions,
    }

    fn parse(args: &[&str]) -> PlayOptions {
        Cli::try_parse_from(std::iter::once("dm-play").chain(args.iter().copied()))
            .expect("the flags parse")
            .options
    }

    #[test]
    fn the_command_line_defaults_are_the_interactive_options_or_the_models() {
        assert_eq!(parse(&[]), PlayOptions::interactive());
        assert_eq!(
            parse(&["--grid", "12", "--device", "cpu"]),
            PlayOptions {
                grid: Some(12),
                ..PlayOptions::interactive()
            }
        );
        assert_eq!(
            parse(&["--exact"]),
            PlayOptions {
                exact: true,
                ..PlayOptions::default()
            }
        );
        assert_eq!(
            parse(&["--exact", "--substeps", "4", "--cfl", "0.3"]),
            PlayOptions {
                substeps: Some(4),
                cfl: Some(0.3),
                exact: true,
                ..PlayOptions::default()
            }
        );
        assert!(Cli::try_parse_from(["dm-play", "--exact", "--grid", "12"]).is_err());
    }
}
