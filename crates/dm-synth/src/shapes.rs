//! Object presets: shape (as a signed distance function, sampled on a
//! jittered lattice), texture and category.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// A rope lying on the floor (linear).
    Rope,
    /// A square cloth lying flat (planar).
    Cloth,
    /// A plush toy: body, head and ears (volumetric).
    Toy,
}

impl Preset {
    pub fn name(self) -> &'static str {
        match self {
            Preset::Rope => "rope",
            Preset::Cloth => "cloth",
            Preset::Toy => "toy",
        }
    }

    pub fn category(self) -> dm_bundle::Category {
        match self {
            Preset::Rope => dm_bundle::Category::Linear,
            Preset::Cloth => dm_bundle::Category::Planar,
            Preset::Toy => dm_bundle::Category::Volumetric,
        }
    }

    /// Median Young's modulus (Pa) and Poisson ratio of the truth, inside
    /// the model's bounds for the category (method.md §2).
    pub fn nominal_material(self) -> (f64, f64) {
        match self {
            Preset::Rope => (8e4, 0.25),
            Preset::Cloth => (1.2e5, 0.15),
            Preset::Toy => (4e5, 0.32),
        }
    }

    /// Signed distance (metres; negative inside) of the rest shape. Objects
    /// rest on the floor z = 0.
    pub fn sdf(self, p: [f64; 3]) -> f64 {
        match self {
            Preset::Rope => {
                let (half_len, r) = (0.24, 0.016);
                let x = (p[0].abs() - half_len).max(0.0);
                (x * x + p[1] * p[1] + (p[2] - r) * (p[2] - r)).sqrt() - r
            }
            Preset::Cloth => {
                let (half, thick) = (0.15, 0.012);
                let q = [
                    p[0].abs() - half,
                    p[1].abs() - half,
                    (p[2] - thick / 2.0).abs() - thick / 2.0,
                ];
                let outside = (q.iter().map(|c| c.max(0.0).powi(2)).sum::<f64>()).sqrt();
                outside + q[0].max(q[1]).max(q[2]).min(0.0)
            }
            Preset::Toy => {
                let body = ellipsoid(p, [0.0, 0.0, 0.075], [0.085, 0.07, 0.075]);
                let head = sphere(p, [0.0, 0.0, 0.185], 0.055);
                let ear_l = sphere(p, [0.0, -0.04, 0.235], 0.02);
                let ear_r = sphere(p, [0.0, 0.04, 0.235], 0.02);
                smooth_union(smooth_union(body, head, 0.02), ear_l.min(ear_r), 0.01)
            }
        }
    }

    /// Axis-aligned bounds of the rest shape.
    pub fn bounds(self) -> ([f64; 3], [f64; 3]) {
        match self {
            Preset::Rope => ([-0.26, -0.02, 0.0], [0.26, 0.02, 0.034]),
            Preset::Cloth => ([-0.16, -0.16, 0.0], [0.16, 0.16, 0.014]),
            Preset::Toy => ([-0.09, -0.075, 0.0], [0.09, 0.075, 0.26]),
        }
    }

    /// Albedo at a rest-shape point: stripes on the rope, a checker on the
    /// cloth, a two-tone plush with a light belly patch.
    pub fn albedo(self, p: [f64; 3]) -> [f32; 3] {
        match self {
            Preset::Rope => {
                let twist =
                    (p[0] * 40.0 + (p[2] - 0.016).atan2(p[1])).rem_euclid(std::f64::consts::TAU);
                if twist < std::f64::consts::PI {
                    [0.80, 0.18, 0.15]
                } else {
                    [0.92, 0.88, 0.80]
                }
            }
            Preset::Cloth => {
                let cell = ((p[0] / 0.04).floor() + (p[1] / 0.04).floor()) as i64;
                if cell.rem_euclid(2) == 0 {
                    [0.15, 0.35, 0.75]
                } else {
                    [0.95, 0.80, 0.25]
                }
            }
            Preset::Toy => {
                let belly = ((p[0] - 0.075) / 0.03).powi(2)
                    + (p[1] / 0.045).powi(2)
                    + ((p[2] - 0.07) / 0.05).powi(2);
                let muzzle = ((p[0] - 0.05) / 0.02).powi(2)
                    + (p[1] / 0.025).powi(2)
                    + ((p[2] - 0.175) / 0.02).powi(2);
                if belly < 1.0 || muzzle < 1.0 {
                    [0.90, 0.78, 0.60]
                } else {
                    [0.55, 0.35, 0.20]
                }
            }
        }
    }
}

fn sphere(p: [f64; 3], c: [f64; 3], r: f64) -> f64 {
    ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt() - r
}

/// Approximate SDF of an ellipsoid (scaled sphere, exact on the axes).
fn ellipsoid(p: [f64; 3], c: [f64; 3], r: [f64; 3]) -> f64 {
    let q = [
        (p[0] - c[0]) / r[0],
        (p[1] - c[1]) / r[1],
        (p[2] - c[2]) / r[2],
    ];
    let k = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt();
    (k - 1.0) * r[0].min(r[1]).min(r[2])
}

fn smooth_union(a: f64, b: f64, k: f64) -> f64 {
    let h = (0.5 + 0.5 * (b - a) / k).clamp(0.0, 1.0);
    b * (1.0 - h) + a * h - k * h * (1.0 - h)
}

/// Particles filling a shape: positions, whether each lies on the surface
/// layer, and the lattice spacing used.
#[derive(Clone, Debug)]
pub struct ParticleCloud {
    pub positions: Vec<[f64; 3]>,
    pub on_surface: Vec<bool>,
    pub spacing: f64,
}

impl ParticleCloud {
    /// Fills `preset` with about `target` particles on a jittered lattice.
    /// Particles within 1.2 spacings of the boundary are "surface".
    pub fn fill(preset: Preset, target: usize, seed: u64) -> Self {
        let (lo, hi) = preset.bounds();
        // Estimate the volume by sampling, then choose the lattice spacing.
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_c10d);
        let box_volume: f64 = (0..3).map(|a| hi[a] - lo[a]).product();
        let probes = 20_000;
        let inside = (0..probes)
            .filter(|_| {
                let p = [0, 1, 2].map(|a| lo[a] + (hi[a] - lo[a]) * rng.random::<f64>());
                preset.sdf(p) < 0.0
            })
            .count();
        let volume = box_volume * inside as f64 / probes as f64;
        let mut spacing = (volume / target as f64).cbrt();
        // Thin objects need at least 3 layers through their thickness.
        let thickness = match preset {
            Preset::Rope => 0.032,
            Preset::Cloth => 0.012,
            Preset::Toy => f64::INFINITY,
        };
        spacing = spacing.min(thickness / 3.0);
        let counts = [0, 1, 2].map(|a| ((hi[a] - lo[a]) / spacing).ceil() as usize + 1);
        let jitter = 0.25 * spacing;
        let mut positions = Vec::new();
        let mut on_surface = Vec::new();
        for i in 0..counts[0] {
            for j in 0..counts[1] {
                for k in 0..counts[2] {
                    let base = [i, j, k].map(|n| n as f64 * spacing);
                    let p = [0, 1, 2].map(|a| {
                        lo[a] + 0.5 * spacing + base[a] + jitter * (2.0 * rng.random::<f64>() - 1.0)
                    });
                    let d = preset.sdf(p);
                    if d < 0.0 {
                        positions.push(p);
                        on_surface.push(d > -1.2 * spacing);
                    }
                }
            }
        }
        Self {
            positions,
            on_surface,
            spacing,
        }
    }

    pub fn len(&self) -> usize {
        self.positions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Volume each particle represents.
    pub fn particle_volume(&self) -> f64 {
        self.spacing.powi(3)
    }
}
