//! Particle state as a struct of arrays, and the per-substep constants
//! every solver stage reads.

use crate::config::PhysicsConfig;
use crate::real::{Mat3, Real, Vec3, vec3};

/// Material-point state (method.md §1): position, velocity, deformation
/// gradient F, APIC affine matrix C, plus constant mass and volume.
#[derive(Clone, Debug, PartialEq)]
pub struct Particles<T> {
    pub x: Vec<Vec3<T>>,
    pub v: Vec<Vec3<T>>,
    pub f: Vec<Mat3<T>>,
    pub c: Vec<Mat3<T>>,
    pub mass: Vec<T>,
    pub volume: Vec<T>,
}

impl<T: Real> Particles<T> {
    /// Undeformed particles at rest, each of the given volume and density.
    pub fn at_rest(positions: &[Vec3<T>], volume: T, density: T) -> Self {
        let n = positions.len();
        Self {
            x: positions.to_vec(),
            v: vec![Vec3::zeros(); n],
            f: vec![Mat3::identity(); n],
            c: vec![Mat3::zeros(); n],
            mass: vec![volume * density; n],
            volume: vec![volume; n],
        }
    }

    pub fn len(&self) -> usize {
        self.x.len()
    }

    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// Reorders every array so that slot `i` takes old slot `order[i]`.
    pub fn permute(&mut self, order: &[u32]) {
        fn apply<V: Copy>(values: &mut Vec<V>, order: &[u32]) {
            *values = order.iter().map(|&i| values[i as usize]).collect();
        }
        apply(&mut self.x, order);
        apply(&mut self.v, order);
        apply(&mut self.f, order);
        apply(&mut self.c, order);
        apply(&mut self.mass, order);
        apply(&mut self.volume, order);
    }
}

/// Floor constants in simulation precision.
#[derive(Clone, Copy, Debug)]
pub struct FloorConsts<T> {
    pub up: Vec3<T>,
    /// Nodes with `x·up <= limit` are on the floor.
    pub limit: T,
    pub friction: T,
}

/// The grid's body force (`config::ForceField`) in simulation precision.
#[derive(Clone, Copy, Debug)]
pub struct ForceFieldConsts<T> {
    pub uniform: Vec3<T>,
    pub axis_drag: Vec3<T>,
    pub attractor_stiffness: T,
    pub attractor_point: Vec3<T>,
}

impl<T: Real> ForceFieldConsts<T> {
    /// The acceleration at node position `x` moving at `v`.
    #[inline(always)]
    pub fn accel(&self, x: &Vec3<T>, v: &Vec3<T>) -> Vec3<T> {
        self.uniform
            - self.axis_drag.component_mul(v)
            - (x - self.attractor_point) * self.attractor_stiffness
    }
}

/// Constants of one substep, derived once from the config.
#[derive(Clone, Copy, Debug)]
pub struct Consts<T> {
    pub res: usize,
    pub dt: T,
    pub dx: T,
    pub inv_dx: T,
    pub origin: Vec3<T>,
    pub gravity: Vec3<T>,
    /// Grid velocity factor of one substep of length `dt`.
    pub grid_damping: T,
    /// exp(-particle_damping * dt).
    pub particle_damping_factor: T,
    pub wall_cells: usize,
    pub clip_lo: Vec3<T>,
    pub clip_hi: Vec3<T>,
    pub svd_lo: T,
    pub svd_hi: T,
    pub plastic: Option<(T, T)>,
    pub floor: Option<FloorConsts<T>>,
    pub drag_linear: T,
    pub drag_quadratic: T,
    /// Viscous damping η, Pa·s.
    pub viscosity: T,
    /// Rest density ρ, kg/m³ (the viscous solve's cell volumes, Σm/(8ρ)).
    pub density: T,
    /// Nodes lighter than this are empty.
    pub empty_node_mass: T,
    /// The grid's body force (all zero without one).
    pub force_field: ForceFieldConsts<T>,
    /// Whether it exerts any force: the forward pass skips it otherwise,
    /// while the backward pass always returns its parameters' adjoints
    /// (a fit can learn it from zero).
    pub force_field_on: bool,
}

impl<T: Real> Consts<T> {
    pub fn new(config: &PhysicsConfig, mean_particle_mass: f64) -> Self {
        let dx = config.dx();
        let origin = config.domain_origin;
        let size = config.domain_size;
        let [clo, chi] = config.position_clip;
        let effects = &config.effects;
        Self {
            res: config.grid_res,
            dt: T::lit(config.dt),
            dx: T::lit(dx),
            inv_dx: T::lit(1.0 / dx),
            origin: vec3(origin),
            gravity: vec3(config.gravity),
            grid_damping: T::lit(
                config
                    .grid_damping
                    .powf(config.dt / crate::config::GRID_DAMPING_REFERENCE_DT),
            ),
            particle_damping_factor: T::lit((-config.particle_damping * config.dt).exp()),
            wall_cells: config.wall_cells,
            clip_lo: vec3(origin.map(|o| o + clo * size)),
            clip_hi: vec3(origin.map(|o| o + chi * size)),
            svd_lo: T::lit(config.svd_clamp[0]),
            svd_hi: T::lit(config.svd_clamp[1]),
            plastic: effects
                .plastic_yield
                .map(|y| (T::lit(1.0 / (1.0 + y)), T::lit(1.0 + y))),
            floor: config.floor.as_ref().map(|f| FloorConsts {
                up: vec3(f.up),
                limit: T::lit(f.height + f.margin),
                friction: T::lit(effects.floor_friction),
            }),
            drag_linear: T::lit(effects.air_drag_linear),
            drag_quadratic: T::lit(effects.air_drag_quadratic),
            viscosity: T::lit(effects.viscosity),
            density: T::lit(config.density),
            empty_node_mass: T::lit(config.empty_node_mass_ratio * mean_particle_mass),
            force_field: ForceFieldConsts {
                uniform: vec3(effects.force_field.uniform),
                axis_drag: vec3(effects.force_field.axis_drag),
                attractor_stiffness: T::lit(effects.force_field.attractor_stiffness),
                attractor_point: vec3(effects.force_field.attractor_point),
            },
            force_field_on: !effects.force_field.is_zero(),
        }
    }
}
