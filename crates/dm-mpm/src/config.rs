//! Simulation settings. One struct is both the run record saved beside
//! outputs and the defaults of method.md §2.

use serde::{Deserialize, Serialize};

/// A ground plane: nodes at or below `height + margin` along `up` cannot
/// move into it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FloorConfig {
    /// Unit vector pointing up (away from the floor).
    pub up: [f64; 3],
    /// Height of the plane along `up`, metres (world frame).
    pub height: f64,
    /// Extra thickness of the collision layer, metres.
    pub margin: f64,
}

/// Physical effects beyond the base model. The synthetic generator hides
/// them in ground truth; the diagnosis stage adds them back as learnable
/// terms. All zero / `None` means the base model of method.md.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Effects {
    /// Linear air drag, 1/s: a = -k v.
    pub air_drag_linear: f64,
    /// Quadratic air drag, 1/m: a = -k |v| v.
    pub air_drag_quadratic: f64,
    /// Coulomb friction coefficient on the floor (0 = frictionless slip).
    pub floor_friction: f64,
    /// Plastic yield: singular values of F are projected into
    /// [1/(1+y), 1+y], so deformation beyond y is permanent.
    pub plastic_yield: Option<f64>,
    /// Viscous (strain-rate) damping η, Pa·s: Cauchy stress 2η sym(∇v),
    /// solved implicitly on the grid each substep (`viscosity.rs`), so
    /// stable at any η. (An explicit viscous stress would be stable only
    /// for η ≲ ρ dx² / (6 dt), ≈ 40 Pa·s on the model's grid, where it
    /// moves nothing visible.)
    pub viscosity: f64,
    /// An open-ended body force per unit mass on the grid (a uniform push,
    /// drag along world axes, a spring towards a point); all zero by
    /// default and then left out of a saved model.
    #[serde(skip_serializing_if = "ForceField::is_zero")]
    pub force_field: ForceField,
}

/// A body force per unit mass applied to every grid node with mass, world
/// frame: a(x, v) = uniform − axis_drag ∘ v − attractor_stiffness (x −
/// attractor_point), with v the node's velocity before gravity.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ForceField {
    /// Uniform acceleration, m/s² (e.g. a steady wind's push per unit mass).
    pub uniform: [f64; 3],
    /// Drag rate along each world axis, 1/s: a_i = −d_i v_i.
    pub axis_drag: [f64; 3],
    /// Stiffness of a spring pulling towards `attractor_point`, 1/s².
    pub attractor_stiffness: f64,
    /// The point the spring pulls towards, metres (world frame).
    pub attractor_point: [f64; 3],
}

impl ForceField {
    /// Whether the field exerts no force anywhere.
    pub fn is_zero(&self) -> bool {
        self.uniform == [0.0; 3] && self.axis_drag == [0.0; 3] && self.attractor_stiffness == 0.0
    }
}

/// The time over which [`PhysicsConfig::grid_damping`] applies once:
/// method.md §2's substep, where its 0.999 per substep was set.
pub const GRID_DAMPING_REFERENCE_DT: f64 = 8e-4;

/// The finest grid a world may have (cells per axis).
pub const MAX_GRID_RES: usize = 512;

/// Everything the MPM world needs besides particles, material and actuators.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PhysicsConfig {
    /// Grid cells per axis.
    pub grid_res: usize,
    /// World position of grid node (0, 0, 0), metres.
    pub domain_origin: [f64; 3],
    /// Edge length of the cubic domain, metres.
    pub domain_size: f64,
    /// Substep, seconds.
    pub dt: f64,
    /// Substeps per video frame.
    pub substeps_per_frame: usize,
    /// Gravity, m/s^2, world frame.
    pub gravity: [f64; 3],
    /// Particle velocity damping rate, 1/s (v *= exp(-rate dt) per substep).
    pub particle_damping: f64,
    /// Grid velocity factor per [`GRID_DAMPING_REFERENCE_DT`] (method.md:
    /// 0.999 per 8e-4 s substep, 1.25 /s). A substep of length dt applies
    /// it to the power dt / 8e-4 s, so the damping per second does not
    /// change when the CFL bound refines the substep for a stiffer
    /// material, nor with a finer grid or another substep count.
    pub grid_damping: f64,
    /// Thickness of the slip walls at the domain faces, cells.
    pub wall_cells: usize,
    /// Particle positions are clipped to this fraction range of the domain.
    pub position_clip: [f64; 2],
    /// Optional ground plane.
    pub floor: Option<FloorConfig>,
    /// Singular values of F are clamped into this range every substep.
    pub svd_clamp: [f64; 2],
    /// Rest density of the material, kg/m^3.
    pub density: f64,
    /// Grid nodes lighter than this fraction of the mean particle mass are
    /// treated as empty (their velocity division is ill-conditioned).
    pub empty_node_mass_ratio: f64,
    /// Extra physics (hidden effects / diagnosis extensions).
    pub effects: Effects,
    /// Courant number bound on the elastic wave speed: when the stiffest
    /// material would need `dt > cfl · dx / c`, the world splits each frame
    /// into more, shorter substeps (frame time unchanged). `None` keeps
    /// `dt` fixed (benchmarks comparing with fixed-step peers).
    pub cfl: Option<f64>,
}

/// Courant number of the substep bound for the model's worlds: stable at
/// the stiff ends of both material bounds with margin (0.6 and 0.7 ran
/// too), and within 0.1 mm of 0.3's training-frame track error on fitted
/// scenes, at 40 % fewer substeps (docs/decisions/0004).
pub const DEFAULT_CFL: f64 = 0.5;

impl PhysicsConfig {
    /// Defaults for thin objects (ropes: linear, cloths: planar), method.md §2.
    pub fn thin_object(domain_origin: [f64; 3], domain_size: f64, up: [f64; 3]) -> Self {
        Self::with_category_numbers(domain_origin, domain_size, up, 20.0, 0.0)
    }

    /// Defaults for volumetric objects (plush toys), method.md §2.
    pub fn volumetric(domain_origin: [f64; 3], domain_size: f64, up: [f64; 3]) -> Self {
        Self::with_category_numbers(domain_origin, domain_size, up, 5.0, 0.05)
    }

    fn with_category_numbers(
        domain_origin: [f64; 3],
        domain_size: f64,
        up: [f64; 3],
        particle_damping: f64,
        floor_margin_fraction: f64,
    ) -> Self {
        let g = 9.8;
        Self {
            grid_res: 32,
            domain_origin,
            domain_size,
            dt: 8e-4,
            substeps_per_frame: 42,
            gravity: [-g * up[0], -g * up[1], -g * up[2]],
            particle_damping,
            grid_damping: 0.999,
            wall_cells: 3,
            position_clip: [0.05, 0.95],
            floor: Some(FloorConfig {
                up,
                height: 0.0,
                margin: floor_margin_fraction * domain_size / 32.0,
            }),
            svd_clamp: [0.5, 2.0],
            density: 1000.0,
            empty_node_mass_ratio: 1e-4,
            effects: Effects::default(),
            cfl: Some(DEFAULT_CFL),
        }
    }

    /// The substep count and length keeping the frame time
    /// `dt · substeps_per_frame` and satisfying the CFL bound for elastic
    /// waves of speed `max_wave_speed` (m/s).
    pub fn stable_substeps(&self, max_wave_speed: f64) -> (usize, f64) {
        let frame_time = self.dt * self.substeps_per_frame as f64;
        match self.cfl {
            Some(cfl) if max_wave_speed > 0.0 => {
                let dt_max = cfl * self.dx() / max_wave_speed;
                if self.dt <= dt_max {
                    (self.substeps_per_frame, self.dt)
                } else {
                    let n = (frame_time / dt_max).ceil() as usize;
                    (n, frame_time / n as f64)
                }
            }
            _ => (self.substeps_per_frame, self.dt),
        }
    }

    /// Grid spacing, metres.
    pub fn dx(&self) -> f64 {
        self.domain_size / self.grid_res as f64
    }

    /// Checks the numbers a user could get wrong; names the field.
    /// A model file's grid is bounded ([`MAX_GRID_RES`]) so that a damaged
    /// or hostile one is refused instead of allocating without limit.
    pub fn validate(&self) -> Result<(), crate::SimError> {
        let bad = |field: &str, why: &str| {
            Err(crate::SimError::InvalidConfig {
                field: field.to_string(),
                problem: why.to_string(),
            })
        };
        if self.grid_res < 8 {
            return bad("grid_res", "must be at least 8");
        }
        if self.grid_res > MAX_GRID_RES {
            return bad(
                "grid_res",
                "must be at most 512 (a 512³ grid already takes 2 GiB per copy)",
            );
        }
        if !(self.domain_size.is_finite() && self.domain_size > 0.0) {
            return bad("domain_size", "must be positive");
        }
        if !(self.dt.is_finite() && self.dt > 0.0) {
            return bad("dt", "must be positive");
        }
        if self.substeps_per_frame == 0 {
            return bad("substeps_per_frame", "must be at least 1");
        }
        // Saturating: a huge value read from a file must not wrap to a small one.
        if self.wall_cells.saturating_mul(2).saturating_add(4) > self.grid_res {
            return bad("wall_cells", "walls leave no interior");
        }
        let [lo, hi] = self.position_clip;
        let min_clip = 1.5 / self.grid_res as f64;
        // Strict at the top: a particle exactly 1.5 cells below the top face
        // has its stencil base at res - 2, one node past the grid.
        if !(lo >= min_clip && hi < 1.0 - min_clip && lo < hi) {
            return bad(
                "position_clip",
                "must lie inside the grid by at least 1.5 cells so every stencil fits",
            );
        }
        let [slo, shi] = self.svd_clamp;
        if !(slo > 0.0 && slo <= 1.0 && shi >= 1.0) {
            return bad("svd_clamp", "must satisfy 0 < low <= 1 <= high");
        }
        if self.density.is_nan() || self.density <= 0.0 {
            return bad("density", "must be positive");
        }
        if self.gravity.iter().any(|g| !g.is_finite()) {
            return bad("gravity", "must be finite");
        }
        if let Some(floor) = &self.floor {
            let n = (floor.up[0].powi(2) + floor.up[1].powi(2) + floor.up[2].powi(2)).sqrt();
            if (n - 1.0).abs() > 1e-6 {
                return bad("floor.up", "must be a unit vector");
            }
        }
        let e = &self.effects;
        // A negative coefficient would feed energy in (and make the viscous
        // system indefinite, which conjugate gradients cannot solve).
        for (field, value) in [
            ("effects.air_drag_linear", e.air_drag_linear),
            ("effects.air_drag_quadratic", e.air_drag_quadratic),
            ("effects.floor_friction", e.floor_friction),
            ("effects.viscosity", e.viscosity),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return bad(field, "must be finite and non-negative");
            }
        }
        if let Some(y) = e.plastic_yield
            && !(y.is_finite() && y > 0.0)
        {
            return bad("effects.plastic_yield", "must be finite and positive");
        }
        let field = &e.force_field;
        for (name, values) in [
            ("effects.force_field.uniform", &field.uniform[..]),
            (
                "effects.force_field.attractor_point",
                &field.attractor_point[..],
            ),
        ] {
            if values.iter().any(|v| !v.is_finite()) {
                return bad(name, "must be finite");
            }
        }
        // Negative rates would feed energy in; an explicit drag or spring
        // stiffer than 1/dt (1/dt² for the spring) would overshoot.
        for (name, value, limit) in [
            (
                "effects.force_field.axis_drag",
                field.axis_drag[0],
                1.0 / self.dt,
            ),
            (
                "effects.force_field.axis_drag",
                field.axis_drag[1],
                1.0 / self.dt,
            ),
            (
                "effects.force_field.axis_drag",
                field.axis_drag[2],
                1.0 / self.dt,
            ),
            (
                "effects.force_field.attractor_stiffness",
                field.attractor_stiffness,
                1.0 / (self.dt * self.dt),
            ),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return bad(name, "must be finite and non-negative");
            }
            if value >= limit {
                return bad(
                    name,
                    "is too stiff for the substep (rate × dt must stay below 1)",
                );
            }
        }
        Ok(())
    }
}

/// Two horizontal unit vectors (east, north) completing the unit vector
/// `up` to a right-handed frame; for +z up they are +x and +y, so azimuths
/// read as in the world frame.
pub fn horizontal_basis(up: [f64; 3]) -> ([f64; 3], [f64; 3]) {
    let helper = if up[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let d: f64 = (0..3).map(|a| helper[a] * up[a]).sum();
    let e = [0, 1, 2].map(|a| helper[a] - d * up[a]);
    let len = e.iter().map(|c| c * c).sum::<f64>().sqrt();
    let east = e.map(|c| c / len);
    let north = [
        up[1] * east[2] - up[2] * east[1],
        up[2] * east[0] - up[0] * east[2],
        up[0] * east[1] - up[1] * east[0],
    ];
    (east, north)
}
