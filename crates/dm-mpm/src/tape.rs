//! Reverse mode over a video frame: the tape of the last W substeps and
//! the frame's backward pass (truncated BPTT, method.md §2).
//!
//! Within a frame, gradients flow exactly through the last `window`
//! substeps. When the window is shorter than the frame, the adjoint at the
//! window's start is passed to the frame's start unchanged (the earlier
//! substeps' Jacobian is taken as the identity): that keeps gradients
//! flowing across frames through the state while bounding the cost, as in
//! the method; a window covering the whole frame gives the exact gradient.
//! Grasp capture (rest offsets) is not differentiated.

use crate::SimError;
use crate::actuators::ActuatorMode;
use crate::actuators_backward::GainGrads;
use crate::config::ForceField;
use crate::g2p_backward::ParticleGrads;
use crate::real::{Real, Vec3};
use crate::state::Particles;
use crate::substep::{SubstepCache, SubstepGrads, SubstepInputs, substep_backward_into};
use crate::world::World;

/// Most bytes a tape may spend on recorded grids, counted at full grid
/// size (the stored box is usually much smaller); beyond it the backward
/// pass recomputes P2G instead (the grids are a cache, not needed for
/// correctness). 256 MiB holds 20 substeps of a 64³ f64 grid.
const TAPE_GRID_BUDGET_BYTES: usize = 256 << 20;

/// What the backward pass of one frame needs.
#[derive(Clone, Debug)]
pub struct FrameTape<T: Real> {
    pub(crate) window: usize,
    /// State entering each recorded substep, in slot order, oldest first.
    states: Vec<Particles<T>>,
    anchor_x: Vec<Vec<Vec3<T>>>,
    anchor_v: Vec<Vec3<T>>,
    /// Grid right after P2G and bucketing of each recorded substep, when
    /// within [`TAPE_GRID_BUDGET_BYTES`]: the backward pass then skips
    /// recomputing them (about a fifth of its time at 10⁴ particles, 32³).
    /// Bitwise what the recomputation gives, so results do not depend on
    /// whether they were stored.
    caches: Vec<SubstepCache<T>>,
    store_grids: bool,
}

impl<T: Real> FrameTape<T> {
    pub(crate) fn new(window: usize, res: usize) -> Self {
        let grid_bytes = res.pow(3) * std::mem::size_of::<T::Lane4>();
        Self {
            window,
            states: Vec::new(),
            anchor_x: Vec::new(),
            anchor_v: Vec::new(),
            caches: Vec::new(),
            store_grids: window.saturating_mul(grid_bytes) <= TAPE_GRID_BUDGET_BYTES,
        }
    }

    /// Whether this tape records each substep's post-P2G grid.
    pub(crate) fn stores_grids(&self) -> bool {
        self.store_grids
    }

    /// Records the forward cache of the substep last passed to `record`.
    pub(crate) fn record_cache(&mut self, cache: SubstepCache<T>) {
        debug_assert_eq!(self.caches.len() + 1, self.states.len());
        self.caches.push(cache);
    }

    pub(crate) fn record(
        &mut self,
        state: &Particles<T>,
        anchor_x: &[Vec3<T>],
        anchor_v: &[Vec3<T>],
    ) {
        self.states.push(state.clone());
        self.anchor_x.push(anchor_x.to_vec());
        self.anchor_v = anchor_v.to_vec();
    }

    /// Substeps recorded (the differentiated window).
    pub fn len(&self) -> usize {
        self.states.len()
    }

    pub fn is_empty(&self) -> bool {
        self.states.is_empty()
    }
}

/// Gradients of one frame, in the caller's particle order.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameGrads<T> {
    /// Adjoint of the state at the frame's start (see the module docs).
    pub state: ParticleGrads<T>,
    pub mu: Vec<T>,
    pub lambda: Vec<T>,
    pub weights: Vec<[T; 3]>,
    pub gains: GainGrads,
    /// Adjoints of the effect coefficients over the differentiated window.
    pub effects: EffectGrads,
    /// Adjoint of each particle's mass over the differentiated window
    /// (a density gradient's parameter).
    pub mass: Vec<T>,
    /// Adjoints of the anchor positions at the frame's start and end
    /// (`anchors_from`, `anchors_to` of the step) over the differentiated
    /// window, through the substeps' interpolated anchor positions and the
    /// frame's anchor velocity. Zero in rigid mode.
    pub anchors_from: Vec<[f64; 3]>,
    pub anchors_to: Vec<[f64; 3]>,
}

/// Adjoints of the learnable effect coefficients (`PhysicsConfig::effects`)
/// and of gravity, summed over particles and substeps in f64.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct EffectGrads {
    /// ∂L/∂k₁, linear air drag (1/s).
    pub air_drag_linear: f64,
    /// ∂L/∂k₂, quadratic air drag (1/m).
    pub air_drag_quadratic: f64,
    /// ∂L/∂η, viscosity (Pa·s).
    pub viscosity: f64,
    /// ∂L/∂g, the gravity vector (m/s²; a ground tilt turns it).
    pub gravity: [f64; 3],
    /// ∂L/∂μ, the floor's Coulomb friction.
    pub floor_friction: f64,
    /// ∂L/∂c, the particle damping rate (1/s; `PhysicsConfig::particle_damping`).
    pub particle_damping: f64,
    /// ∂L/∂ of each parameter of the grid's body force, in its own units
    /// (`Effects::force_field`; also where it is zero).
    pub force_field: ForceField,
}

impl std::ops::AddAssign for EffectGrads {
    fn add_assign(&mut self, other: Self) {
        self.air_drag_linear += other.air_drag_linear;
        self.air_drag_quadratic += other.air_drag_quadratic;
        self.viscosity += other.viscosity;
        self.floor_friction += other.floor_friction;
        self.particle_damping += other.particle_damping;
        let (field, other_field) = (&mut self.force_field, &other.force_field);
        field.attractor_stiffness += other_field.attractor_stiffness;
        for a in 0..3 {
            self.gravity[a] += other.gravity[a];
            field.uniform[a] += other_field.uniform[a];
            field.axis_drag[a] += other_field.axis_drag[a];
            field.attractor_point[a] += other_field.attractor_point[a];
        }
    }
}

impl<T: Real> World<T> {
    /// Backward pass of a frame recorded by [`World::step_frame_taped`],
    /// given the adjoint of the state after it (caller's order).
    pub fn backward_frame(
        &mut self,
        tape: &FrameTape<T>,
        grad_after: &ParticleGrads<T>,
    ) -> Result<FrameGrads<T>, SimError> {
        crate::world::on_worker(|| self.backward_frame_here(tape, grad_after))
    }

    fn backward_frame_here(
        &mut self,
        tape: &FrameTape<T>,
        grad_after: &ParticleGrads<T>,
    ) -> Result<FrameGrads<T>, SimError> {
        let n = self.particle_count();
        if grad_after.x.len() != n {
            return Err(SimError::InvalidInput(
                "gradient size does not match particles".into(),
            ));
        }
        let mut grad = ParticleGrads {
            x: self.to_slot_order(&grad_after.x),
            v: self.to_slot_order(&grad_after.v),
            f: self.to_slot_order(&grad_after.f),
            c: self.to_slot_order(&grad_after.c),
        };
        let mut mu = vec![T::zero(); n];
        let mut lambda = vec![T::zero(); n];
        let mut weights = vec![[T::zero(); 3]; n];
        let mut mass = vec![T::zero(); n];
        let mut gains = GainGrads::default();
        let mut effects = EffectGrads::default();
        let mut step = SubstepGrads::zeros(n);
        let k = self.consts;
        let coupled = self.actuators.coupling_count() > 0;
        let anchors = tape.anchor_v.len();
        let mut anchors_from = vec![[0.0; 3]; anchors];
        let mut anchors_to = vec![[0.0; 3]; anchors];
        let (mut grad_anchor_x, mut grad_anchor_v) = (anchors_from.clone(), anchors_from.clone());
        let steps = self.config().substeps_per_frame;
        let frame_dt = self.config().dt * steps as f64;
        for r in (0..tape.states.len()).rev() {
            let before = &tape.states[r];
            if coupled && self.actuators.config.mode == ActuatorMode::Rigid {
                // Rigid particles are overwritten after the substep.
                for p in 0..n {
                    if self.actuators.is_coupled(p) {
                        grad.x[p] = Vec3::zeros();
                        grad.v[p] = Vec3::zeros();
                    }
                }
            }
            if coupled {
                self.external_accel.resize(n, Vec3::zeros());
                self.actuators.accelerations(
                    &before.x,
                    &before.v,
                    &tape.anchor_x[r],
                    &tape.anchor_v,
                    &mut self.external_accel,
                );
            }
            let inputs = SubstepInputs {
                material: &self.material,
                pure_neo_hookean: self.pure_neo_hookean,
                external_accel: coupled.then_some(&self.external_accel[..]),
            };
            substep_backward_into(
                &k,
                &inputs,
                before,
                tape.caches.get(r),
                &grad,
                &mut self.scratch,
                &mut step,
            )?;
            if coupled {
                let g = self.actuators.accelerations_vjp(
                    &before.x,
                    &before.v,
                    &tape.anchor_x[r],
                    &tape.anchor_v,
                    &step.external_accel,
                    &mut step.state.x,
                    &mut step.state.v,
                );
                gains.kp += g.kp;
                gains.kd += g.kd;
                // Substep s of the frame had anchors from + (to − from)·s/S
                // moving at (to − from)/frame_dt.
                grad_anchor_x.iter_mut().for_each(|g| *g = [0.0; 3]);
                grad_anchor_v.iter_mut().for_each(|g| *g = [0.0; 3]);
                self.actuators.anchors_vjp(
                    &step.external_accel,
                    &mut grad_anchor_x,
                    &mut grad_anchor_v,
                );
                let s = steps - tape.states.len() + r;
                let along = s as f64 / steps as f64;
                for c in 0..anchors {
                    for a in 0..3 {
                        let (gx, gv) = (grad_anchor_x[c][a], grad_anchor_v[c][a] / frame_dt);
                        anchors_from[c][a] += (1.0 - along) * gx - gv;
                        anchors_to[c][a] += along * gx + gv;
                    }
                }
            }
            for share in &step.effects {
                effects.air_drag_linear += share[0].to_f64();
                effects.air_drag_quadratic += share[1].to_f64();
            }
            effects.viscosity += step.viscosity.to_f64();
            effects.floor_friction += step.friction.to_f64();
            // κ = e^(−c dt): ∂κ/∂c = −dt κ.
            effects.particle_damping -=
                (step.damping_factor * k.dt * k.particle_damping_factor).to_f64();
            let (field, step_field) = (&mut effects.force_field, &step.force_field);
            field.attractor_stiffness += step_field.attractor_stiffness.to_f64();
            for a in 0..3 {
                effects.gravity[a] += step.gravity[a].to_f64();
                field.uniform[a] += step_field.uniform[a].to_f64();
                field.axis_drag[a] += step_field.axis_drag[a].to_f64();
                field.attractor_point[a] += step_field.attractor_point[a].to_f64();
            }
            for p in 0..n {
                mu[p] += step.mu[p];
                lambda[p] += step.lambda[p];
                mass[p] += step.mass[p];
                for e in 0..3 {
                    weights[p][e] += step.weights[p][e];
                }
            }
            // The substep's input adjoint becomes the next one's output
            // adjoint; the old buffers are reused (overwritten) next time.
            std::mem::swap(&mut grad, &mut step.state);
        }
        Ok(FrameGrads {
            state: ParticleGrads {
                x: self.to_caller_order(&grad.x),
                v: self.to_caller_order(&grad.v),
                f: self.to_caller_order(&grad.f),
                c: self.to_caller_order(&grad.c),
            },
            mu: self.to_caller_order(&mu),
            lambda: self.to_caller_order(&lambda),
            weights: self.to_caller_order(&weights),
            gains,
            effects,
            mass: self.to_caller_order(&mass),
            anchors_from,
            anchors_to,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenes::{BenchExperts, bench_block_frames};

    /// The forward caches are an optimisation only: the backward pass
    /// must give bitwise the same gradients with and without them.
    #[test]
    fn cached_and_recomputed_backward_agree_bitwise() {
        let grads = |store_grids: bool| {
            let mut world =
                bench_block_frames::<f32>(300, 32, BenchExperts::NeoHookean, 3, 6).expect("world");
            let mut tape = FrameTape::new(4, world.consts.res);
            tape.store_grids = store_grids;
            world
                .advance_frame(&[], &[], &[], crate::world::FrameRun::Taped(&mut tape, 0))
                .expect("frame");
            assert_eq!(tape.caches.len(), if store_grids { 4 } else { 0 });
            let n = world.particle_count();
            let mut upstream = ParticleGrads::zeros(n);
            for (p, g) in upstream.x.iter_mut().enumerate() {
                *g = Vec3::new(1.0, -0.5, 0.25) * (p as f32 / n as f32);
            }
            upstream.f.iter_mut().for_each(|g| g[(0, 1)] = 0.3);
            world.backward_frame(&tape, &upstream).expect("backward")
        };
        assert_eq!(grads(true), grads(false));
    }
}
