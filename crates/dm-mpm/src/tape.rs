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
use crate::g2p_backward::ParticleGrads;
use crate::real::{Real, Vec3};
use crate::state::Particles;
use crate::substep::{SubstepInputs, substep_backward};
use crate::world::World;

/// What the backward pass of one frame needs.
#[derive(Clone, Debug)]
pub struct FrameTape<T> {
    pub(crate) window: usize,
    /// State entering each recorded substep, in slot order, oldest first.
    states: Vec<Particles<T>>,
    anchor_x: Vec<Vec<Vec3<T>>>,
    anchor_v: Vec<Vec3<T>>,
}

impl<T: Real> FrameTape<T> {
    pub(crate) fn new(window: usize) -> Self {
        Self {
            window,
            states: Vec::new(),
            anchor_x: Vec::new(),
            anchor_v: Vec::new(),
        }
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
}

impl<T: Real> World<T> {
    /// Backward pass of a frame recorded by [`World::step_frame_taped`],
    /// given the adjoint of the state after it (caller's order).
    pub fn backward_frame(
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
        let mut gains = GainGrads::default();
        let k = self.consts;
        let coupled = self.actuators.coupling_count() > 0;
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
            let mut step = substep_backward(&k, &inputs, before, &grad, &mut self.scratch)?;
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
            }
            for p in 0..n {
                mu[p] += step.mu[p];
                lambda[p] += step.lambda[p];
                for e in 0..3 {
                    weights[p][e] += step.weights[p][e];
                }
            }
            grad = step.state;
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
        })
    }
}
