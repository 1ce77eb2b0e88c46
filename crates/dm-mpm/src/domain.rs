//! Choosing the simulation domain around a scene.

use crate::config::PhysicsConfig;

/// A cubic domain `(origin, size)` whose usable interior — inside the slip
/// walls and the position clip, with one spare cell — contains the box
/// `[lo, hi]`. The box is centred in the cube.
pub fn cube_domain_containing(
    lo: [f64; 3],
    hi: [f64; 3],
    grid_res: usize,
    wall_cells: usize,
    position_clip: [f64; 2],
) -> ([f64; 3], f64) {
    let margin = position_clip[0]
        .max(1.0 - position_clip[1])
        .max((wall_cells as f64 + 1.0) / grid_res as f64);
    let extent = (0..3).map(|a| hi[a] - lo[a]).fold(1e-6, f64::max);
    let size = extent / (1.0 - 2.0 * margin);
    let origin = [0, 1, 2].map(|a| 0.5 * (lo[a] + hi[a]) - 0.5 * size);
    (origin, size)
}

impl PhysicsConfig {
    /// The box particles stay in, `(lo, hi)`: the domain inside its
    /// position clip.
    pub fn interior(&self) -> ([f64; 3], [f64; 3]) {
        let at = |f: f64| self.domain_origin.map(|o| o + f * self.domain_size);
        (at(self.position_clip[0]), at(self.position_clip[1]))
    }

    /// This configuration in a cube domain that also holds `points`: the
    /// same grid, so coarser cells where the domain grows; unchanged when
    /// the domain's clipped interior already holds them.
    pub fn with_domain_containing(&self, points: &[[f64; 3]]) -> Self {
        let (inner_lo, inner_hi) = self.interior();
        let inside = |p: &[f64; 3]| (0..3).all(|a| p[a] >= inner_lo[a] && p[a] <= inner_hi[a]);
        if points.iter().all(inside) {
            return self.clone();
        }
        let origin = self.domain_origin;
        let mut lo = origin;
        let mut hi = origin.map(|o| o + self.domain_size);
        for p in points {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let (domain_origin, domain_size) =
            cube_domain_containing(lo, hi, self.grid_res, self.wall_cells, self.position_clip);
        Self {
            domain_origin,
            domain_size,
            ..self.clone()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_fits_inside_walls_and_clip() {
        let (lo, hi) = ([-0.3, -0.1, -0.02], [0.2, 0.1, 0.4]);
        let (origin, size) = cube_domain_containing(lo, hi, 32, 3, [0.05, 0.95]);
        let dx = size / 32.0;
        for a in 0..3 {
            assert!(lo[a] >= origin[a] + 4.0 * dx - 1e-12);
            assert!(lo[a] >= origin[a] + 0.05 * size - 1e-12);
            assert!(hi[a] <= origin[a] + size - 4.0 * dx + 1e-12);
        }
    }
}
