//! Stage 3: momentum to velocity, gravity, grid damping, slip walls at the
//! domain faces and the floor (with optional Coulomb friction).

use crate::grid::Grid;
use crate::real::{Lane4, Real, Vec3};
use crate::state::Consts;
use rayon::prelude::*;

pub fn grid_update<T: Real>(k: &Consts<T>, grid: &mut Grid<T>) {
    let res = k.res;
    let wall = k.wall_cells;
    grid.nodes
        .par_chunks_mut(res * res)
        .enumerate()
        .for_each(|(i, slab)| {
            for (jk, node) in slab.iter_mut().enumerate() {
                let lanes = node.to_array();
                let m = lanes[3];
                if m <= k.empty_node_mass {
                    // Too light to divide by safely: treat as empty.
                    *node = T::Lane4::default();
                    continue;
                }
                let idx = [i, jk / res, jk % res];
                let mut v = Vec3::new(lanes[0], lanes[1], lanes[2]) / m;
                v = (v + k.gravity * k.dt) * k.grid_damping;
                for a in 0..3 {
                    if (idx[a] < wall && v[a] < T::zero())
                        || (idx[a] + wall >= res && v[a] > T::zero())
                    {
                        v[a] = T::zero();
                    }
                }
                if let Some(floor) = &k.floor {
                    let pos = k.origin
                        + Vec3::new(
                            T::lit(idx[0] as f64),
                            T::lit(idx[1] as f64),
                            T::lit(idx[2] as f64),
                        ) * k.dx;
                    if pos.dot(&floor.up) <= floor.limit {
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
                }
                *node = T::Lane4::from_array([v.x, v.y, v.z, m]);
            }
        });
}
