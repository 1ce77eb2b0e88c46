//! One MPM substep as a pure function of the particle state, and its
//! reverse-mode adjoint: stress → P2G → grid update → G2P, each stage
//! differentiated by its backward twin. The backward pass recomputes the
//! substep's forward grids from the stored input state, unless the frame
//! tape kept them ([`SubstepCache`], within the tape's memory budget).

use crate::SimError;
use crate::g2p::{ParticleFailure, g2p};
use crate::g2p_backward::{GatherAdjoint, NodeVelocityGrads, ParticleGrads, g2p_backward};
use crate::grid::{Grid, GridBox, NodeBox};
use crate::grid_update::grid_update;
use crate::grid_update_backward::{ForceFieldGrads, grid_update_backward};
use crate::material::ParticleMaterial;
use crate::p2g::{BlockSchedule, p2g};
use crate::p2g_backward::p2g_particle_vjp;
use crate::real::{Mat3, Real, Vec3};
use crate::state::{Consts, Particles};
use crate::stress::{ImpulseInputs, Impulses};
use crate::stress_backward::particle_impulse_vjp;
use crate::viscosity::ViscousSolver;
use rayon::prelude::*;

/// Buffers reused across substeps.
#[derive(Debug)]
pub struct SubstepScratch<T: Real> {
    pub schedule: BlockSchedule,
    pub grid: Grid<T>,
    /// The grid right after P2G, written by the backward pass.
    pub(crate) grid_pre: Grid<T>,
    /// Whether the forward pass keeps what its backward twin would
    /// recompute (for the tape, see [`SubstepScratch::take_cache`]).
    pub(crate) keep_pre_grid: bool,
    kept: Option<SubstepCache<T>>,
    grad_u: NodeVelocityGrads<T>,
    grad_pre: Vec<T::Lane4>,
    gather_bar: Vec<GatherAdjoint<T>>,
    viscous: ViscousSolver<T>,
    impulses: Impulses<T>,
    /// The scatter parts' own grids (P2G's and its adjoint's; zero between uses).
    scatter_spare: Vec<Vec<T::Lane4>>,
    /// A box outside which `grid` is known to be zero (`None`: unknown).
    grid_written: Option<NodeBox>,
}

impl<T: Real> SubstepScratch<T> {
    pub fn new(res: usize) -> Self {
        Self {
            schedule: BlockSchedule::default(),
            grid: Grid::new(res),
            grid_pre: Grid::new(res),
            keep_pre_grid: false,
            kept: None,
            grad_u: Vec::new(),
            grad_pre: Vec::new(),
            gather_bar: Vec::new(),
            viscous: ViscousSolver::default(),
            impulses: Impulses::default(),
            scatter_spare: Vec::new(),
            grid_written: None,
        }
    }
}

/// What the forward pass of a substep computed that its backward pass
/// would otherwise recompute: the grid right after P2G (only the box the
/// particles touch) and the particle bucketing. Both are pure functions of
/// the substep's input state, so the cached copy is bitwise what the
/// recomputation gives.
#[derive(Clone, Debug)]
pub(crate) struct SubstepCache<T: Real> {
    pre_grid: Option<GridBox<T>>,
    schedule: BlockSchedule,
}

impl<T: Real> SubstepScratch<T> {
    /// What the last [`substep_forward`] kept (it must have run with
    /// `keep_pre_grid` set).
    pub(crate) fn take_cache(&mut self) -> SubstepCache<T> {
        self.kept
            .take()
            .expect("take_cache follows a forward substep run with keep_pre_grid")
    }
}

/// The material and forcing a substep reads besides the state.
#[derive(Clone, Copy, Debug)]
pub struct SubstepInputs<'a, T> {
    pub material: &'a ParticleMaterial<T>,
    pub pure_neo_hookean: bool,
    pub external_accel: Option<&'a [Vec3<T>]>,
}

/// Adjoint of a substep with respect to everything it reads.
#[derive(Clone, Debug, PartialEq)]
pub struct SubstepGrads<T> {
    pub state: ParticleGrads<T>,
    pub mu: Vec<T>,
    pub lambda: Vec<T>,
    pub weights: Vec<[T; 3]>,
    pub external_accel: Vec<Vec3<T>>,
    /// Per-particle shares of the drag-parameter adjoints (see
    /// `ImpulseGrads::effects`); sum over particles for the gradient.
    pub effects: Vec<[T; 2]>,
    /// Adjoint of the viscosity η (the grid's implicit viscous solve).
    pub viscosity: T,
    /// Adjoint of the gravity vector (a ground tilt's parameter).
    pub gravity: Vec3<T>,
    /// Adjoint of the floor's Coulomb friction μ.
    pub friction: T,
    /// Adjoints of the grid's body force (also where it is zero).
    pub force_field: ForceFieldGrads<T>,
    /// Adjoint of the per-substep particle damping factor κ = e^(−c dt).
    pub damping_factor: T,
    /// Adjoint of each particle's mass (a density gradient's parameter).
    pub mass: Vec<T>,
}

/// Accumulated wall time per solver stage (for benchmarks).
#[derive(Clone, Copy, Debug, Default)]
pub struct StageSeconds {
    pub actuators: f64,
    pub schedule: f64,
    /// The per-particle stress and impulses P2G scatters.
    pub stress: f64,
    pub p2g: f64,
    pub grid_update: f64,
    pub g2p: f64,
}

/// A stopwatch that adds each lap to a stage's total, when timing is on.
struct Laps<'a> {
    totals: Option<&'a mut StageSeconds>,
    clock: std::time::Instant,
}

impl Laps<'_> {
    fn lap(&mut self, stage: fn(&mut StageSeconds) -> &mut f64) {
        if let Some(totals) = self.totals.as_deref_mut() {
            let now = std::time::Instant::now();
            *stage(totals) += (now - self.clock).as_secs_f64();
            self.clock = now;
        }
    }
}

/// Advances `particles` by one substep (no actuator constraints), adding
/// the time of each stage to `timings` when given.
pub fn substep_forward<T: Real>(
    k: &Consts<T>,
    inputs: &SubstepInputs<'_, T>,
    particles: &mut Particles<T>,
    scratch: &mut SubstepScratch<T>,
    timings: Option<&mut StageSeconds>,
) -> Result<(), ParticleFailure> {
    let mut laps = Laps {
        totals: timings,
        clock: std::time::Instant::now(),
    };
    scratch.schedule.rebuild(&particles.x, k);
    match scratch.grid_written.take() {
        Some(written) => scratch.grid.clear_box(written),
        None => scratch.grid.clear(),
    }
    let occupied = scratch.schedule.node_box(k.res);
    scratch.grid_written = Some(occupied.unwrap_or(([0; 3], [0; 3])));
    laps.lap(|s| &mut s.schedule);
    let impulse = ImpulseInputs {
        particles,
        material: inputs.material,
        pure_neo_hookean: inputs.pure_neo_hookean,
        external_accel: inputs.external_accel,
    };
    scratch.impulses.compute(k, &impulse, false);
    laps.lap(|s| &mut s.stress);
    p2g(
        k,
        &scratch.schedule,
        &impulse,
        &scratch.impulses,
        &mut scratch.grid,
        &mut scratch.scatter_spare,
    );
    if scratch.keep_pre_grid {
        scratch.kept = Some(SubstepCache {
            pre_grid: occupied.map(|(lo, hi)| GridBox::capture(&scratch.grid, lo, hi)),
            schedule: scratch.schedule.clone(),
        });
    }
    laps.lap(|s| &mut s.p2g);
    if k.viscosity != T::zero() {
        // The viscous solve may write any node.
        scratch.grid_written = None;
    }
    grid_update(k, &mut scratch.grid, &mut scratch.viscous, occupied);
    laps.lap(|s| &mut s.grid_update);
    let result = g2p(k, &scratch.grid, particles);
    laps.lap(|s| &mut s.g2p);
    result
}

/// Adjoint of [`substep_forward`] at the state `before`, given the adjoint
/// of the state after it.
pub fn substep_backward<T: Real>(
    k: &Consts<T>,
    inputs: &SubstepInputs<'_, T>,
    before: &Particles<T>,
    grad_after: &ParticleGrads<T>,
    scratch: &mut SubstepScratch<T>,
) -> Result<SubstepGrads<T>, SimError> {
    let mut grads = SubstepGrads::zeros(0);
    substep_backward_into(k, inputs, before, None, grad_after, scratch, &mut grads)?;
    Ok(grads)
}

impl<T: Real> SubstepGrads<T> {
    pub fn zeros(n: usize) -> Self {
        Self {
            state: ParticleGrads::zeros(n),
            mu: vec![T::zero(); n],
            lambda: vec![T::zero(); n],
            weights: vec![[T::zero(); 3]; n],
            external_accel: vec![Vec3::zeros(); n],
            effects: vec![[T::zero(); 2]; n],
            viscosity: T::zero(),
            gravity: Vec3::zeros(),
            friction: T::zero(),
            force_field: ForceFieldGrads::default(),
            damping_factor: T::zero(),
            mass: vec![T::zero(); n],
        }
    }

    /// Resizes every buffer to `n` particles, keeping allocations (every
    /// entry is overwritten by [`substep_backward_into`]).
    fn resize(&mut self, n: usize) {
        let s = &mut self.state;
        s.x.resize(n, Vec3::zeros());
        s.v.resize(n, Vec3::zeros());
        s.f.resize(n, Mat3::zeros());
        s.c.resize(n, Mat3::zeros());
        self.mu.resize(n, T::zero());
        self.lambda.resize(n, T::zero());
        self.weights.resize(n, [T::zero(); 3]);
        self.external_accel.resize(n, Vec3::zeros());
        self.effects.resize(n, [T::zero(); 2]);
        self.mass.resize(n, T::zero());
    }
}

/// [`substep_backward`] writing into `grads` (every entry overwritten), so
/// a frame's backward pass reuses its buffers instead of allocating (and
/// page-faulting in) fresh ones each substep. `cache`, when given, holds
/// what this substep's forward pass computed, saving the recomputation
/// of the bucketing and P2G.
pub(crate) fn substep_backward_into<T: Real>(
    k: &Consts<T>,
    inputs: &SubstepInputs<'_, T>,
    before: &Particles<T>,
    cache: Option<&SubstepCache<T>>,
    grad_after: &ParticleGrads<T>,
    scratch: &mut SubstepScratch<T>,
    grads: &mut SubstepGrads<T>,
) -> Result<(), SimError> {
    let n = before.len();
    // The forward grids of this substep: taped or recomputed.
    let impulse = ImpulseInputs {
        particles: before,
        material: inputs.material,
        pure_neo_hookean: inputs.pure_neo_hookean,
        external_accel: inputs.external_accel,
    };
    scratch.impulses.compute(k, &impulse, true);
    let schedule = match cache {
        Some(cache) => {
            match &cache.pre_grid {
                Some(grid_box) => grid_box.restore(k.res, &mut scratch.grid_pre),
                None => scratch.grid_pre.clear(),
            }
            &cache.schedule
        }
        None => {
            scratch.schedule.rebuild(&before.x, k);
            scratch.grid_pre.clear();
            p2g(
                k,
                &scratch.schedule,
                &impulse,
                &scratch.impulses,
                &mut scratch.grid_pre,
                &mut scratch.scatter_spare,
            );
            &scratch.schedule
        }
    };
    let pre_grid = &scratch.grid_pre;
    scratch.grid.nodes.clone_from(&pre_grid.nodes);
    scratch.grid_written = None;
    grid_update(
        k,
        &mut scratch.grid,
        &mut scratch.viscous,
        schedule.node_box(k.res),
    );

    grads.resize(n);
    grads.damping_factor = g2p_backward(
        k,
        schedule,
        &scratch.grid,
        &before.x,
        &before.f,
        grad_after,
        &mut grads.state,
        &mut scratch.grad_u,
        &mut scratch.gather_bar,
        &mut scratch.scatter_spare,
    );
    let grid_parameters = grid_update_backward(
        k,
        pre_grid,
        &scratch.grad_u,
        &mut scratch.grad_pre,
        &mut scratch.viscous,
    )?;
    grads.viscosity = grid_parameters.viscosity;
    grads.gravity = grid_parameters.gravity;
    grads.friction = grid_parameters.friction;
    grads.force_field = grid_parameters.force_field;
    let grad_pre = &scratch.grad_pre;
    let impulses = &scratch.impulses;
    let state = &mut grads.state;
    (
        state.x.par_iter_mut(),
        state.v.par_iter_mut(),
        state.f.par_iter_mut(),
        state.c.par_iter_mut(),
        grads.mu.par_iter_mut(),
        grads.lambda.par_iter_mut(),
        grads.weights.par_iter_mut(),
        grads.external_accel.par_iter_mut(),
        grads.effects.par_iter_mut(),
        grads.mass.par_iter_mut(),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(p, (gx, gv, gf, gc, gmu, glambda, gw, ga, ge, gm))| {
            let own = (impulses.affine[p], impulses.momentum[p]);
            let scatter = p2g_particle_vjp(k, &impulse, p, own, grad_pre);
            let rotation = impulses.rotation.get(p);
            let g =
                particle_impulse_vjp(k, &impulse, p, rotation, &scatter.affine, &scatter.momentum);
            // x and F also carry the gather's adjoint (g2p_backward); v
            // and C reach the substep's output only through P2G.
            *gx += scatter.x;
            *gv = g.v;
            *gf += g.f;
            *gc = g.c;
            *gmu = g.mu;
            *glambda = g.lambda;
            *gw = g.weights;
            *ga = g.external_accel;
            *ge = g.effects;
            *gm = scatter.mass + g.mass;
        });
    Ok(())
}
