//! Stage 3: momentum to velocity, gravity and any body force, grid damping, the implicit
//! viscous solve when η > 0 (`viscosity.rs`), then slip walls at the
//! domain faces and the floor (with optional Coulomb friction).

use crate::grid::{Grid, NodeBox};
use crate::real::{Lane4, Real, Vec3};
use crate::state::Consts;
use crate::viscosity::{ViscousSolver, viscosity_solve};
use rayon::prelude::*;

/// u = (w + dt (g + a(x, w))) γ of node `idx` with lanes `[P, m]`, w = P/m
/// and a the body force (zero without one); `None` for a node too light
/// to divide by safely (treated as empty).
#[inline(always)]
pub(crate) fn node_velocity<T: Real>(
    k: &Consts<T>,
    idx: [usize; 3],
    lanes: &[T; 4],
) -> Option<Vec3<T>> {
    let m = lanes[3];
    if m <= k.empty_node_mass {
        return None;
    }
    let v = Vec3::new(lanes[0], lanes[1], lanes[2]) / m;
    let mut accel = k.gravity;
    if k.force_field_on {
        accel += k.force_field.accel(&node_position(k, idx), &v);
    }
    Some((v + accel * k.dt) * k.grid_damping)
}

/// World position of node `idx`.
#[inline(always)]
pub(crate) fn node_position<T: Real>(k: &Consts<T>, idx: [usize; 3]) -> Vec3<T> {
    k.origin
        + Vec3::new(
            T::from_index(idx[0]),
            T::from_index(idx[1]),
            T::from_index(idx[2]),
        ) * k.dx
}

/// The slip walls and the floor applied to the velocity of node `idx`.
#[inline(always)]
pub(crate) fn apply_boundaries<T: Real>(k: &Consts<T>, idx: [usize; 3], mut v: Vec3<T>) -> Vec3<T> {
    let (res, wall) = (k.res, k.wall_cells);
    for a in 0..3 {
        if (idx[a] < wall && v[a] < T::zero()) || (idx[a] + wall >= res && v[a] > T::zero()) {
            v[a] = T::zero();
        }
    }
    if let Some(floor) = &k.floor
        && node_position(k, idx).dot(&floor.up) <= floor.limit
    {
        let vn = v.dot(&floor.up);
        if vn < T::zero() {
            let mut vt = v - floor.up * vn;
            if floor.friction > T::zero() {
                let speed = vt.norm();
                let slow = floor.friction * (-vn);
                vt = if speed > slow {
                    vt * ((speed - slow) / speed)
                } else {
                    Vec3::zeros()
                };
            }
            v = vt;
        }
    }
    v
}

/// Runs `f(idx, node)` on every node, slab-parallel.
fn for_each_node<T: Real>(grid: &mut Grid<T>, f: impl Fn([usize; 3], &mut T::Lane4) + Sync) {
    let res = grid.res;
    for_each_node_in(grid, ([0; 3], [res; 3]), f);
}

/// Runs `f(idx, node)` on every node of the box `[lo, hi)`, slab-parallel.
fn for_each_node_in<T: Real>(
    grid: &mut Grid<T>,
    (lo, hi): NodeBox,
    f: impl Fn([usize; 3], &mut T::Lane4) + Sync,
) {
    let res = grid.res;
    grid.nodes[lo[0] * res * res..hi[0] * res * res]
        .par_chunks_mut(res * res)
        .enumerate()
        .for_each(|(slab_index, slab)| {
            let i = lo[0] + slab_index;
            for j in lo[1]..hi[1] {
                for kk in lo[2]..hi[2] {
                    f([i, j, kk], &mut slab[j * res + kk]);
                }
            }
        });
}

/// The grid update; `viscous` holds the viscous solve's buffers (unused
/// when η = 0). `occupied`, when given, is a box outside which every node
/// is empty: those nodes stay zero, so only the box is visited.
pub fn grid_update<T: Real>(
    k: &Consts<T>,
    grid: &mut Grid<T>,
    viscous: &mut ViscousSolver<T>,
    occupied: Option<NodeBox>,
) {
    if k.viscosity == T::zero() {
        let whole = ([0; 3], [grid.res; 3]);
        for_each_node_in(grid, occupied.unwrap_or(whole), |idx, node| {
            let lanes = node.to_array();
            *node = match node_velocity(k, idx, &lanes) {
                Some(u) => {
                    let v = apply_boundaries(k, idx, u);
                    T::Lane4::from_array([v.x, v.y, v.z, lanes[3]])
                }
                None => T::Lane4::default(),
            };
        });
        return;
    }
    node_velocities(k, grid);
    viscosity_solve(k, grid, viscous);
    for_each_node(grid, |idx, node| {
        let lanes = node.to_array();
        let v = apply_boundaries(k, idx, Vec3::new(lanes[0], lanes[1], lanes[2]));
        *node = T::Lane4::from_array([v.x, v.y, v.z, lanes[3]]);
    });
}

/// Lanes `[P, m]` become `[u, m]`, u the node velocity before the viscous
/// solve and the boundaries (empty nodes zero).
pub(crate) fn node_velocities<T: Real>(k: &Consts<T>, grid: &mut Grid<T>) {
    for_each_node(grid, |idx, node| {
        let lanes = node.to_array();
        *node = match node_velocity(k, idx, &lanes) {
            Some(u) => T::Lane4::from_array([u.x, u.y, u.z, lanes[3]]),
            None => T::Lane4::default(),
        };
    });
}
