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
//! branch is taken from the forward values, like the projections'.

use crate::SimError;
use crate::grid::Grid;
use crate::real::{Lane4, Real, Vec3};
use crate::state::Consts;
use rayon::prelude::*;

/// Adjoint of the grid update. `pre` is the grid right after P2G
/// (momentum, mass), `grad_u` the adjoint of the node velocities.
/// Returns per node `[P̄_x, P̄_y, P̄_z, m̄]`.
pub fn grid_update_backward<T: Real>(
    k: &Consts<T>,
    pre: &Grid<T>,
    grad_u: &[T::Lane4],
    grad_pre: &mut Vec<T::Lane4>,
) -> Result<(), SimError> {
    let res = k.res;
    let wall = k.wall_cells;
    grad_pre.clear();
    grad_pre.resize(pre.nodes.len(), T::Lane4::default());
    grad_pre
        .par_chunks_mut(res * res)
        .zip(pre.nodes.par_chunks(res * res))
        .zip(grad_u.par_chunks(res * res))
        .enumerate()
        .for_each(|(i, ((out, slab), gslab))| {
            for (jk, (o, (node, g))) in out.iter_mut().zip(slab.iter().zip(gslab)).enumerate() {
                let lanes = node.to_array();
                let m = lanes[3];
                if m <= k.empty_node_mass {
                    continue;
                }
                let idx = [i, jk / res, jk % res];
                let momentum = Vec3::new(lanes[0], lanes[1], lanes[2]);
                let mut v = (momentum / m + k.gravity * k.dt) * k.grid_damping;
                let mut wall_kept = [true; 3];
                for a in 0..3 {
                    if (idx[a] < wall && v[a] < T::zero())
                        || (idx[a] + wall >= res && v[a] > T::zero())
                    {
                        v[a] = T::zero();
                        wall_kept[a] = false;
                    }
                }
                let ga = g.to_array();
                let mut gv = Vec3::new(ga[0], ga[1], ga[2]);
                if let Some(floor) = &k.floor {
                    let pos = k.origin
                        + Vec3::new(
                            T::from_index(idx[0]),
                            T::from_index(idx[1]),
                            T::from_index(idx[2]),
                        ) * k.dx;
                    let vn = v.dot(&floor.up);
                    if pos.dot(&floor.up) <= floor.limit && vn < T::zero() {
                        gv = floor_adjoint(floor.up, floor.friction, v, vn, gv);
                    }
                }
                for a in 0..3 {
                    if !wall_kept[a] {
                        gv[a] = T::zero();
                    }
                }
                let gp = gv * (k.grid_damping / m);
                let gm = -gv.dot(&momentum) * k.grid_damping / (m * m);
                *o = T::Lane4::from_array([gp.x, gp.y, gp.z, gm]);
            }
        });
    Ok(())
}

/// Adjoint of the floor's velocity map at a node moving into the floor
/// (`vn` = n·v < 0): the normal projection, and with μ > 0 the Coulomb
/// slip or stick of the module docs.
fn floor_adjoint<T: Real>(n: Vec3<T>, friction: T, v: Vec3<T>, vn: T, g: Vec3<T>) -> Vec3<T> {
    let projected = g - n * n.dot(&g);
    if friction <= T::zero() {
        return projected;
    }
    let vt = v - n * vn;
    let speed = vt.norm();
    if speed <= friction * (-vn) {
        return Vec3::zeros();
    }
    let t = vt / speed;
    let along = t.dot(&g);
    projected + n * (friction * along) + (projected - t * along) * (friction * vn / speed)
}
