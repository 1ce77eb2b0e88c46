//! The background grid (struct of one interleaved array: momentum or
//! velocity in xyz plus mass per node, so a stencil row is one cache line)
//! and the quadratic B-spline stencil shared by P2G and G2P.

use crate::real::{Real, Vec3};

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
