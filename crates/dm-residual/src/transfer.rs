//! Particle ↔ grid-node transfers of the particle-grid residual with the
//! MPM's quadratic B-spline weights, each with its backward twin.
//!
//! Node sums run node by node over a node's particles in particle order
//! (a gather, not a scatter), so they are deterministic and parallel.

use crate::kernels::{Rows, Scalar};
use rayon::prelude::*;
use std::collections::HashMap;

/// Nodes of one particle's stencil.
pub const STENCIL: usize = 27;

/// The grid nodes a cloud reaches and which particle reaches which node.
#[derive(Clone, Debug)]
pub struct Stencil {
    /// Each particle's base cell (the stencil's lowest corner), per axis.
    pub base: Vec<[f64; 3]>,
    /// Node id of stencil slot s of particle p at `p * 27 + s`.
    pub node_of: Vec<u32>,
    /// Integer grid coordinates of each node, ids in order of first use.
    pub cells: Vec<[i64; 3]>,
    /// Slots (p * 27 + s) reaching node i: `members[starts[i]..starts[i + 1]]`,
    /// in increasing order.
    members: Vec<u32>,
    starts: Vec<usize>,
}

impl Stencil {
    pub fn new(positions: &[[f64; 3]], origin: [f64; 3], dx: f64) -> Self {
        let mut ids: HashMap<[i64; 3], u32> = HashMap::new();
        let mut cells: Vec<[i64; 3]> = Vec::new();
        let mut base = Vec::with_capacity(positions.len());
        let mut node_of = Vec::with_capacity(positions.len() * STENCIL);
        for x in positions {
            let cell = [0, 1, 2].map(|a| ((x[a] - origin[a]) / dx - 0.5).floor() as i64);
            base.push(cell.map(|c| c as f64));
            for i in 0..3 {
                for j in 0..3 {
                    for k in 0..3 {
                        let node = [cell[0] + i, cell[1] + j, cell[2] + k];
                        let next = cells.len() as u32;
                        node_of.push(*ids.entry(node).or_insert_with(|| {
                            cells.push(node);
                            next
                        }));
                    }
                }
            }
        }
        // Counting sort of the slots by node: each node's members stay in
        // slot order.
        let mut starts = vec![0usize; cells.len() + 1];
        for &n in &node_of {
            starts[n as usize + 1] += 1;
        }
        for i in 0..cells.len() {
            starts[i + 1] += starts[i];
        }
        let mut fill = starts.clone();
        let mut members = vec![0u32; node_of.len()];
        for (slot, &n) in node_of.iter().enumerate() {
            members[fill[n as usize]] = slot as u32;
            fill[n as usize] += 1;
        }
        Self {
            base,
            node_of,
            cells,
            members,
            starts,
        }
    }

    pub fn nodes(&self) -> usize {
        self.cells.len()
    }

    fn members(&self, node: usize) -> &[u32] {
        &self.members[self.starts[node]..self.starts[node + 1]]
    }
}

/// Quadratic B-spline weights of the three offsets at fractional grid
/// coordinate `f` (relative to the base cell), and their derivatives.
fn spline<T: Scalar>(f: T) -> ([T; 3], [T; 3]) {
    let half = T::lit(0.5);
    let a = T::lit(1.5) - f;
    let b = f - T::one();
    let c = f - half;
    (
        [half * a * a, T::lit(0.75) - b * b, half * c * c],
        [-a, -(b + b), c],
    )
}

/// Particle p's grid coordinate on `axis` relative to its base cell.
fn fraction<T: Scalar>(
    x: &Rows<T>,
    stencil: &Stencil,
    origin: [f64; 3],
    dx: f64,
    p: usize,
    axis: usize,
) -> T {
    (x.row(p)[axis] - T::lit(origin[axis])) / T::lit(dx) - T::lit(stencil.base[p][axis])
}

/// The stencil weights `w` (particles × 27), differentiable in x.
pub fn spline_weights<T: Scalar>(
    x: &Rows<T>,
    stencil: &Stencil,
    origin: [f64; 3],
    dx: f64,
) -> Rows<T> {
    let mut w = Rows::zeros(x.rows(), STENCIL);
    w.data
        .par_chunks_mut(STENCIL)
        .enumerate()
        .for_each(|(p, out)| {
            let axes = [0, 1, 2].map(|a| spline(fraction(x, stencil, origin, dx, p, a)).0);
            let mut s = 0;
            for i in 0..3 {
                for j in 0..3 {
                    for k in 0..3 {
                        out[s] = axes[0][i] * axes[1][j] * axes[2][k];
                        s += 1;
                    }
                }
            }
        });
    w
}

/// ∂L/∂x (particles × 3) from ∂L/∂w.
pub fn spline_weights_backward<T: Scalar>(
    x: &Rows<T>,
    stencil: &Stencil,
    origin: [f64; 3],
    dx: f64,
    grad: &Rows<T>,
) -> Rows<T> {
    let mut out = Rows::zeros(x.rows(), 3);
    out.data.par_chunks_mut(3).enumerate().for_each(|(p, dxp)| {
        let axes = [0, 1, 2].map(|a| spline(fraction(x, stencil, origin, dx, p, a)));
        let g = grad.row(p);
        let inverse_dx = T::lit(1.0 / dx);
        let mut s = 0;
        for i in 0..3 {
            for j in 0..3 {
                for k in 0..3 {
                    let (wx, wy, wz) = (axes[0].0[i], axes[1].0[j], axes[2].0[k]);
                    let (dwx, dwy, dwz) = (axes[0].1[i], axes[1].1[j], axes[2].1[k]);
                    dxp[0] = dxp[0] + g[s] * dwx * wy * wz * inverse_dx;
                    dxp[1] = dxp[1] + g[s] * wx * dwy * wz * inverse_dx;
                    dxp[2] = dxp[2] + g[s] * wx * wy * dwz * inverse_dx;
                    s += 1;
                }
            }
        }
    });
    out
}

/// Each node's weighted mean of the particle rows reaching it:
/// Σ w·f / max(Σ w, `floor`). Returns the means and the weight sums
/// (before the floor).
pub fn node_means<T: Scalar>(
    features: &Rows<T>,
    w: &Rows<T>,
    stencil: &Stencil,
    floor: f64,
) -> (Rows<T>, Vec<T>) {
    let width = features.width;
    let mut means = Rows::zeros(stencil.nodes(), width);
    let mut sums = vec![T::zero(); stencil.nodes()];
    means
        .data
        .par_chunks_mut(width)
        .zip(sums.par_iter_mut())
        .enumerate()
        .for_each(|(node, (out, sum))| {
            for &slot in stencil.members(node) {
                let slot = slot as usize;
                let weight = w.data[slot];
                *sum = *sum + weight;
                for (o, f) in out.iter_mut().zip(features.row(slot / STENCIL)) {
                    *o = *o + weight * *f;
                }
            }
            let divisor = sum.max(T::lit(floor));
            out.iter_mut().for_each(|o| *o = *o / divisor);
        });
    (means, sums)
}

/// Backward of [`node_means`]: (∂L/∂features, ∂L/∂w) from ∂L/∂means.
/// Where the weight sum is below `floor` the divisor is that constant.
pub fn node_means_backward<T: Scalar>(
    features: &Rows<T>,
    w: &Rows<T>,
    stencil: &Stencil,
    floor: f64,
    means: &Rows<T>,
    sums: &[T],
    grad: &Rows<T>,
) -> (Rows<T>, Rows<T>) {
    let width = features.width;
    // ∂L/∂(Σ w·f) = g / S; ∂L/∂S = −Σ_c g_c·mean_c / S where S is not floored.
    let mut d_total = grad.clone();
    let mut d_sum = vec![T::zero(); stencil.nodes()];
    d_total
        .data
        .par_chunks_mut(width)
        .zip(d_sum.par_iter_mut())
        .enumerate()
        .for_each(|(node, (g, ds))| {
            let divisor = sums[node].max(T::lit(floor));
            if sums[node] > T::lit(floor) {
                let along = g
                    .iter()
                    .zip(means.row(node))
                    .fold(T::zero(), |s, (a, b)| s + *a * *b);
                *ds = -along / divisor;
            }
            g.iter_mut().for_each(|v| *v = *v / divisor);
        });
    let mut d_features = Rows::zeros(features.rows(), width);
    let mut d_w = Rows::zeros(w.rows(), STENCIL);
    d_features
        .data
        .par_chunks_mut(width)
        .zip(d_w.data.par_chunks_mut(STENCIL))
        .enumerate()
        .for_each(|(p, (df, dw))| {
            let f = features.row(p);
            for s in 0..STENCIL {
                let node = stencil.node_of[p * STENCIL + s] as usize;
                let weight = w.data[p * STENCIL + s];
                let dt = d_total.row(node);
                let mut along = T::zero();
                for c in 0..width {
                    df[c] = df[c] + weight * dt[c];
                    along = along + f[c] * dt[c];
                }
                dw[s] = along + d_sum[node];
            }
        });
    (d_features, d_w)
}

/// Each particle's weighted sum of its stencil's node rows.
pub fn to_particles<T: Scalar>(node_values: &Rows<T>, w: &Rows<T>, stencil: &Stencil) -> Rows<T> {
    let width = node_values.width;
    let mut out = Rows::zeros(w.rows(), width);
    out.data
        .par_chunks_mut(width)
        .enumerate()
        .for_each(|(p, o)| {
            for s in 0..STENCIL {
                let weight = w.data[p * STENCIL + s];
                let node = stencil.node_of[p * STENCIL + s] as usize;
                for (acc, v) in o.iter_mut().zip(node_values.row(node)) {
                    *acc = *acc + weight * *v;
                }
            }
        });
    out
}

/// Backward of [`to_particles`]: (∂L/∂node rows, ∂L/∂w) from ∂L/∂out.
pub fn to_particles_backward<T: Scalar>(
    node_values: &Rows<T>,
    w: &Rows<T>,
    stencil: &Stencil,
    grad: &Rows<T>,
) -> (Rows<T>, Rows<T>) {
    let width = node_values.width;
    let mut d_nodes = Rows::zeros(stencil.nodes(), width);
    d_nodes
        .data
        .par_chunks_mut(width)
        .enumerate()
        .for_each(|(node, out)| {
            for &slot in stencil.members(node) {
                let slot = slot as usize;
                let weight = w.data[slot];
                for (o, g) in out.iter_mut().zip(grad.row(slot / STENCIL)) {
                    *o = *o + weight * *g;
                }
            }
        });
    let mut d_w = Rows::zeros(w.rows(), STENCIL);
    d_w.data
        .par_chunks_mut(STENCIL)
        .enumerate()
        .for_each(|(p, dw)| {
            let g = grad.row(p);
            for s in 0..STENCIL {
                let node = stencil.node_of[p * STENCIL + s] as usize;
                dw[s] = node_values
                    .row(node)
                    .iter()
                    .zip(g)
                    .fold(T::zero(), |acc, (v, gi)| acc + *v * *gi);
            }
        });
    (d_nodes, d_w)
}
