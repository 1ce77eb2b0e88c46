//! The MPM world: owns the state and runs substeps and video frames.
//!
//! Particles are stored in a spatially coherent slot order (sorted by grid
//! block at construction) for cache locality; every public accessor speaks
//! in the caller's particle order.

use crate::SimError;
use crate::actuators::{ActuatorConfig, ActuatorMode, Actuators, Grip};
use crate::config::PhysicsConfig;
use crate::material::ParticleMaterial;
use crate::real::{Mat3, Real, Vec3, vec3};
use crate::state::{Consts, Particles};
use crate::substep::{StageSeconds, SubstepInputs, SubstepScratch, substep_forward};
use crate::tape::FrameTape;

/// Refuse materials that would need more substeps per frame than this.
pub const MAX_SUBSTEPS_PER_FRAME: usize = 4096;

#[derive(Debug)]
pub struct World<T: Real> {
    config: PhysicsConfig,
    pub(crate) consts: Consts<T>,
    pub(crate) particles: Particles<T>,
    pub(crate) material: ParticleMaterial<T>,
    pub(crate) pure_neo_hookean: bool,
    pub(crate) actuators: Actuators<T>,
    anchor_x: Vec<Vec3<T>>,
    anchor_v: Vec<Vec3<T>>,
    pub(crate) scratch: SubstepScratch<T>,
    pub(crate) external_accel: Vec<Vec3<T>>,
    /// `id_of_slot[slot]` = caller's particle index.
    pub(crate) id_of_slot: Vec<u32>,
    frame: usize,
    substep_in_frame: usize,
    /// Seconds spent per stage since construction (for benchmarks).
    pub stage_seconds: StageSeconds,
}

/// The same world with scratch buffers of its own (they hold nothing
/// between substeps), as a world built the same way would be.
impl<T: Real> Clone for World<T> {
    fn clone(&self) -> Self {
        Self {
            config: self.config.clone(),
            consts: self.consts,
            particles: self.particles.clone(),
            material: self.material.clone(),
            pure_neo_hookean: self.pure_neo_hookean,
            actuators: self.actuators.clone(),
            anchor_x: self.anchor_x.clone(),
            anchor_v: self.anchor_v.clone(),
            scratch: SubstepScratch::new(self.config.grid_res),
            external_accel: self.external_accel.clone(),
            id_of_slot: self.id_of_slot.clone(),
            frame: self.frame,
            substep_in_frame: self.substep_in_frame,
            stage_seconds: self.stage_seconds,
        }
    }
}

impl<T: Real> World<T> {
    /// A world of particles at rest at `positions`, each of volume
    /// `particle_volume` (m³), with the given per-particle material.
    pub fn new(
        config: PhysicsConfig,
        positions: &[[f64; 3]],
        particle_volume: f64,
        material: ParticleMaterial<T>,
        actuators: ActuatorConfig,
    ) -> Result<Self, SimError> {
        config.validate()?;
        let n = positions.len();
        if n == 0 {
            return Err(SimError::InvalidInput("no particles".into()));
        }
        if material.len() != n || material.lambda.len() != n || material.expert_weights.len() != n {
            return Err(SimError::InvalidInput(format!(
                "material has {} entries for {} particles",
                material.len(),
                n
            )));
        }
        if let Some(i) = positions
            .iter()
            .position(|p| p.iter().any(|c| !c.is_finite()))
        {
            return Err(SimError::InvalidInput(format!(
                "particle {i} position is not finite"
            )));
        }
        if !(particle_volume.is_finite() && particle_volume > 0.0) {
            return Err(SimError::InvalidInput(
                "particle volume must be positive".into(),
            ));
        }
        // Refine the substep if the stiffest particle's P-wave would outrun it.
        let max_modulus = material
            .mu
            .iter()
            .zip(&material.lambda)
            .map(|(&mu, &la)| (la + mu + mu).to_f64())
            .fold(0.0, f64::max);
        let mut config = config;
        let (substeps, dt) = config.stable_substeps((max_modulus / config.density).sqrt());
        if substeps > MAX_SUBSTEPS_PER_FRAME {
            return Err(SimError::InvalidConfig {
                field: "dt".into(),
                problem: format!(
                    "the stiffest material (P-wave modulus {max_modulus:.3e} Pa) needs {substeps} \
                     substeps per frame at this grid for stability (more than {MAX_SUBSTEPS_PER_FRAME}); \
                     lower E or coarsen the grid"
                ),
            });
        }
        config.substeps_per_frame = substeps;
        config.dt = dt;
        let consts = Consts::new(&config, particle_volume * config.density);
        let xs: Vec<Vec3<T>> = positions.iter().map(|&p| vec3(p)).collect();
        let mut world = Self {
            particles: Particles::at_rest(&xs, T::lit(particle_volume), T::lit(config.density)),
            pure_neo_hookean: material.is_pure_neo_hookean(),
            material,
            actuators: Actuators::new(actuators, n),
            anchor_x: Vec::new(),
            anchor_v: Vec::new(),
            scratch: SubstepScratch::new(config.grid_res),
            external_accel: Vec::new(),
            id_of_slot: (0..n as u32).collect(),
            frame: 0,
            substep_in_frame: 0,
            stage_seconds: StageSeconds::default(),
            consts,
            config,
        };
        world.sort_particles_spatially();
        Ok(world)
    }

    fn sort_particles_spatially(&mut self) {
        self.scratch
            .schedule
            .rebuild(&self.particles.x, &self.consts);
        let order = self.scratch.schedule.order().to_vec();
        self.particles.permute(&order);
        let m = &mut self.material;
        m.mu = order.iter().map(|&i| m.mu[i as usize]).collect();
        m.lambda = order.iter().map(|&i| m.lambda[i as usize]).collect();
        m.expert_weights = order
            .iter()
            .map(|&i| m.expert_weights[i as usize])
            .collect();
        self.actuators.permute(&order);
        self.id_of_slot = order.iter().map(|&i| self.id_of_slot[i as usize]).collect();
    }

    /// The configuration in force (with the substep actually used).
    pub fn config(&self) -> &PhysicsConfig {
        &self.config
    }

    pub fn particle_count(&self) -> usize {
        self.particles.len()
    }

    pub fn frame(&self) -> usize {
        self.frame
    }

    pub fn actuators(&self) -> &Actuators<T> {
        &self.actuators
    }

    /// Replaces the material (caller's particle order).
    pub fn set_material(&mut self, material: ParticleMaterial<T>) -> Result<(), SimError> {
        let n = self.particle_count();
        if material.len() != n || material.lambda.len() != n || material.expert_weights.len() != n {
            return Err(SimError::InvalidInput(
                "material size does not match particles".into(),
            ));
        }
        let ids = &self.id_of_slot;
        self.pure_neo_hookean = material.is_pure_neo_hookean();
        self.material = ParticleMaterial {
            mu: ids.iter().map(|&i| material.mu[i as usize]).collect(),
            lambda: ids.iter().map(|&i| material.lambda[i as usize]).collect(),
            expert_weights: ids
                .iter()
                .map(|&i| material.expert_weights[i as usize])
                .collect(),
        };
        Ok(())
    }

    /// Reorders values given in slot order into the caller's order.
    pub fn to_caller_order<V: Copy + Default>(&self, values: &[V]) -> Vec<V> {
        let mut out = vec![V::default(); values.len()];
        for (slot, &id) in self.id_of_slot.iter().enumerate() {
            out[id as usize] = values[slot];
        }
        out
    }

    /// Reorders values given in the caller's particle order into slots.
    pub fn to_slot_order<V: Copy>(&self, values: &[V]) -> Vec<V> {
        self.id_of_slot
            .iter()
            .map(|&id| values[id as usize])
            .collect()
    }

    /// The full particle state in the caller's order (for checkpoints and
    /// gradient checks).
    pub fn state(&self) -> Particles<T> {
        let p = &self.particles;
        Particles {
            x: self.to_caller_order(&p.x),
            v: self.to_caller_order(&p.v),
            f: self.to_caller_order(&p.f),
            c: self.to_caller_order(&p.c),
            mass: self.to_caller_order(&p.mass),
            volume: self.to_caller_order(&p.volume),
        }
    }

    /// Replaces the particle state (caller's order, same particle count).
    pub fn set_state(&mut self, state: &Particles<T>) -> Result<(), SimError> {
        if state.len() != self.particle_count() {
            return Err(SimError::InvalidInput(
                "state size does not match particles".into(),
            ));
        }
        self.particles = Particles {
            x: self.to_slot_order(&state.x),
            v: self.to_slot_order(&state.v),
            f: self.to_slot_order(&state.f),
            c: self.to_slot_order(&state.c),
            mass: self.to_slot_order(&state.mass),
            volume: self.to_slot_order(&state.volume),
        };
        Ok(())
    }

    /// Scales each particle's mass (caller's order) by `factors[i]` relative
    /// to `volume × config.density`: a density varying across the object.
    /// The CFL substep was chosen for `config.density`, so factors below 1
    /// (lighter, faster waves) are refused.
    pub fn set_density_factors(&mut self, factors: &[f64]) -> Result<(), SimError> {
        if factors.len() != self.particle_count() {
            return Err(SimError::InvalidInput(
                "density factor count does not match particles".into(),
            ));
        }
        if let Some(i) = factors.iter().position(|f| !(f.is_finite() && *f >= 1.0)) {
            return Err(SimError::InvalidInput(format!(
                "density factor of particle {i} must be finite and at least 1 \
                 (lower config.density instead)"
            )));
        }
        let density = self.config.density;
        for (slot, &id) in self.id_of_slot.iter().enumerate() {
            let volume = self.particles.volume[slot].to_f64();
            self.particles.mass[slot] = T::lit(volume * density * factors[id as usize]);
        }
        Ok(())
    }

    /// Sets the extra physics (drag, friction, plasticity, viscosity) in
    /// force from the next substep.
    pub fn set_effects(&mut self, effects: crate::Effects) -> Result<(), SimError> {
        self.change_config(|config| config.effects = effects)
    }

    /// Sets gravity (m/s², world frame) from the next substep.
    pub fn set_gravity(&mut self, gravity: [f64; 3]) -> Result<(), SimError> {
        self.change_config(|config| config.gravity = gravity)
    }

    /// Sets the particle damping rate (1/s) from the next substep.
    pub fn set_particle_damping(&mut self, rate: f64) -> Result<(), SimError> {
        self.change_config(|config| config.particle_damping = rate)
    }

    /// `change` applied to a copy of the config, which then replaces it.
    fn change_config(&mut self, change: impl FnOnce(&mut PhysicsConfig)) -> Result<(), SimError> {
        let mut config = self.config.clone();
        change(&mut config);
        self.replace_config(config)
    }

    /// Validates `config` and rebuilds the substep constants from it.
    fn replace_config(&mut self, config: PhysicsConfig) -> Result<(), SimError> {
        config.validate()?;
        let particle_volume = self.particles.volume.first().map_or(0.0, |v| v.to_f64());
        self.consts = Consts::new(&config, particle_volume * config.density);
        self.config = config;
        Ok(())
    }

    /// Sets the actuator gains (k_p in 1/s², k_d in 1/s).
    pub fn set_gains(&mut self, kp: f64, kd: f64) {
        self.actuators.config.kp = kp;
        self.actuators.config.kd = kd;
    }

    /// The hands' hold on the caller's particles `particles`, in that order.
    pub fn grip(&self, particles: &[usize]) -> Result<Grip, SimError> {
        let n = self.particle_count();
        let mut slot_of = vec![0usize; n];
        for (slot, &id) in self.id_of_slot.iter().enumerate() {
            slot_of[id as usize] = slot;
        }
        if let Some(bad) = particles.iter().find(|&&i| i >= n) {
            return Err(SimError::InvalidInput(format!(
                "particle {bad} does not exist; the world has {n}"
            )));
        }
        Ok(self
            .actuators
            .grip_of(particles.iter().map(|&i| slot_of[i])))
    }

    /// Replaces the hands' hold on the object by `grip` (one entry per
    /// particle, caller's order): the next frames pull the particles it
    /// couples, and anchors it marks grasped take hold of nothing more.
    pub fn set_grip(&mut self, grip: &Grip) -> Result<(), SimError> {
        if grip.couplings.len() != self.particle_count() {
            return Err(SimError::InvalidInput(format!(
                "a grip of {} particles for a world of {}",
                grip.couplings.len(),
                self.particle_count()
            )));
        }
        let finite =
            grip.couplings.iter().flatten().all(|c| {
                c.capture_distance.is_finite() && c.rest_offset.iter().all(|v| v.is_finite())
            });
        if !finite {
            return Err(SimError::InvalidInput(
                "a grip's offsets are not finite".into(),
            ));
        }
        self.actuators.set_grip(grip, &self.id_of_slot);
        Ok(())
    }

    /// Lets go of the object: every coupling to a hand anchor is dropped,
    /// and the next frame's active anchors grasp afresh.
    pub fn release_grasps(&mut self) {
        self.actuators = Actuators::new(self.actuators.config, self.particle_count());
    }

    /// Positions in the caller's particle order, metres.
    pub fn positions(&self) -> Vec<[f64; 3]> {
        self.to_caller_order(&self.particles.x)
            .iter()
            .map(|p| [p.x.to_f64(), p.y.to_f64(), p.z.to_f64()])
            .collect()
    }

    pub fn velocities(&self) -> Vec<[f64; 3]> {
        self.to_caller_order(&self.particles.v)
            .iter()
            .map(|p| [p.x.to_f64(), p.y.to_f64(), p.z.to_f64()])
            .collect()
    }

    pub fn deformation_gradients(&self) -> Vec<Mat3<T>> {
        self.to_caller_order(&self.particles.f)
    }

    /// Sets all velocities (caller's order), e.g. an initial throw.
    pub fn set_velocities(&mut self, v: &[[f64; 3]]) -> Result<(), SimError> {
        if v.len() != self.particle_count() {
            return Err(SimError::InvalidInput(
                "velocity count does not match particles".into(),
            ));
        }
        for (slot, &id) in self.id_of_slot.iter().enumerate() {
            self.particles.v[slot] = vec3(v[id as usize]);
        }
        Ok(())
    }

    /// Total linear momentum, kg m/s.
    pub fn total_momentum(&self) -> [f64; 3] {
        let mut sum = [0.0; 3];
        for (v, m) in self.particles.v.iter().zip(&self.particles.mass) {
            for a in 0..3 {
                sum[a] += v[a].to_f64() * m.to_f64();
            }
        }
        sum
    }

    /// Total kinetic energy, J.
    pub fn kinetic_energy(&self) -> f64 {
        self.particles
            .v
            .iter()
            .zip(&self.particles.mass)
            .map(|(v, m)| 0.5 * m.to_f64() * v.norm_squared().to_f64())
            .sum()
    }

    /// One MPM substep with the anchors where they are now.
    pub fn substep(&mut self) -> Result<(), SimError> {
        on_worker(|| self.substep_here())
    }

    fn substep_here(&mut self) -> Result<(), SimError> {
        let k = self.consts;
        let clock = std::time::Instant::now();
        let has_actuators = self.update_external_accel();
        self.stage_seconds.actuators += clock.elapsed().as_secs_f64();
        let inputs = SubstepInputs {
            material: &self.material,
            pure_neo_hookean: self.pure_neo_hookean,
            external_accel: has_actuators.then_some(&self.external_accel[..]),
        };
        substep_forward(
            &k,
            &inputs,
            &mut self.particles,
            &mut self.scratch,
            Some(&mut self.stage_seconds),
        )
        .map_err(|failure| SimError::Diverged {
            frame: self.frame,
            substep: self.substep_in_frame,
            particle: self.id_of_slot[failure.slot] as usize,
            reason: failure.reason.to_string(),
        })?;
        if has_actuators && self.actuators.config.mode == ActuatorMode::Rigid {
            let anchor_end = self.anchors_at_substep_end();
            self.actuators.enforce_rigid(
                &mut self.particles.x,
                &mut self.particles.v,
                &anchor_end,
                &self.anchor_v,
            );
        }
        self.substep_in_frame += 1;
        Ok(())
    }

    /// Actuator accelerations for the current state and anchors; false when
    /// no particle is coupled (the buffer is then unused).
    fn update_external_accel(&mut self) -> bool {
        if self.actuators.coupling_count() == 0 {
            return false;
        }
        self.external_accel
            .resize(self.particle_count(), Vec3::zeros());
        self.actuators.accelerations(
            &self.particles.x,
            &self.particles.v,
            &self.anchor_x,
            &self.anchor_v,
            &mut self.external_accel,
        );
        true
    }

    /// Anchor positions at the end of the current substep (rigid mode places
    /// particles there, since G2P already advanced them to that time).
    fn anchors_at_substep_end(&self) -> Vec<Vec3<T>> {
        self.anchor_x
            .iter()
            .zip(&self.anchor_v)
            .map(|(x, v)| x + v * self.consts.dt)
            .collect()
    }

    /// Advances one video frame while the anchors move linearly from
    /// `anchors_from` to `anchors_to`. `active` marks anchors allowed to
    /// grasp (their grasp is captured at the start of the frame).
    pub fn step_frame(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        active: &[bool],
    ) -> Result<(), SimError> {
        self.advance_frame(anchors_from, anchors_to, active, FrameRun::Whole)
            .map(|_| ())
    }

    /// Like [`World::step_frame`], returning the state (as
    /// [`World::state`]) entering the frame's substep `at` (the state after
    /// the frame when `at` is the frame's substep count or more): where
    /// [`World::step_frame_rest_taped`] picks the frame up again.
    pub fn step_frame_keeping(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        active: &[bool],
        at: usize,
    ) -> Result<Particles<T>, SimError> {
        let kept = self.advance_frame(anchors_from, anchors_to, active, FrameRun::Keeping(at))?;
        Ok(kept.unwrap_or_else(|| self.state()))
    }

    /// Like [`World::step_frame`], recording what the backward pass needs
    /// for the last `window` substeps of the frame (all of them when
    /// `window >= substeps_per_frame`).
    pub fn step_frame_taped(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        active: &[bool],
        window: usize,
    ) -> Result<FrameTape<T>, SimError> {
        self.taped_frame(anchors_from, anchors_to, active, window, false)
    }

    /// The last `window` substeps of a frame, taped, from the state entering
    /// them ([`World::step_frame_keeping`]'s at `substeps_per_frame -
    /// window`, restored with [`World::set_state`]): the tape and the state
    /// after are [`World::step_frame_taped`]'s from the frame's start,
    /// without running the frame's first substeps again. It grasps nothing:
    /// the frame's grasps are the ones its first run made (a grasp is
    /// never undone).
    pub fn step_frame_rest_taped(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        window: usize,
    ) -> Result<FrameTape<T>, SimError> {
        let no_grasp = vec![false; anchors_from.len()];
        self.taped_frame(anchors_from, anchors_to, &no_grasp, window, true)
    }

    /// A frame with its last `window` substeps taped: all of it, or only
    /// those substeps (`rest_only`).
    fn taped_frame(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        active: &[bool],
        window: usize,
        rest_only: bool,
    ) -> Result<FrameTape<T>, SimError> {
        let steps = self.config.substeps_per_frame;
        let mut tape = FrameTape::new(window.min(steps), self.consts.res);
        let first = if rest_only { steps - tape.window } else { 0 };
        let run = FrameRun::Taped(&mut tape, first);
        self.advance_frame(anchors_from, anchors_to, active, run)?;
        Ok(tape)
    }

    pub(crate) fn advance_frame(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        active: &[bool],
        run: FrameRun<'_, T>,
    ) -> Result<Option<Particles<T>>, SimError> {
        on_worker(|| self.advance_frame_here(anchors_from, anchors_to, active, run))
    }

    fn advance_frame_here(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        active: &[bool],
        run: FrameRun<'_, T>,
    ) -> Result<Option<Particles<T>>, SimError> {
        let path = self.begin_frame(anchors_from, anchors_to, active, None)?;
        self.anchor_v = path.velocity.clone();
        let steps = self.config.substeps_per_frame;
        let (mut tape, first, keep_at) = match run {
            FrameRun::Whole => (None, 0, None),
            FrameRun::Keeping(at) => (None, 0, Some(at)),
            FrameRun::Taped(tape, first) => (Some(tape), first, None),
        };
        let mut kept = None;
        self.substep_in_frame = first;
        for s in first..steps {
            if keep_at == Some(s) {
                kept = Some(self.state());
            }
            self.anchor_x = path.at_substep(s);
            // A taped substep also keeps its post-P2G grid and bucketing
            // for the backward pass when the tape's memory budget allows.
            let mut taped = tape.as_deref_mut().filter(|tape| s + tape.window >= steps);
            if let Some(tape) = taped.as_deref_mut() {
                tape.record(&self.particles, &self.anchor_x, &self.anchor_v);
                self.scratch.keep_pre_grid = tape.stores_grids();
            }
            let result = self.substep_here();
            self.scratch.keep_pre_grid = false;
            result?;
            if let Some(tape) = taped
                && tape.stores_grids()
            {
                tape.record_cache(self.scratch.take_cache());
            }
        }
        self.frame += 1;
        Ok(kept)
    }

    /// Checks a frame's anchors, lets active anchors grasp (at
    /// `positions`, slot order; the world's own when `None`) and returns
    /// where the anchors are during the frame.
    pub fn begin_frame(
        &mut self,
        anchors_from: &[[f64; 3]],
        anchors_to: &[[f64; 3]],
        active: &[bool],
        positions: Option<&[Vec3<T>]>,
    ) -> Result<AnchorPath<T>, SimError> {
        let m = anchors_from.len();
        if anchors_to.len() != m || active.len() != m {
            return Err(SimError::InvalidInput(
                "anchor arrays differ in length".into(),
            ));
        }
        if anchors_from
            .iter()
            .chain(anchors_to)
            .any(|p| p.iter().any(|c| !c.is_finite()))
        {
            return Err(SimError::InvalidInput(format!(
                "anchor positions for frame {} are not finite",
                self.frame
            )));
        }
        let needed = self.actuators.anchors_needed();
        if m < needed {
            return Err(SimError::InvalidInput(format!(
                "frame {} has {m} anchors but particles are grasped by anchor {}",
                self.frame,
                needed - 1
            )));
        }
        let steps = self.config.substeps_per_frame;
        let frame_dt = self.config.dt * steps as f64;
        let from: Vec<Vec3<T>> = anchors_from.iter().map(|&p| vec3(p)).collect();
        let x = positions.unwrap_or(&self.particles.x);
        self.actuators.grasp(x, &from, active);
        Ok(AnchorPath {
            velocity: anchors_from
                .iter()
                .zip(anchors_to)
                .map(|(a, b)| vec3([0, 1, 2].map(|i| (b[i] - a[i]) / frame_dt)))
                .collect(),
            from: anchors_from.to_vec(),
            to: anchors_to.to_vec(),
            steps,
        })
    }

    /// Counts a frame advanced outside [`World::step_frame`] (by another
    /// backend holding the state).
    pub fn count_frame(&mut self) {
        self.frame += 1;
    }

    /// The substep constants in force.
    pub fn consts(&self) -> &Consts<T> {
        &self.consts
    }

    /// The particle state in slot order (the world's internal order).
    pub fn slot_particles(&self) -> &Particles<T> {
        &self.particles
    }

    /// Mutable particle state in slot order, for a backend writing back
    /// the state it advanced.
    pub fn slot_particles_mut(&mut self) -> &mut Particles<T> {
        &mut self.particles
    }

    /// The material in slot order.
    pub fn slot_material(&self) -> &ParticleMaterial<T> {
        &self.material
    }

    /// Whether every particle is a pure Neo-Hookean one (the fast path).
    pub fn is_pure_neo_hookean(&self) -> bool {
        self.pure_neo_hookean
    }

    /// `id_of_slot[slot]` = the caller's index of the particle in `slot`.
    pub fn id_of_slot(&self) -> &[u32] {
        &self.id_of_slot
    }

    /// Advances one frame with no anchors.
    pub fn step_frame_free(&mut self) -> Result<(), SimError> {
        self.step_frame(&[], &[], &[])
    }
}

/// Where the anchors are during one frame: moving linearly from their
/// positions at its start to those at its end.
#[derive(Clone, Debug)]
pub struct AnchorPath<T> {
    /// Anchor velocities, m/s.
    pub velocity: Vec<Vec3<T>>,
    from: Vec<[f64; 3]>,
    to: Vec<[f64; 3]>,
    steps: usize,
}

impl<T: Real> AnchorPath<T> {
    /// Anchor positions at the start of substep `s`.
    pub fn at_substep(&self, s: usize) -> Vec<Vec3<T>> {
        let t = s as f64 / self.steps as f64;
        self.from
            .iter()
            .zip(&self.to)
            .map(|(a, b)| vec3([0, 1, 2].map(|i| a[i] + (b[i] - a[i]) * t)))
            .collect()
    }
}

/// Runs `op` on a worker of the current rayon pool (directly when already
/// on one). A frame's substeps have a dozen parallel stages each; called
/// from outside the pool, every stage would hand its work to the pool and
/// sleep until it is done (a futex wake and wait per stage), where on a
/// worker the stages fork and join among the workers.
pub fn on_worker<R: Send>(op: impl FnOnce() -> R + Send) -> R {
    if rayon::current_thread_index().is_some() {
        op()
    } else {
        rayon::scope(|_| op())
    }
}

/// What [`World::advance_frame`] does besides stepping the frame.
pub(crate) enum FrameRun<'a, T: Real> {
    Whole,
    /// Keep the state entering this substep.
    Keeping(usize),
    /// Tape the tape's window, running the substeps from this one on.
    Taped(&'a mut FrameTape<T>, usize),
}
