//! The background grid (struct of one interleaved array: momentum or
//! velocity in xyz plus mass per node, so a stencil row is one cache line)
//! and the quadratic B-spline stencil shared by P2G and G2P.

use crate::real::{Lane4, Real, Vec3};

/// Grid nodes, `res^3`, z fastest. Lanes of `nodes[i]` are
/// `[p_x, p_y, p_z, m]`; after the grid update the first three hold velocity.
#[derive(Clone, Debug)]
pub struct Grid<T: Real> {
    pub res: usize,
    pub nodes: Vec<T::Lane4>,
}

impl<T: Real> Grid<T> {
    pub fn new(res: usize) -> Self {
        Self {
            res,
            nodes: vec![T::Lane4::default(); res * res * res],
        }
    }

    #[inline(always)]
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        (i * self.res + j) * self.res + k
    }

    pub fn clear(&mut self) {
        self.nodes.fill(T::Lane4::default());
    }

    /// Zeroes the nodes of the box `[lo, hi)`.
    pub fn clear_box(&mut self, (lo, hi): NodeBox) {
        for i in lo[0]..hi[0] {
            for j in lo[1]..hi[1] {
                let row = self.index(i, j, 0);
                self.nodes[row + lo[2]..row + hi[2]].fill(T::Lane4::default());
            }
        }
    }
}

/// A box of grid nodes `[lo, hi)`.
pub type NodeBox = ([usize; 3], [usize; 3]);

/// The nodes of a [`Grid`] inside a box `[lo, hi)`, for a grid known to be
/// zero outside it: a compact copy (the frame tape stores one per substep;
/// a block of particles touches a small part of the grid, and fresh tape
/// memory costs a page fault per 4 KiB).
#[derive(Clone, Debug)]
pub struct GridBox<T: Real> {
    lo: [usize; 3],
    hi: [usize; 3],
    nodes: Vec<T::Lane4>,
}

impl<T: Real> GridBox<T> {
    /// Copies the nodes of `grid` inside `[lo, hi)`.
    pub fn capture(grid: &Grid<T>, lo: [usize; 3], hi: [usize; 3]) -> Self {
        let len = hi[2] - lo[2];
        let mut nodes = Vec::with_capacity((hi[0] - lo[0]) * (hi[1] - lo[1]) * len);
        for i in lo[0]..hi[0] {
            for j in lo[1]..hi[1] {
                let row = grid.index(i, j, lo[2]);
                nodes.extend_from_slice(&grid.nodes[row..row + len]);
            }
        }
        Self { lo, hi, nodes }
    }

    /// Writes the captured grid into `grid` (resized to `res³`): the box's
    /// nodes, zero elsewhere — bitwise the grid that was captured.
    pub fn restore(&self, res: usize, grid: &mut Grid<T>) {
        grid.res = res;
        grid.nodes.clear();
        grid.nodes.resize(res * res * res, T::Lane4::default());
        let len = self.hi[2] - self.lo[2];
        let mut rows = self.nodes.chunks_exact(len.max(1));
        for i in self.lo[0]..self.hi[0] {
            for j in self.lo[1]..self.hi[1] {
                let row = grid.index(i, j, self.lo[2]);
                if let Some(src) = rows.next() {
                    grid.nodes[row..row + len].copy_from_slice(src);
                }
            }
        }
    }
}

/// The 3x3x3 quadratic B-spline support of one particle.
#[derive(Clone, Copy, Debug)]
pub struct Stencil<T> {
    /// Lowest node of the support.
    pub base: [usize; 3],
    /// `w[axis][offset]`, offsets 0..3 from `base`.
    pub w: [[T; 3]; 3],
    /// Particle position minus `base`, in cells (in [0.5, 1.5) inside the domain).
    pub frac: Vec3<T>,
}

/// Lowest stencil node along one axis, clamped so the support stays inside
/// the grid even for a particle that escaped (its weights are then wrong,
/// but memory stays safe; the position clip keeps real particles inside).
#[inline(always)]
pub fn stencil_base<T: Real>(coord_cells: T, res: usize) -> usize {
    let b = (coord_cells - T::lit(0.5)).floor();
    if b >= T::zero() {
        // `as` saturates, so a huge value still ends at res - 3.
        (b.to_f64() as usize).min(res - 3)
    } else {
        0 // negative or NaN
    }
}

#[inline(always)]
fn axis_weights<T: Real>(f: T) -> [T; 3] {
    let half = T::lit(0.5);
    let d0 = T::lit(1.5) - f;
    let d1 = f - T::one();
    let d2 = f - half;
    [half * d0 * d0, T::lit(0.75) - d1 * d1, half * d2 * d2]
}

#[inline(always)]
pub fn stencil<T: Real>(x: &Vec3<T>, origin: &Vec3<T>, inv_dx: T, res: usize) -> Stencil<T> {
    let g = (x - origin) * inv_dx;
    let base = [
        stencil_base(g.x, res),
        stencil_base(g.y, res),
        stencil_base(g.z, res),
    ];
    let frac = Vec3::new(
        g.x - T::from_index(base[0]),
        g.y - T::from_index(base[1]),
        g.z - T::from_index(base[2]),
    );
    let w = [
        axis_weights(frac.x),
        axis_weights(frac.y),
        axis_weights(frac.z),
    ];
    Stencil { base, w, frac }
}

/// Node offsets 0, 1, 2 as floats, hoisted so loops never convert indices.
#[inline(always)]
pub fn offsets<T: Real>() -> [T; 3] {
    [T::zero(), T::one(), T::lit(2.0)]
}

/// Derivatives of the 1D quadratic B-spline weights with respect to the
/// fractional cell coordinate (`d w[offset] / d frac`).
#[inline(always)]
pub fn axis_weight_slopes<T: Real>(f: T) -> [T; 3] {
    [
        f - T::lit(1.5),
        T::lit(-2.0) * (f - T::one()),
        f - T::lit(0.5),
    ]
}

impl<T: Real> Stencil<T> {
    /// `d w_ijk / d x_p` for the node at offset (i, j, k), metres⁻¹.
    #[inline(always)]
    pub fn weight_gradient(
        &self,
        slopes: &[[T; 3]; 3],
        inv_dx: T,
        i: usize,
        j: usize,
        k: usize,
    ) -> Vec3<T> {
        let w = &self.w;
        Vec3::new(
            slopes[0][i] * w[1][j] * w[2][k],
            w[0][i] * slopes[1][j] * w[2][k],
            w[0][i] * w[1][j] * slopes[2][k],
        ) * inv_dx
    }

    /// Per-axis weight slopes of this stencil.
    #[inline(always)]
    pub fn slopes(&self) -> [[T; 3]; 3] {
        [
            axis_weight_slopes(self.frac.x),
            axis_weight_slopes(self.frac.y),
            axis_weight_slopes(self.frac.z),
        ]
    }

    /// `x_node − x_p` for the node at offset (i, j, k), metres.
    #[inline(always)]
    pub fn node_offset(&self, dx: T, i: usize, j: usize, k: usize) -> Vec3<T> {
        (Vec3::new(T::from_index(i), T::from_index(j), T::from_index(k)) - self.frac) * dx
    }
}

/// Weighted sums of per-node data `n_i` (4 lanes) over a particle's
/// stencil, as the adjoints of both transfers need them. With node offset
/// o_i = (i, j, k), weight w_i and its gradient ∇w_i (per unit `frac`,
/// i.e. without the 1/dx factor):
///
/// * `sum     = Σ w_i n_i`
/// * `moment[b] = Σ w_i o_{i,b} n_i`
/// * `slope[c]  = Σ (∂w_i/∂frac_c) n_i`
/// * `slope_moment[c][b] = Σ (∂w_i/∂frac_c) o_{i,b} n_i`
///
/// These turn the 27-node loops of the adjoints into a few 3×3 products
/// per particle (see `g2p_backward.rs`, `p2g_backward.rs`).
#[derive(Clone, Copy, Debug)]
pub struct StencilMoments<L> {
    pub sum: L,
    pub moment: [L; 3],
    pub slope: [L; 3],
    pub slope_moment: [[L; 3]; 3],
}

/// Gathers [`StencilMoments`] of `nodes` over the stencil `st`.
///
/// Each weight factorises over the axes, so the sums are built axis by
/// axis (z, then y, then x) from four 1D factors per axis — weight w,
/// w·o, slope s, s·o — and only products with at most one slope and one
/// moment factor are kept: 12 multiplies and adds per row of three nodes,
/// 9 FMAs per row and 16 per x-slab instead of ~150 scalar operations per
/// node.
#[inline(always)]
pub fn gather_moments<T: Real>(
    st: &Stencil<T>,
    nodes: &[T::Lane4],
    res: usize,
) -> StencilMoments<T::Lane4> {
    let sp = |x: T| T::Lane4::splat(x);
    let two = sp(T::lit(2.0));
    let off = offsets::<T>();
    let slopes = st.slopes();
    let zero = T::Lane4::default();
    let mut out = StencilMoments {
        sum: zero,
        moment: [zero; 3],
        slope: [zero; 3],
        slope_moment: [[zero; 3]; 3],
    };
    for i in 0..3 {
        // Sums over the (j, k) slab: weight-type factors named y_z, with
        // w = weight, o = weight·offset, s = slope, so = slope·offset.
        let (mut w_w, mut o_w, mut w_o) = (zero, zero, zero);
        let (mut s_w, mut w_s, mut so_w) = (zero, zero, zero);
        let (mut s_o, mut o_s, mut w_so) = (zero, zero, zero);
        for j in 0..3 {
            let row = ((st.base[0] + i) * res + st.base[1] + j) * res + st.base[2];
            let n = &nodes[row..row + 3];
            let a0 = n[0] * sp(st.w[2][0]);
            let a1 = n[1] * sp(st.w[2][1]);
            let a2 = n[2] * sp(st.w[2][2]);
            let b0 = n[0] * sp(slopes[2][0]);
            let b1 = n[1] * sp(slopes[2][1]);
            let b2 = n[2] * sp(slopes[2][2]);
            let z_w = a0 + a1 + a2;
            let z_o = a2.mul_add(two, a1);
            let z_s = b0 + b1 + b2;
            let z_so = b2.mul_add(two, b1);
            let (wy, sy) = (sp(st.w[1][j]), sp(slopes[1][j]));
            let (wy_o, sy_o) = (sp(st.w[1][j] * off[j]), sp(slopes[1][j] * off[j]));
            w_w = z_w.mul_add(wy, w_w);
            o_w = z_w.mul_add(wy_o, o_w);
            w_o = z_o.mul_add(wy, w_o);
            s_w = z_w.mul_add(sy, s_w);
            w_s = z_s.mul_add(wy, w_s);
            so_w = z_w.mul_add(sy_o, so_w);
            s_o = z_o.mul_add(sy, s_o);
            o_s = z_s.mul_add(wy_o, o_s);
            w_so = z_so.mul_add(wy, w_so);
        }
        let (wx, sx) = (sp(st.w[0][i]), sp(slopes[0][i]));
        let (wx_o, sx_o) = (sp(st.w[0][i] * off[i]), sp(slopes[0][i] * off[i]));
        // x factor = weight.
        out.sum = w_w.mul_add(wx, out.sum);
        out.moment[1] = o_w.mul_add(wx, out.moment[1]);
        out.moment[2] = w_o.mul_add(wx, out.moment[2]);
        out.slope[1] = s_w.mul_add(wx, out.slope[1]);
        out.slope[2] = w_s.mul_add(wx, out.slope[2]);
        out.slope_moment[1][1] = so_w.mul_add(wx, out.slope_moment[1][1]);
        out.slope_moment[1][2] = s_o.mul_add(wx, out.slope_moment[1][2]);
        out.slope_moment[2][1] = o_s.mul_add(wx, out.slope_moment[2][1]);
        out.slope_moment[2][2] = w_so.mul_add(wx, out.slope_moment[2][2]);
        // x factor = weight·offset (moment along x).
        out.moment[0] = w_w.mul_add(wx_o, out.moment[0]);
        out.slope_moment[1][0] = s_w.mul_add(wx_o, out.slope_moment[1][0]);
        out.slope_moment[2][0] = w_s.mul_add(wx_o, out.slope_moment[2][0]);
        // x factor = slope.
        out.slope[0] = w_w.mul_add(sx, out.slope[0]);
        out.slope_moment[0][1] = o_w.mul_add(sx, out.slope_moment[0][1]);
        out.slope_moment[0][2] = w_o.mul_add(sx, out.slope_moment[0][2]);
        // x factor = slope·offset.
        out.slope_moment[0][0] = w_w.mul_add(sx_o, out.slope_moment[0][0]);
    }
    out
}
