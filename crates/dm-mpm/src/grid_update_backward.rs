//! Backward twin of `grid_update.rs`.
//!
//! Forward, per node with mass m > threshold: u_pre = (P/m + dt g) γ, then
//! the slip walls zero outward components and the floor removes an
//! inward normal component — linear projections Π whose active set is
//! taken from the forward values. Backward: ū_pre = Π ū (Π symmetric),
//! P̄ = γ ū_pre / m, m̄ = −γ ū_pre · P / m². Empty nodes pass nothing back.
//!
//! Coulomb floor friction (μ > 0) replaces the floor's projection on a
//! node moving into the floor, with n the floor normal, v_n = n·v < 0,
//! v_t = v − n v_n and t̂ = v_t/|v_t|: sliding (|v_t| > −μ v_n) gives
//! u = v_t + μ v_n t̂, whose Jacobian-transpose is
//! ū ↦ Π_t ū + μ (t̂·ū) n + (μ v_n/|v_t|)(Π_t ū − t̂ (t̂·ū)) with
//! Π_t = I − n nᵀ; sticking gives u = 0 and passes nothing back. The
//! branch is taken from the forward values, like the projections'. The
//! coefficient's own adjoint (a learnt friction) is
//! μ̄ = Σ ū · ∂u/∂μ = Σ v_n (t̂·ū) over the sliding floor nodes (a
//! sticking node's u = 0 does not depend on μ), summed like ḡ below.
//!
//! With η > 0 the viscous solve sits between u_pre and the boundaries:
//! the boundaries' adjoint is taken at its output, and its own adjoint
//! (`viscosity_backward.rs`) turns that into ū_pre and a share of m̄.
//!
//! Gravity (a learnable tilt): ḡ = dt γ Σ ū_pre over the nodes
//! with mass, summed per slab and then over slabs in order, so the sum
//! does not depend on the thread count.
//!
//! A body force a = a₀ − D w − κ (x − p) (w = P/m, D diagonal, x the
//! node's position) adds dt a to u_pre before γ: the node's velocity
//! adjoint becomes w̄ = γ (1 − dt D) ū_pre, and the parameters' adjoints
//! are ā₀ = ḡ, D̄ = −dt γ Σ ū_pre ∘ w, κ̄ = −dt γ Σ ū_pre · (x − p) and
//! p̄ = κ ḡ, summed as ḡ is.

use crate::SimError;
use crate::grid::Grid;
use crate::grid_update::{node_position, node_velocities, node_velocity};
use crate::real::{Lane4, Real, Vec3};
use crate::state::Consts;
use crate::viscosity::ViscousSolver;
use rayon::prelude::*;

/// Adjoints of the grid update's parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridParameterGrads<T: Real> {
    /// Adjoint of the viscosity η (zero when η = 0).
    pub viscosity: T,
    /// Adjoint of the gravity vector.
    pub gravity: Vec3<T>,
    /// Adjoint of the floor's Coulomb friction μ (zero when μ = 0).
    pub friction: T,
    /// Adjoints of the body force's parameters (also where it is zero).
    pub force_field: ForceFieldGrads<T>,
}

/// Adjoints of `config::ForceField`'s parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ForceFieldGrads<T> {
    pub uniform: Vec3<T>,
    pub axis_drag: Vec3<T>,
    pub attractor_stiffness: T,
    pub attractor_point: Vec3<T>,
}

impl<T: Real> Default for ForceFieldGrads<T> {
    fn default() -> Self {
        Self {
            uniform: Vec3::zeros(),
            axis_drag: Vec3::zeros(),
            attractor_stiffness: T::zero(),
            attractor_point: Vec3::zeros(),
        }
    }
}

/// One slab's sums over its nodes with mass: Σ ū_pre (gravity), Σ ū_pre ∘
/// w and Σ ū_pre · (x − p) (the body force's, also when it is zero, so a
/// fit can learn it from there; see the module docs).
#[derive(Clone, Copy)]
struct SlabSums<T: Real> {
    gravity: Vec3<T>,
    along_velocity: Vec3<T>,
    along_offset: T,
}

impl<T: Real> SlabSums<T> {
    fn zero() -> Self {
        Self {
            gravity: Vec3::zeros(),
            along_velocity: Vec3::zeros(),
            along_offset: T::zero(),
        }
    }

    /// Adds node `idx` (momentum P, mass m) with velocity adjoint `gu`.
    #[inline(always)]
    fn add(&mut self, k: &Consts<T>, idx: [usize; 3], momentum: Vec3<T>, m: T, gu: Vec3<T>) {
        self.gravity += gu;
        self.along_velocity += gu.component_mul(&(momentum / m));
        self.along_offset += gu.dot(&(node_position(k, idx) - k.force_field.attractor_point));
    }

    /// Scaled by dt γ, as the parameters' adjoints are.
    fn scaled(self, k: &Consts<T>) -> Self {
        let scale = k.dt * k.grid_damping;
        Self {
            gravity: self.gravity * scale,
            along_velocity: self.along_velocity * scale,
            along_offset: self.along_offset * scale,
        }
    }

    /// Sums the slabs' scaled sums in order (independent of the thread
    /// count) into the gravity's and the body force's adjoints.
    fn parameters(
        k: &Consts<T>,
        slabs: impl Iterator<Item = Self>,
    ) -> (Vec3<T>, ForceFieldGrads<T>) {
        let total = slabs.fold(Self::zero(), |a, b| Self {
            gravity: a.gravity + b.gravity,
            along_velocity: a.along_velocity + b.along_velocity,
            along_offset: a.along_offset + b.along_offset,
        });
        let field = ForceFieldGrads {
            uniform: total.gravity,
            axis_drag: -total.along_velocity,
            attractor_stiffness: -total.along_offset,
            attractor_point: total.gravity * k.force_field.attractor_stiffness,
        };
        (total.gravity, field)
    }
}

/// [`SlabSums`] of slab `i` given its nodes and their ū_pre.
fn slab_sums<T: Real>(k: &Consts<T>, i: usize, slab: &[T::Lane4], grad: &[Vec3<T>]) -> SlabSums<T> {
    let res = k.res;
    let mut sums = SlabSums::zero();
    for (jk, (node, g)) in slab.iter().zip(grad).enumerate() {
        let lanes = node.to_array();
        if lanes[3] > k.empty_node_mass {
            let momentum = Vec3::new(lanes[0], lanes[1], lanes[2]);
            sums.add(k, [i, jk / res, jk % res], momentum, lanes[3], *g);
        }
    }
    sums.scaled(k)
}

/// Adjoint of the grid update. `pre` is the grid right after P2G
/// (momentum, mass), `grad_u` the adjoint of the node velocities.
/// Writes per node `[P̄_x, P̄_y, P̄_z, m̄]` and returns the adjoints of the
/// viscosity and gravity.
pub fn grid_update_backward<T: Real>(
    k: &Consts<T>,
    pre: &Grid<T>,
    grad_u: &[T::Lane4],
    grad_pre: &mut Vec<T::Lane4>,
    viscous: &mut ViscousSolver<T>,
) -> Result<GridParameterGrads<T>, SimError> {
    let res = k.res;
    grad_pre.clear();
    grad_pre.resize(pre.nodes.len(), T::Lane4::default());
    if k.viscosity == T::zero() {
        let slab_sums: Vec<(SlabSums<T>, T)> = grad_pre
            .par_chunks_mut(res * res)
            .zip(pre.nodes.par_chunks(res * res))
            .zip(grad_u.par_chunks(res * res))
            .enumerate()
            .map(|(i, ((out, slab), gslab))| {
                let (mut sums, mut friction) = (SlabSums::zero(), T::zero());
                for (jk, (o, (node, g))) in out.iter_mut().zip(slab.iter().zip(gslab)).enumerate() {
                    let lanes = node.to_array();
                    let idx = [i, jk / res, jk % res];
                    let Some(u) = node_velocity(k, idx, &lanes) else {
                        continue;
                    };
                    let momentum = Vec3::new(lanes[0], lanes[1], lanes[2]);
                    let ga = g.to_array();
                    let (gu, friction_share) =
                        boundaries_adjoint(k, idx, u, Vec3::new(ga[0], ga[1], ga[2]));
                    sums.add(k, idx, momentum, lanes[3], gu);
                    friction += friction_share;
                    *o = velocity_adjoint(k, momentum, lanes[3], gu, T::zero());
                }
                (sums.scaled(k), friction)
            })
            .collect();
        let (gravity, force_field) = SlabSums::parameters(k, slab_sums.iter().map(|s| s.0));
        return Ok(GridParameterGrads {
            viscosity: T::zero(),
            gravity,
            friction: slab_sums.iter().fold(T::zero(), |a, b| a + b.1),
            force_field,
        });
    }
    // u per node, then the viscous solve's v: recomputed, as the rest of
    // the grid update's forward values are.
    let mut velocities = std::mem::replace(&mut viscous.backward_grid, Grid::new(0));
    velocities.res = res;
    velocities.nodes.clone_from(&pre.nodes);
    node_velocities(k, &mut velocities);
    let solved = viscous.solve_grid(k, &velocities);
    if solved {
        let system = &viscous.system;
        for (&g, v) in system.nodes.iter().zip(&viscous.v) {
            velocities.nodes[g] = T::Lane4::from_array([v.x, v.y, v.z, pre.nodes[g].to_array()[3]]);
        }
    }
    // Adjoint of the boundaries at v, per node.
    let mut grad_v = std::mem::take(&mut viscous.backward_grad_v);
    grad_v.clear();
    grad_v.resize(pre.nodes.len(), Vec3::zeros());
    let friction_sums: Vec<T> = grad_v
        .par_chunks_mut(res * res)
        .zip(velocities.nodes.par_chunks(res * res))
        .zip(grad_u.par_chunks(res * res))
        .enumerate()
        .map(|(i, ((out, slab), gslab))| {
            let mut friction = T::zero();
            for (jk, (o, (node, g))) in out.iter_mut().zip(slab.iter().zip(gslab)).enumerate() {
                let a = node.to_array();
                let ga = g.to_array();
                let (gv, friction_share) = boundaries_adjoint(
                    k,
                    [i, jk / res, jk % res],
                    Vec3::new(a[0], a[1], a[2]),
                    Vec3::new(ga[0], ga[1], ga[2]),
                );
                *o = gv;
                friction += friction_share;
            }
            friction
        })
        .collect();
    let mut grad_mass = std::mem::take(&mut viscous.backward_grad_mass);
    grad_mass.clear();
    grad_mass.resize(pre.nodes.len(), T::zero());
    let mut grad_viscosity = T::zero();
    if solved {
        let gathered: Vec<Vec3<T>> = viscous.system.nodes.iter().map(|&g| grad_v[g]).collect();
        let vjp = viscous.vjp(&gathered);
        for ((&g, gu), gm) in viscous.system.nodes.iter().zip(&vjp.u).zip(&vjp.mass) {
            grad_v[g] = *gu;
            grad_mass[g] = *gm;
        }
        grad_viscosity = vjp.viscosity;
    }
    let slabs: Vec<SlabSums<T>> = pre
        .nodes
        .par_chunks(res * res)
        .zip(grad_v.par_chunks(res * res))
        .enumerate()
        .map(|(i, (slab, grad))| slab_sums(k, i, slab, grad))
        .collect();
    let (gravity, force_field) = SlabSums::parameters(k, slabs.into_iter());
    grad_pre
        .par_iter_mut()
        .zip(&pre.nodes)
        .zip(grad_v.par_iter().zip(&grad_mass))
        .for_each(|((o, node), (gu, gm))| {
            let lanes = node.to_array();
            let m = lanes[3];
            if m > k.empty_node_mass {
                let momentum = Vec3::new(lanes[0], lanes[1], lanes[2]);
                *o = velocity_adjoint(k, momentum, m, *gu, *gm);
            }
        });
    viscous.backward_grid = velocities;
    viscous.backward_grad_v = grad_v;
    viscous.backward_grad_mass = grad_mass;
    Ok(GridParameterGrads {
        viscosity: grad_viscosity,
        gravity,
        friction: friction_sums.iter().fold(T::zero(), |a, b| a + *b),
        force_field,
    })
}

/// `[P̄, m̄]` of u = (P/m + dt (g + a)) γ given ū, plus `extra_mass` (m̄
/// from the viscous solve); a body force's axis drag scales w̄ by
/// 1 − dt D.
#[inline(always)]
fn velocity_adjoint<T: Real>(
    k: &Consts<T>,
    momentum: Vec3<T>,
    m: T,
    mut gu: Vec3<T>,
    extra_mass: T,
) -> T::Lane4 {
    if k.force_field_on {
        gu -= gu.component_mul(&k.force_field.axis_drag) * k.dt;
    }
    let gp = gu * (k.grid_damping / m);
    let gm = -gu.dot(&momentum) * k.grid_damping / (m * m) + extra_mass;
    T::Lane4::from_array([gp.x, gp.y, gp.z, gm])
}

/// Adjoint of [`crate::grid_update::apply_boundaries`] at the velocity `v`
/// it was applied to, given the adjoint `g` of its output: the input's
/// adjoint and this node's share of μ̄.
#[inline(always)]
fn boundaries_adjoint<T: Real>(
    k: &Consts<T>,
    idx: [usize; 3],
    mut v: Vec3<T>,
    g: Vec3<T>,
) -> (Vec3<T>, T) {
    let (res, wall) = (k.res, k.wall_cells);
    let mut wall_kept = [true; 3];
    for a in 0..3 {
        if (idx[a] < wall && v[a] < T::zero()) || (idx[a] + wall >= res && v[a] > T::zero()) {
            v[a] = T::zero();
            wall_kept[a] = false;
        }
    }
    let (mut gv, mut friction) = (g, T::zero());
    if let Some(floor) = &k.floor {
        let vn = v.dot(&floor.up);
        if node_position(k, idx).dot(&floor.up) <= floor.limit && vn < T::zero() {
            (gv, friction) = floor_adjoint(floor.up, floor.friction, v, vn, gv);
        }
    }
    for a in 0..3 {
        if !wall_kept[a] {
            gv[a] = T::zero();
        }
    }
    (gv, friction)
}

/// Adjoint of the floor's velocity map at a node moving into the floor
/// (`vn` = n·v < 0): the normal projection, and with μ > 0 the Coulomb
/// slip or stick of the module docs; also ū · ∂u/∂μ.
fn floor_adjoint<T: Real>(n: Vec3<T>, friction: T, v: Vec3<T>, vn: T, g: Vec3<T>) -> (Vec3<T>, T) {
    let projected = g - n * n.dot(&g);
    if friction <= T::zero() {
        return (projected, T::zero());
    }
    let vt = v - n * vn;
    let speed = vt.norm();
    if speed <= friction * (-vn) {
        return (Vec3::zeros(), T::zero());
    }
    let t = vt / speed;
    let along = t.dot(&g);
    (
        projected + n * (friction * along) + (projected - t * along) * (friction * vn / speed),
        vn * along,
    )
}
