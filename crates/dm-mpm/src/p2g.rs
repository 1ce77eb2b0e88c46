//! Stage 2: particle-to-grid scatter of mass and APIC momentum.
//!
//! Parallel and deterministic without atomics: particles are bucketed by
//! the grid block (BLOCK³ cells) holding their stencil base, which gives a
//! spatially coherent order. That order is cut into [`SCATTER_PARTS`]
//! ranges of equal size; the parts scatter side by side, each into a grid
//! of its own and in order, and the grids are then summed in part order.
//! Each node therefore sums its contributions in an order that does not
//! depend on the number of threads: results are bitwise identical for any
//! pool.

use crate::grid::{Grid, Stencil, offsets, stencil, stencil_base};
use crate::real::{Lane4, Real, Vec3};
use crate::state::Consts;
use crate::stress::{CHUNK, ImpulseInputs, Impulses};
use rayon::prelude::*;

/// Block edge in cells: the bucketing's granularity.
pub const BLOCK: usize = 4;

/// Particle ranges scattered side by side, each into its own grid: a fixed
/// number, so the sums do not depend on the thread count. Each part beyond
/// the first costs a grid buffer and one add per node of the occupied box:
/// on two cores at 8 000 particles two parts run the substep 5 % faster
/// than four and eight 8 % slower; four keep the scatter parallel on
/// four-core laptops.
pub const SCATTER_PARTS: usize = 4;

/// Particles bucketed by block, rebuilt every substep (a counting sort).
#[derive(Clone, Debug, Default)]
pub struct BlockSchedule {
    blocks_per_axis: usize,
    key: Vec<u32>,
    /// `block_start[b]..block_start[b + 1]` indexes `order` for block b.
    block_start: Vec<u32>,
    order: Vec<u32>,
    /// Blocks holding at least one particle.
    occupied: Vec<u32>,
}

impl BlockSchedule {
    /// Buckets `x` by block. Slot order is kept inside each block.
    pub fn rebuild<T: Real>(&mut self, x: &[Vec3<T>], k: &Consts<T>) {
        self.blocks_per_axis = k.res.div_ceil(BLOCK);
        let n_blocks = self.blocks_per_axis.pow(3);
        let blocks_per_axis = self.blocks_per_axis as u32;
        self.key.resize(x.len(), 0);
        self.key
            .par_chunks_mut(CHUNK)
            .zip(x.par_chunks(CHUNK))
            .for_each(|(keys, xs)| {
                for (key, p) in keys.iter_mut().zip(xs) {
                    *key = block_index(p, k, blocks_per_axis);
                }
            });
        self.block_start.clear();
        self.block_start.resize(n_blocks + 1, 0);
        for &b in &self.key {
            self.block_start[b as usize + 1] += 1;
        }
        for b in 0..n_blocks {
            self.block_start[b + 1] += self.block_start[b];
        }
        let mut cursor: Vec<u32> = self.block_start[..n_blocks].to_vec();
        self.order.resize(x.len(), 0);
        for (p, &b) in self.key.iter().enumerate() {
            let c = &mut cursor[b as usize];
            self.order[*c as usize] = p as u32;
            *c += 1;
        }
        self.occupied.clear();
        for b in 0..n_blocks {
            if self.block_start[b] != self.block_start[b + 1] {
                self.occupied.push(b as u32);
            }
        }
    }

    /// Slots sorted by block (a spatially coherent particle order).
    pub fn order(&self) -> &[u32] {
        &self.order
    }

    /// The box of nodes `[lo, hi)` that the particles' stencils can touch
    /// (every node P2G writes lies inside it), `None` without particles.
    pub fn node_box(&self, res: usize) -> Option<([usize; 3], [usize; 3])> {
        let n = self.blocks_per_axis;
        let mut lo = [usize::MAX; 3];
        let mut hi = [0; 3];
        for &b in &self.occupied {
            let b = b as usize;
            let block = [b / (n * n), (b / n) % n, b % n];
            for a in 0..3 {
                lo[a] = lo[a].min(block[a] * BLOCK);
                // Stencil bases in the block, plus the stencil's 3 nodes.
                hi[a] = hi[a].max((block[a] * BLOCK + BLOCK - 1 + 3).min(res));
            }
        }
        (lo[0] < hi[0]).then_some((lo, hi))
    }
}

/// The block holding the stencil base of a particle at `x`.
#[inline(always)]
fn block_index<T: Real>(x: &Vec3<T>, k: &Consts<T>, blocks_per_axis: u32) -> u32 {
    let g = (x - k.origin) * k.inv_dx;
    let b = |c: T| (stencil_base(c, k.res) / BLOCK) as u32;
    let n = blocks_per_axis;
    (b(g.x) * n + b(g.y)) * n + b(g.z)
}

/// A raw pointer to the grid nodes of one scatter part.
#[derive(Debug)]
struct NodesPtr<L>(*mut L);

/// Write access to the 27 nodes of one particle's stencil, and only those.
#[derive(Debug)]
pub struct StencilNodes<'a, L> {
    nodes: &'a NodesPtr<L>,
    res: usize,
    base: [usize; 3],
}

impl<L> StencilNodes<'_, L> {
    /// The three nodes at stencil offsets (i, j, 0..3), contiguous in the
    /// grid (z is the fastest axis).
    #[inline(always)]
    pub fn row(&mut self, i: usize, j: usize) -> &mut [L; 3] {
        assert!(i < 3 && j < 3, "stencil offset out of range");
        let index = ((self.base[0] + i) * self.res + self.base[1] + j) * self.res + self.base[2];
        // SAFETY: bases are clamped to [0, res-3], so index + 2 < res³ (the
        // length checked in `scatter`); each part owns its grid, and
        // handles one particle at a time.
        unsafe { &mut *self.nodes.0.add(index).cast::<[L; 3]>() }
    }
}

impl BlockSchedule {
    /// Runs `body(p, stencil, nodes)` for every particle, letting it
    /// accumulate into its own stencil nodes of `nodes`: the particles'
    /// block order in [`SCATTER_PARTS`] ranges side by side, each range
    /// into its own grid (`nodes`, then the `spare` grids, which are kept
    /// zero between calls), summed into `nodes` in part order — so every
    /// node sums in an order independent of the thread count.
    pub fn scatter<T: Real, L: Copy + Default + std::ops::AddAssign + Send + Sync>(
        &self,
        k: &Consts<T>,
        x: &[Vec3<T>],
        nodes: &mut [L],
        spare: &mut Vec<Vec<L>>,
        body: impl Fn(usize, &Stencil<T>, &mut StencilNodes<'_, L>) + Sync,
    ) {
        let res = k.res;
        let len = res * res * res;
        assert_eq!(nodes.len(), len, "grid size mismatch");
        let Some((lo, hi)) = self.node_box(res) else {
            return;
        };
        spare.resize_with(SCATTER_PARTS - 1, Vec::new);
        for grid in spare.iter_mut() {
            if grid.len() != len {
                grid.clear();
                grid.resize(len, L::default());
            }
        }
        let n = self.order.len();
        let mut grids: Vec<&mut [L]> = std::iter::once(nodes)
            .chain(spare.iter_mut().map(|grid| &mut grid[..]))
            .collect();
        grids.par_iter_mut().enumerate().for_each(|(part, grid)| {
            let ptr = NodesPtr(grid.as_mut_ptr());
            for &p in &self.order[part * n / SCATTER_PARTS..(part + 1) * n / SCATTER_PARTS] {
                let p = p as usize;
                let st = stencil(&x[p], &k.origin, k.inv_dx, res);
                let mut writer = StencilNodes {
                    nodes: &ptr,
                    res,
                    base: st.base,
                };
                body(p, &st, &mut writer);
            }
        });
        let [main, rest @ ..] = &mut grids[..] else {
            unreachable!("at least one scatter part")
        };
        for i in lo[0]..hi[0] {
            for j in lo[1]..hi[1] {
                let row = (i * res + j) * res;
                for node in row + lo[2]..row + hi[2] {
                    for grid in rest.iter_mut() {
                        main[node] += grid[node];
                        grid[node] = L::default();
                    }
                }
            }
        }
    }
}

/// Scatters mass and momentum (`momentum + affine · (x_node − x_p)`) of
/// every particle to its 27 stencil nodes, given the impulses computed
/// from `inputs`. `grid` must be cleared.
pub fn p2g<T: Real>(
    k: &Consts<T>,
    schedule: &BlockSchedule,
    inputs: &ImpulseInputs<'_, T>,
    impulses: &Impulses<T>,
    grid: &mut Grid<T>,
    spare: &mut Vec<Vec<T::Lane4>>,
) {
    let mass = &inputs.particles.mass;
    let zero = T::zero();
    schedule.scatter(
        k,
        &inputs.particles.x,
        &mut grid.nodes,
        spare,
        |p, st, nodes| {
            let (a, momentum) = (impulses.affine[p], impulses.momentum[p]);
            // q(i,j,k) = [momentum + A·((i,j,k) − frac)·dx, m] as 4 lanes,
            // built incrementally; each node then takes one FMA.
            let col = |c: usize| {
                let v = a.column(c) * k.dx;
                T::Lane4::from_array([v.x, v.y, v.z, zero])
            };
            let (ax, ay, az) = (col(0), col(1), col(2));
            let q0v = momentum - a * (st.frac * k.dx);
            let q0 = T::Lane4::from_array([q0v.x, q0v.y, q0v.z, mass[p]]);
            scatter_affine::<T>(st, q0, [ax, ay, az], nodes);
        },
    );
}

/// Adds `w_i (q0 + cols[0] i + cols[1] j + cols[2] k)` to the node at
/// stencil offset (i, j, k): an affine field scattered with the B-spline
/// weights (P2G's momentum and mass, and the adjoint of G2P's gather).
/// The field is built incrementally, so each node takes one FMA.
#[inline(always)]
pub fn scatter_affine<T: Real>(
    st: &Stencil<T>,
    q0: T::Lane4,
    cols: [T::Lane4; 3],
    nodes: &mut StencilNodes<'_, T::Lane4>,
) {
    let off = offsets::<T>();
    let [ax, ay, az] = cols;
    for i in 0..3 {
        let qi = ax.mul_add(T::Lane4::splat(off[i]), q0);
        for j in 0..3 {
            let wij = st.w[0][i] * st.w[1][j];
            let qij = ay.mul_add(T::Lane4::splat(off[j]), qi);
            let q = [qij, qij + az, qij + az + az];
            let row = nodes.row(i, j);
            for kk in 0..3 {
                let w = T::Lane4::splat(wij * st.w[2][kk]);
                row[kk] = w.mul_add(q[kk], row[kk]);
            }
        }
    }
}
