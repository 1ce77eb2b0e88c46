//! Stage 3b (only when η > 0): implicit strain-rate viscosity on the grid.
//!
//! Explicit viscous stress is stable only for η ≲ ρ dx² / (6 dt), about
//! 40 Pa·s on the model's grid, where it moves nothing visible.
//! Here the node velocities u (after gravity and damping, before the
//! boundaries) are replaced by the solution of
//!
//!   (M + dt K) v = M u,
//!
//! backward Euler for the viscous force −K v. K comes from the Cauchy
//! stress σ = 2η sym(∇v) integrated over grid cells: in each cell whose 8
//! corner nodes all carry mass, ∇v is the trilinear gradient at the
//! centre, ∇v = Σ_q v_q g_qᵀ with g_q = s_q / (4 dx), s_q ∈ {±1}³ the
//! corner's side, and the cell's material volume is V_c = H_c / ρ with H_c
//! the harmonic mean of its corner masses (dx³ inside the object). The
//! harmonic mean keeps a light node's viscous coupling in proportion to
//! its own mass (V_c ≤ 8 m_q / ρ), so every row of the system has the same
//! ratio dt η / (ρ dx²) of viscous to inertial terms: with the arithmetic
//! mean, a nearly empty node beside full ones made the solve
//! ill-conditioned (200 iterations for 120 unknowns, and a solution only
//! accurate to 1e-5 in the finite-difference test).
//! So vᵀ K w = Σ_c 2η V_c sym(∇v_c) : sym(∇w_c): symmetric, positive
//! semi-definite, and zero on rigid motions (a linear field whose gradient
//! is skew), so it damps deformation rates only. One quadrature point per
//! cell leaves hourglass modes undamped; viscosity needs no more, since
//! the elastic stress controls them.
//!
//! The system is solved by conjugate gradients with a Jacobi
//! preconditioner, warm-started from u; dot products are serial sums, so
//! the result does not depend on the thread count. Its buffers live in a
//! [`ViscousSolver`] reused from substep to substep: fresh ones cost more
//! in page faults than the solve (measured on the toy truth: 123 s → 104 s
//! for 18 frames from the slot maps alone).

use crate::grid::Grid;
use crate::real::{Lane4, Mat3, Real, Vec3};
use crate::state::Consts;
use rayon::prelude::*;

/// Marks an empty node or an inactive cell in the slot maps.
pub(crate) const NONE: u32 = u32::MAX;
/// Cells or nodes per parallel task: smaller tasks cost more in hand-offs
/// than they save on these short loops.
const PARALLEL_MIN_LEN: usize = 1024;
/// Conjugate gradients stops here even short of its tolerance (a Jacobi-
/// preconditioned solve at the η of the diagnosis ranges takes 10–60).
const MAX_ITERATIONS: usize = 500;

/// Corner `q` of a cell (bits a b c: offset along x y z) and the sign of
/// its trilinear shape function's gradient at the cell centre.
fn corner_offset(q: usize) -> [usize; 3] {
    [(q >> 2) & 1, (q >> 1) & 1, q & 1]
}

fn corner_gradient<T: Real>(q: usize, inv_dx: T) -> Vec3<T> {
    let side = |bit: usize| if bit == 1 { T::one() } else { -T::one() };
    let [a, b, c] = corner_offset(q);
    Vec3::new(side(a), side(b), side(c)) * (inv_dx * T::lit(0.25))
}

/// One cell with 8 non-empty corners.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Cell<T> {
    /// Unknown index of each corner (corner order of [`corner_offset`]).
    pub(crate) corners: [u32; 8],
    /// Material volume V_c = H(m) / ρ, H the harmonic mean.
    pub(crate) volume: T,
}

/// The linear system of one grid's viscous solve: its unknowns (the
/// non-empty nodes), its cells, and the operator's scale 2η dt.
#[derive(Debug)]
pub(crate) struct ViscousSystem<T: Real> {
    /// Grid index of each unknown.
    pub(crate) nodes: Vec<usize>,
    pub(crate) mass: Vec<T>,
    pub(crate) cells: Vec<Cell<T>>,
    /// For each unknown, its up to 8 cells and its corner in each.
    pub(crate) node_cells: Vec<[(u32, u8); 8]>,
    /// Jacobi diagonal of M + dt K (equal for the three components).
    pub(crate) diagonal: Vec<T>,
    /// 2 dt, and the operator's scale 2η dt.
    pub(crate) two_dt: T,
    pub(crate) scale: T,
    gradients: [Vec3<T>; 8],
    pub(crate) density: T,
    /// Box-local maps from grid coordinates to unknowns and cells.
    slot: Vec<u32>,
    cell_slot: Vec<u32>,
}

/// Conjugate-gradient work vectors.
#[derive(Debug, Default)]
pub(crate) struct CgBuffers<T: Real> {
    r: Vec<Vec3<T>>,
    z: Vec<Vec3<T>>,
    p: Vec<Vec3<T>>,
    q: Vec<Vec3<T>>,
    stress: Vec<Mat3<T>>,
}

/// A viscous solve's system, its input u and output v per unknown, and
/// every buffer, kept for reuse (one per [`crate::substep::SubstepScratch`]).
#[derive(Debug)]
pub struct ViscousSolver<T: Real> {
    pub(crate) system: ViscousSystem<T>,
    pub(crate) u: Vec<Vec3<T>>,
    pub(crate) v: Vec<Vec3<T>>,
    b: Vec<Vec3<T>>,
    pub(crate) cg: CgBuffers<T>,
    /// Scratch of the backward pass (`grid_update_backward.rs`).
    pub(crate) backward_grid: Grid<T>,
    pub(crate) backward_grad_v: Vec<Vec3<T>>,
    pub(crate) backward_grad_mass: Vec<T>,
}

impl<T: Real> Default for ViscousSolver<T> {
    fn default() -> Self {
        Self {
            system: ViscousSystem {
                nodes: Vec::new(),
                mass: Vec::new(),
                cells: Vec::new(),
                node_cells: Vec::new(),
                diagonal: Vec::new(),
                two_dt: T::zero(),
                scale: T::zero(),
                gradients: [Vec3::zeros(); 8],
                density: T::one(),
                slot: Vec::new(),
                cell_slot: Vec::new(),
            },
            u: Vec::new(),
            v: Vec::new(),
            b: Vec::new(),
            cg: CgBuffers::default(),
            backward_grid: Grid::new(0),
            backward_grad_v: Vec::new(),
            backward_grad_mass: Vec::new(),
        }
    }
}

impl<T: Real> ViscousSystem<T> {
    /// Rebuilds the system of `grid`, whose lane 3 holds node masses
    /// (empty nodes zero or at most `k.empty_node_mass`).
    fn rebuild(&mut self, k: &Consts<T>, grid: &Grid<T>) {
        let res = grid.res;
        let coords = |g: usize| [g / (res * res), (g / res) % res, g % res];
        self.nodes.clear();
        self.mass.clear();
        // The box of non-empty nodes: the slot maps cover it only.
        let (mut lo, mut hi) = ([usize::MAX; 3], [0; 3]);
        for (g, node) in grid.nodes.iter().enumerate() {
            let m = node.to_array()[3];
            if m > k.empty_node_mass && m > T::zero() {
                self.nodes.push(g);
                self.mass.push(m);
                let c = coords(g);
                for a in 0..3 {
                    lo[a] = lo[a].min(c[a]);
                    hi[a] = hi[a].max(c[a]);
                }
            }
        }
        let dims = [0, 1, 2].map(|a| (hi[a] + 1).saturating_sub(lo[a]));
        let local =
            |c: [usize; 3]| ((c[0] - lo[0]) * dims[1] + (c[1] - lo[1])) * dims[2] + (c[2] - lo[2]);
        let inside = |c: [usize; 3]| (0..3).all(|a| c[a] >= lo[a] && c[a] <= hi[a]);
        let boxed = dims.iter().product();
        self.slot.clear();
        self.slot.resize(boxed, NONE);
        for (u, &g) in self.nodes.iter().enumerate() {
            self.slot[local(coords(g))] = u as u32;
        }
        self.cells.clear();
        self.cell_slot.clear();
        self.cell_slot.resize(boxed, NONE);
        for &g in &self.nodes {
            let [i, j, l] = coords(g);
            if i + 1 > hi[0] || j + 1 > hi[1] || l + 1 > hi[2] {
                continue;
            }
            let mut corners = [NONE; 8];
            for (q, corner) in corners.iter_mut().enumerate() {
                let [a, b, c] = corner_offset(q);
                *corner = self.slot[local([i + a, j + b, l + c])];
            }
            if corners.contains(&NONE) {
                continue;
            }
            let inverse_sum: T = corners
                .iter()
                .fold(T::zero(), |s, &u| s + T::one() / self.mass[u as usize]);
            self.cell_slot[local([i, j, l])] = self.cells.len() as u32;
            self.cells.push(Cell {
                corners,
                volume: T::lit(8.0) / (inverse_sum * k.density),
            });
        }
        self.node_cells.clear();
        for &g in &self.nodes {
            let [i, j, l] = coords(g);
            let mut adjacent = [(NONE, 0u8); 8];
            for (q, entry) in adjacent.iter_mut().enumerate() {
                let [a, b, c] = corner_offset(q);
                if i >= a && j >= b && l >= c && inside([i - a, j - b, l - c]) {
                    *entry = (self.cell_slot[local([i - a, j - b, l - c])], q as u8);
                }
            }
            self.node_cells.push(adjacent);
        }
        self.two_dt = T::lit(2.0) * k.dt;
        self.scale = self.two_dt * k.viscosity;
        self.density = k.density;
        self.gradients = std::array::from_fn(|q| corner_gradient(q, k.inv_dx));
        // Diagonal of dt K per component: Σ_c η V_c (|g|² + g_a²) dt
        // = Σ_c (2η dt) V_c / (8 dx²).
        let per_volume = self.scale * k.inv_dx * k.inv_dx / T::lit(8.0);
        self.diagonal.clear();
        for (adjacent, &m) in self.node_cells.iter().zip(&self.mass) {
            let d = adjacent
                .iter()
                .filter(|(c, _)| *c != NONE)
                .fold(m, |d, &(c, _)| {
                    d + self.cells[c as usize].volume * per_volume
                });
            self.diagonal.push(d);
        }
    }

    /// sym(∇v) of `cell`.
    #[inline(always)]
    fn cell_strain_rate(&self, cell: &Cell<T>, v: &[Vec3<T>]) -> Mat3<T> {
        let mut grad = Mat3::zeros();
        for (q, &u) in cell.corners.iter().enumerate() {
            grad += v[u as usize] * self.gradients[q].transpose();
        }
        (grad + grad.transpose()) * T::lit(0.5)
    }

    /// sym(∇v) of every cell.
    pub(crate) fn strain_rates(&self, v: &[Vec3<T>], out: &mut Vec<Mat3<T>>) {
        out.resize(self.cells.len(), Mat3::zeros());
        out.par_iter_mut()
            .with_min_len(PARALLEL_MIN_LEN)
            .zip(&self.cells)
            .for_each(|(s, cell)| *s = self.cell_strain_rate(cell, v));
    }

    /// out = (M + dt K) v; `stress` is scratch.
    fn apply(&self, v: &[Vec3<T>], stress: &mut Vec<Mat3<T>>, out: &mut [Vec3<T>]) {
        // The stress 2η V_c sym(∇v) times dt, per cell.
        stress.resize(self.cells.len(), Mat3::zeros());
        stress
            .par_iter_mut()
            .with_min_len(PARALLEL_MIN_LEN)
            .zip(&self.cells)
            .for_each(|(s, cell)| *s = self.cell_strain_rate(cell, v) * (self.scale * cell.volume));
        let stress = &*stress;
        out.par_iter_mut()
            .with_min_len(PARALLEL_MIN_LEN)
            .enumerate()
            .for_each(|(n, o)| {
                let mut f = v[n] * self.mass[n];
                for &(c, q) in &self.node_cells[n] {
                    if c != NONE {
                        f += stress[c as usize] * self.gradients[q as usize];
                    }
                }
                *o = f;
            });
    }

    /// Solves (M + dt K) x = b, starting from `x`; returns the iterations.
    /// The vector updates and dot products run serially in one fused
    /// loop each: they cost little next to `apply`, and a serial sum does
    /// not depend on the thread count.
    pub(crate) fn solve(&self, b: &[Vec3<T>], x: &mut [Vec3<T>], cg: &mut CgBuffers<T>) -> usize {
        let n = self.nodes.len();
        let tolerance = T::lit(1e1) * T::default_epsilon() * dot(b, b).sqrt();
        let CgBuffers { r, z, p, q, stress } = cg;
        for buffer in [&mut *r, &mut *z, &mut *p, &mut *q] {
            buffer.clear();
            buffer.resize(n, Vec3::zeros());
        }
        self.apply(x, stress, r);
        let (mut rz, mut rr) = (T::zero(), T::zero());
        for i in 0..n {
            r[i] = b[i] - r[i];
            z[i] = r[i] / self.diagonal[i];
            p[i] = z[i];
            rz += r[i].dot(&z[i]);
            rr += r[i].norm_squared();
        }
        for iteration in 0..MAX_ITERATIONS {
            if rr.sqrt() <= tolerance {
                return iteration;
            }
            self.apply(p, stress, q);
            let pq = dot(p, q);
            if pq <= T::zero() {
                return iteration;
            }
            let alpha = rz / pq;
            let (mut rz_next, mut rr_next) = (T::zero(), T::zero());
            for i in 0..n {
                x[i] += p[i] * alpha;
                r[i] -= q[i] * alpha;
                z[i] = r[i] / self.diagonal[i];
                rz_next += r[i].dot(&z[i]);
                rr_next += r[i].norm_squared();
            }
            let beta = rz_next / rz;
            (rz, rr) = (rz_next, rr_next);
            for i in 0..n {
                p[i] = z[i] + p[i] * beta;
            }
        }
        MAX_ITERATIONS
    }
}

/// Σ a·b, serially.
fn dot<T: Real>(a: &[Vec3<T>], b: &[Vec3<T>]) -> T {
    a.iter().zip(b).fold(T::zero(), |s, (a, b)| s + a.dot(b))
}

impl<T: Real> ViscousSolver<T> {
    /// The viscous solve of `grid` (lanes `[u, m]`, empty nodes zero):
    /// fills `system`, `u` and `v` (per unknown). False, and nothing to
    /// apply, when η = 0 or no cell is full.
    pub(crate) fn solve_grid(&mut self, k: &Consts<T>, grid: &Grid<T>) -> bool {
        if k.viscosity == T::zero() {
            return false;
        }
        self.system.rebuild(k, grid);
        if self.system.cells.is_empty() {
            return false;
        }
        let system = &self.system;
        self.u.clear();
        self.u.extend(system.nodes.iter().map(|&g| {
            let a = grid.nodes[g].to_array();
            Vec3::new(a[0], a[1], a[2])
        }));
        self.b.clear();
        self.b
            .extend(self.u.iter().zip(&system.mass).map(|(u, m)| u * *m));
        self.v.clone_from(&self.u);
        system.solve(&self.b, &mut self.v, &mut self.cg);
        true
    }
}

/// Replaces the node velocities of `grid` (lanes `[u, m]`, empty nodes
/// zero) by the viscous solve's v. No-op when η = 0 or no cell is full.
pub fn viscosity_solve<T: Real>(k: &Consts<T>, grid: &mut Grid<T>, solver: &mut ViscousSolver<T>) {
    if solver.solve_grid(k, grid) {
        let system = &solver.system;
        for ((&g, v), &m) in system.nodes.iter().zip(&solver.v).zip(&system.mass) {
            grid.nodes[g] = T::Lane4::from_array([v.x, v.y, v.z, m]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::PhysicsConfig;

    /// Same relative tolerance as the solve's own stopping rule, with room
    /// for the round-off of a few hundred unknowns.
    const SOLVE_RTOL: f64 = 1e-12;

    /// A 6³-node block of full nodes (mass ρ dx³) inside a 12³ grid, with
    /// node velocities from `velocity(position)`; η such that
    /// dt η / (ρ dx²) = 3.
    fn block(velocity: impl Fn(Vec3<f64>) -> Vec3<f64>) -> (Consts<f64>, Grid<f64>) {
        let mut config = PhysicsConfig::volumetric([0.0; 3], 1.0, [0.0, 0.0, 1.0]);
        config.grid_res = 12;
        config.dt = 1e-3;
        config.density = 1000.0;
        let dx = config.dx();
        config.effects.viscosity = 3.0 * config.density * dx * dx / config.dt;
        let node_mass = config.density * dx * dx * dx;
        let k = Consts::new(&config, node_mass);
        let mut grid = Grid::new(12);
        for i in 3..9 {
            for j in 3..9 {
                for l in 3..9 {
                    let x = Vec3::new(i as f64, j as f64, l as f64) * dx;
                    let v = velocity(x);
                    let g = grid.index(i, j, l);
                    // Uneven masses, as at an object's surface.
                    let m = node_mass * (0.5 + 0.1 * ((i + 2 * j + 3 * l) % 5) as f64);
                    grid.nodes[g] = Lane4::from_array([v.x, v.y, v.z, m]);
                }
            }
        }
        (k, grid)
    }

    fn velocities(grid: &Grid<f64>) -> Vec<(Vec3<f64>, f64)> {
        grid.nodes
            .iter()
            .map(|n| {
                let n = n.to_array();
                (Vec3::new(n[0], n[1], n[2]), n[3])
            })
            .collect()
    }

    #[test]
    fn rigid_motion_is_not_damped() {
        let omega = Vec3::new(0.3, -1.2, 0.7);
        let rigid = |x: Vec3<f64>| Vec3::new(0.1, 0.0, -0.2) + omega.cross(&x);
        let (k, mut grid) = block(rigid);
        let before = velocities(&grid);
        viscosity_solve(&k, &mut grid, &mut ViscousSolver::default());
        for ((v, _), (u, _)) in velocities(&grid).iter().zip(&before) {
            assert!(
                (v - u).norm() <= SOLVE_RTOL * (1.0 + u.norm()),
                "{v} vs {u}"
            );
        }
    }

    #[test]
    fn shear_keeps_momentum_and_loses_kinetic_energy() {
        let shear = |x: Vec3<f64>| Vec3::new((6.0 * x.z).sin(), 0.0, 0.3 * x.x);
        let (k, mut grid) = block(shear);
        let before = velocities(&grid);
        viscosity_solve(&k, &mut grid, &mut ViscousSolver::default());
        let after = velocities(&grid);
        let momentum =
            |s: &[(Vec3<f64>, f64)]| s.iter().fold(Vec3::zeros(), |p, (v, m)| p + v * *m);
        let energy = |s: &[(Vec3<f64>, f64)]| {
            s.iter()
                .map(|(v, m)| 0.5 * m * v.norm_squared())
                .sum::<f64>()
        };
        let (p0, p1) = (momentum(&before), momentum(&after));
        assert!(
            (p1 - p0).norm() <= SOLVE_RTOL * p0.norm().max(1e-3),
            "{p0} → {p1}"
        );
        let (e0, e1) = (energy(&before), energy(&after));
        // A strain-rate field at dt η/(ρ dx²) = 3 loses a visible share.
        assert!(e1 < 0.95 * e0, "kinetic energy {e0} → {e1}");
    }

    #[test]
    fn the_solve_does_not_depend_on_the_thread_count() {
        let shear = |x: Vec3<f64>| Vec3::new((6.0 * x.z).sin(), 0.2 * x.y, 0.3 * x.x);
        let run = |threads: usize| {
            let (k, mut grid) = block(shear);
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool")
                .install(|| viscosity_solve(&k, &mut grid, &mut ViscousSolver::default()));
            grid.nodes.iter().map(|n| n.to_array()).collect::<Vec<_>>()
        };
        assert_eq!(run(1), run(3));
    }
}
