//! Effect terms a fit learns beside the material: the drag and
//! viscosity coefficients, a ground tilt, a stiff ball's factor and a
//! density gradient's excess and axis, where the start model has them
//! switched on.
//! A fit from a bundle has none on and learns none; `dm-diagnose` starts
//! its candidates' fits with one on.
//!
//! The groups step at the effect rate (`--effect-lr`, by default the
//! material rate `--lr`) or fixed multiples of it, so a fit can step its
//! material faster without its effects overshooting.
//!
//! * Coefficients (linear and quadratic drag, viscosity, floor friction)
//!   are stepped as natural logs: they stay positive and each step is
//!   relative (drag spans 1–200 /s, η 3e3–5e4 Pa·s, μ 0.3–0.9);
//!   ∂L/∂ln k = k ∂L/∂k. Friction's ∂L/∂μ comes from the floor's sliding
//!   nodes only (a sticking node's velocity is 0 whatever μ is).
//! * A tilt is gravity turned away from the floor's down direction. It is
//!   learnt as the horizontal components h = (h_e, h_n) of ĝ in the
//!   floor's (east, north) basis, |g| fixed: g = |g| (h_e e + h_n n − c up)
//!   with c = √(1 − |h|²), so ∂g/∂h_e = |g| (e + (h_e/c) up). Its Adam rate
//!   is [`TILT_RATE_FACTOR`] × the effect rate: at 0.1 a step would turn
//!   gravity by ≈ 6°, as much as a whole hidden tilt.
//! * A stiff ball's factor is stepped as its log, at the effect rate
//!   (it spans 8–15 in the tests' draws).
//! * A density gradient's excess a (heavy end 1 + |a| times the light
//!   end) is stepped as itself, total mass kept, at [`DENSITY_RATE_FACTOR`]
//!   × the effect rate: the tests' draws span 2–4 and a quick fit has
//!   four steps. Its axis turns by an angle about the object's
//!   least-spread principal direction (a cloth's normal), so it stays in
//!   the plane of the two main axes the trials start from, at
//!   [`DENSITY_AXIS_RATE_FACTOR`] × the effect rate: a square cloth's
//!   main axis is any in-plane direction. (Stepping the axis's three
//!   components instead let Adam, which normalises each component, turn
//!   a cloth's axis 25° out of its plane on noise: seed 1021.)
//!
//! The gradients are the frame adjoint's `EffectGrads` and mass adjoints
//! (dm-mpm `tape.rs`; f64 finite-difference tests in
//! `crates/dm-mpm/tests/gradients_frame.rs`), chained to the extension's
//! parameters by `dm_model::extension` (its own FD tests).

use crate::optim::{OptimError, ParamSet};
use dm_model::WorldModel;
use dm_mpm::config::horizontal_basis;
use dm_mpm::tape::EffectGrads;
use dm_mpm::{Effects, PhysicsConfig};
use serde::{Deserialize, Serialize};

/// Adam's group of the learnt effect coefficients (natural logs).
pub const EFFECTS_GROUP: &str = "effects_log";
/// Adam's group of the tilt's horizontal components.
pub const TILT_GROUP: &str = "gravity_tilt";
/// The tilt's Adam rate relative to the effect rate (module docs).
pub const TILT_RATE_FACTOR: f64 = 0.2;
/// Adam's group of a stiff ball's log factor.
pub const STIFFNESS_GROUP: &str = "stiff_ball_log_factor";
/// Adam's group of a density gradient's excess.
pub const DENSITY_GROUP: &str = "density_excess";
/// The density excess's Adam rate relative to the effect rate (module
/// docs): 0.3 per step at the default 0.1.
pub const DENSITY_RATE_FACTOR: f64 = 3.0;
/// Adam's group of a density gradient's axis: its turn (radians) from
/// where it is, about the object's least-spread direction.
pub const DENSITY_AXIS_GROUP: &str = "density_axis_turn";
/// The turn's Adam rate relative to the effect rate: 0.2 rad (11°) per
/// step at the default, so a quick fit's four steps can turn a cloth's
/// axis by its 45° of ambiguity.
pub const DENSITY_AXIS_RATE_FACTOR: f64 = 2.0;
/// Adam's group of the particle damping rate's natural log.
pub const DAMPING_GROUP: &str = "particle_damping_log";
/// The damping's Adam rate relative to the effect rate: 0.3 per step at
/// the default, so a quick fit's six material steps can take it from the
/// thin objects' 20 /s down to about 3 /s.
pub const DAMPING_RATE_FACTOR: f64 = 3.0;
/// The lowest learnt particle damping rate, 1/s.
pub const MIN_PARTICLE_DAMPING: f64 = 0.5;
/// Adam's group of the grid's body force: its uniform push, axis drags and
/// spring stiffness, each divided by [`FORCE_FIELD_SCALES`].
pub const FORCE_FIELD_GROUP: &str = "force_field";
/// The body force's Adam rate relative to the effect rate: 0.3 scale
/// units per step at the default.
pub const FORCE_FIELD_RATE_FACTOR: f64 = 3.0;
/// Units of the body force's group, so that one Adam step moves each
/// parameter by a similar share of its plausible range: m/s² for the
/// push (a 6° tilt pulls sideways by 1 m/s²), 10 /s for the axis drags
/// (the thin objects' own damping is 20 /s), 10 /s² for the spring.
pub const FORCE_FIELD_SCALES: [f64; 7] = [1.0, 1.0, 1.0, 10.0, 10.0, 10.0, 10.0];
/// The stiffest learnt axis drag (d dt) and spring (κ dt²) a substep
/// takes: half the stability limit `PhysicsConfig::validate` enforces.
const FORCE_FIELD_STIFFNESS_SHARE: f64 = 0.5;
/// Below this |h| (≈ 0.006°) gravity counts as untilted: the tilt is off.
const TILT_OFF: f64 = 1e-4;

/// A coefficient in `Effects`: how to read, write and differentiate it.
struct Coefficient {
    read: fn(&Effects) -> f64,
    write: fn(&mut Effects, f64),
    gradient: fn(&EffectGrads) -> f64,
}

const COEFFICIENTS: [Coefficient; 4] = [
    Coefficient {
        read: |e| e.air_drag_linear,
        write: |e, v| e.air_drag_linear = v,
        gradient: |g| g.air_drag_linear,
    },
    Coefficient {
        read: |e| e.air_drag_quadratic,
        write: |e, v| e.air_drag_quadratic = v,
        gradient: |g| g.air_drag_quadratic,
    },
    Coefficient {
        read: |e| e.viscosity,
        write: |e, v| e.viscosity = v,
        gradient: |g| g.viscosity,
    },
    Coefficient {
        read: |e| e.floor_friction,
        write: |e, v| e.floor_friction = v,
        gradient: |g| g.floor_friction,
    },
];

fn switched_on(effects: &Effects) -> impl Iterator<Item = &'static Coefficient> + '_ {
    COEFFICIENTS.iter().filter(|c| (c.read)(effects) > 0.0)
}

/// The tilt's frame: the floor's up and horizontal basis, |g| and h.
struct Tilt {
    up: [f64; 3],
    east: [f64; 3],
    north: [f64; 3],
    magnitude: f64,
    h: [f64; 2],
}

impl Tilt {
    /// The tilt of `physics`, when it has a floor and gravity is tilted.
    fn of(physics: &PhysicsConfig) -> Option<Tilt> {
        let up = physics.floor.as_ref()?.up;
        let (east, north) = horizontal_basis(up);
        let g = physics.gravity;
        let magnitude = g.iter().map(|c| c * c).sum::<f64>().sqrt();
        if magnitude == 0.0 {
            return None;
        }
        let along = |d: [f64; 3]| (0..3).map(|a| g[a] * d[a]).sum::<f64>() / magnitude;
        let h = [along(east), along(north)];
        (h[0].hypot(h[1]) > TILT_OFF).then_some(Tilt {
            up,
            east,
            north,
            magnitude,
            h,
        })
    }

    fn gravity(&self, h: [f64; 2]) -> [f64; 3] {
        // |h| < 1 always in practice (tilts of a few degrees); the clamp
        // keeps a wild step from producing NaN.
        let c = (1.0 - h[0] * h[0] - h[1] * h[1]).max(0.0).sqrt();
        std::array::from_fn(|a| {
            self.magnitude * (h[0] * self.east[a] + h[1] * self.north[a] - c * self.up[a])
        })
    }

    fn gradient(&self, grad_g: [f64; 3]) -> [f64; 2] {
        let c = (1.0 - self.h[0] * self.h[0] - self.h[1] * self.h[1])
            .max(1e-12)
            .sqrt();
        let dot = |d: [f64; 3]| (0..3).map(|a| grad_g[a] * d[a]).sum::<f64>();
        let up = dot(self.up);
        [
            self.magnitude * (dot(self.east) + self.h[0] / c * up),
            self.magnitude * (dot(self.north) + self.h[1] / c * up),
        ]
    }
}

/// Gradients of the extension terms a fit learns (`dm_model::extension`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ExtensionGrads {
    /// ∂L/∂ln(factor) of a stiff ball.
    pub stiffness_log_factor: f64,
    /// ∂L/∂excess of a density gradient, total mass kept.
    pub density_excess: f64,
    /// ∂L/∂axis of a density gradient, total mass kept (perpendicular to
    /// the axis).
    pub density_axis: [f64; 3],
}

/// Adam's rates of the learnt effect groups `model` has, for effect rate
/// `learning_rate` (`--effect-lr`; unset, the material rate): the
/// coefficients and a stiff ball's factor step at it, the tilt and the
/// density terms at their fixed multiples of it.
pub fn group_rates(model: &WorldModel, learning_rate: f64) -> Vec<(&'static str, f64)> {
    let mut rates = Vec::new();
    if switched_on(&model.physics.effects).next().is_some() {
        rates.push((EFFECTS_GROUP, learning_rate));
    }
    if model.extension.stiff_ball.is_some() {
        rates.push((STIFFNESS_GROUP, learning_rate));
    }
    if Tilt::of(&model.physics).is_some() {
        rates.push((TILT_GROUP, TILT_RATE_FACTOR * learning_rate));
    }
    if model.extension.density.is_some() {
        rates.push((DENSITY_GROUP, DENSITY_RATE_FACTOR * learning_rate));
        rates.push((DENSITY_AXIS_GROUP, DENSITY_AXIS_RATE_FACTOR * learning_rate));
    }
    rates
}

/// Appends the groups of the switched-on effects of `model` to `params`
/// and their gradients to `grads` (in the same order).
pub fn add_groups(
    model: &WorldModel,
    effect_grads: &EffectGrads,
    extension_grads: &ExtensionGrads,
    params: ParamSet,
    grads: ParamSet,
) -> Result<(ParamSet, ParamSet), OptimError> {
    let (mut params, mut grads) = add_physics_groups(&model.physics, effect_grads, params, grads)?;
    if let Some(ball) = &model.extension.stiff_ball {
        params = params.with_group(STIFFNESS_GROUP, vec![ball.factor.ln()])?;
        grads = grads.with_group(STIFFNESS_GROUP, vec![extension_grads.stiffness_log_factor])?;
    }
    if let Some(density) = &model.extension.density {
        params = params.with_group(DENSITY_GROUP, vec![density.excess])?;
        grads = grads.with_group(DENSITY_GROUP, vec![extension_grads.density_excess])?;
        // The turn is measured from the current axis: always 0 here, and
        // Adam's moments stay those of one consistently signed angle.
        let turn = turn_direction(&model.particles, density.axis);
        let along: f64 = (0..3)
            .map(|a| extension_grads.density_axis[a] * turn[a])
            .sum();
        params = params.with_group(DENSITY_AXIS_GROUP, vec![0.0])?;
        grads = grads.with_group(DENSITY_AXIS_GROUP, vec![along])?;
    }
    Ok((params, grads))
}

/// [`add_groups`]' groups of the terms in `physics` (drag, viscosity, tilt).
fn add_physics_groups(
    physics: &PhysicsConfig,
    effect_grads: &EffectGrads,
    params: ParamSet,
    grads: ParamSet,
) -> Result<(ParamSet, ParamSet), OptimError> {
    let (logs, log_grads): (Vec<f64>, Vec<f64>) = switched_on(&physics.effects)
        .map(|c| {
            let value = (c.read)(&physics.effects);
            (value.ln(), value * (c.gradient)(effect_grads))
        })
        .unzip();
    let (mut params, mut grads) = (params, grads);
    if !logs.is_empty() {
        params = params.with_group(EFFECTS_GROUP, logs)?;
        grads = grads.with_group(EFFECTS_GROUP, log_grads)?;
    }
    if let Some(tilt) = Tilt::of(physics) {
        params = params.with_group(TILT_GROUP, tilt.h.to_vec())?;
        grads = grads.with_group(TILT_GROUP, tilt.gradient(effect_grads.gravity).to_vec())?;
    }
    Ok((params, grads))
}

/// Writes the stepped groups of [`add_groups`] back into `model`.
pub fn write_back(model: &mut WorldModel, params: &ParamSet) {
    write_back_physics(&mut model.physics, params);
    if let (Some(ball), Some(&[log])) = (
        model.extension.stiff_ball.as_mut(),
        params.get(STIFFNESS_GROUP),
    ) {
        // The ball stays at least as stiff as the rest (the candidate's
        // model: a stiffer region).
        ball.factor = log.exp().max(1.0);
    }
    if let Some(&[excess]) = params.get(DENSITY_GROUP) {
        model
            .extension
            .set_density_excess(&model.particles, excess, &mut model.physics.density);
    }
    if let (Some(&[angle]), Some(density)) = (
        params.get(DENSITY_AXIS_GROUP),
        model.extension.density.as_ref(),
    ) {
        let axis = density.axis;
        let turn = turn_direction(&model.particles, axis);
        let turned = std::array::from_fn(|a| angle.cos() * axis[a] + angle.sin() * turn[a]);
        model
            .extension
            .set_density_axis(&model.particles, turned, &mut model.physics.density);
    }
}

/// The unit direction a positive turn moves `axis` toward: about the
/// particles' least-spread principal direction n, b = n × axis
/// (normalised; zero when the axis is along n).
fn turn_direction(particles: &[[f64; 3]], axis: [f64; 3]) -> [f64; 3] {
    use nalgebra::{Matrix3, Vector3};
    let count = particles.len().max(1) as f64;
    let mean = particles
        .iter()
        .fold(Vector3::zeros(), |m, p| m + Vector3::from(*p))
        / count;
    let covariance = particles.iter().fold(Matrix3::zeros(), |c, p| {
        let d = Vector3::from(*p) - mean;
        c + d * d.transpose()
    }) / count;
    let eigen = covariance.symmetric_eigen();
    let least = eigen.eigenvalues.imin();
    let mut normal: Vector3<f64> = eigen.eigenvectors.column(least).into_owned();
    // A fixed sign, so a turn's sense is the same at every step.
    let largest = normal.iamax();
    if normal[largest] < 0.0 {
        normal = -normal;
    }
    let b = normal.cross(&Vector3::from(axis));
    let length = b.norm();
    if length < 1e-9 {
        return [0.0; 3];
    }
    (b / length).into()
}

/// Appends the particle damping rate's group (its natural log) to
/// `params` and its gradient to `grads`.
pub fn add_damping_group(
    physics: &PhysicsConfig,
    effect_grads: &EffectGrads,
    params: ParamSet,
    grads: ParamSet,
) -> Result<(ParamSet, ParamSet), OptimError> {
    let rate = physics.particle_damping.max(MIN_PARTICLE_DAMPING);
    Ok((
        params.with_group(DAMPING_GROUP, vec![rate.ln()])?,
        grads.with_group(DAMPING_GROUP, vec![rate * effect_grads.particle_damping])?,
    ))
}

/// Writes the stepped damping back, within [`MIN_PARTICLE_DAMPING`] and
/// `ceiling` (the category's default): a fit may remove damping the
/// object does not have, but adds none — extra drag is an effect for the
/// diagnosis to name, not a setting to absorb.
pub fn write_back_damping(physics: &mut PhysicsConfig, params: &ParamSet, ceiling: f64) {
    if let Some(&[log]) = params.get(DAMPING_GROUP) {
        physics.particle_damping = log
            .exp()
            .clamp(MIN_PARTICLE_DAMPING, ceiling.max(MIN_PARTICLE_DAMPING));
    }
}

/// Which of the body force's seven terms a fit steps, in
/// [`ForceFieldTerms::NAMES`]' order; the others keep the model's values.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ForceFieldTerms(pub [bool; 7]);

impl ForceFieldTerms {
    pub const NONE: Self = Self([false; 7]);
    pub const ALL: Self = Self([true; 7]);
    /// The terms: the push along each world axis, the drag along each,
    /// the spring towards the attractor point.
    pub const NAMES: [&'static str; 7] = [
        "push_x", "push_y", "push_z", "drag_x", "drag_y", "drag_z", "spring",
    ];
    /// Their units.
    pub const UNITS: [&'static str; 7] = ["m/s²", "m/s²", "m/s²", "1/s", "1/s", "1/s", "1/s²"];

    pub fn any(self) -> bool {
        self.0.iter().any(|&on| on)
    }

    /// Indices of the terms switched on.
    pub fn indices(self) -> impl Iterator<Item = usize> {
        (0..7).filter(move |&i| self.0[i])
    }
}

/// The body force's seven terms' values, in [`ForceFieldTerms::NAMES`]'
/// order.
pub fn force_field_values(field: &dm_mpm::ForceField) -> [f64; 7] {
    let [ux, uy, uz] = field.uniform;
    let [dx, dy, dz] = field.axis_drag;
    [ux, uy, uz, dx, dy, dz, field.attractor_stiffness]
}

/// Sets term `i` (in [`ForceFieldTerms::NAMES`]' order) of `field`.
pub fn set_force_field_value(field: &mut dm_mpm::ForceField, i: usize, value: f64) {
    match i {
        0..=2 => field.uniform[i] = value,
        3..=5 => field.axis_drag[i - 3] = value,
        _ => field.attractor_stiffness = value,
    }
}

/// Appends the switched-on body-force terms' group (each divided by its
/// [`FORCE_FIELD_SCALES`]) to `params` and their gradients to `grads`:
/// ∂L/∂θ = scale ∂L/∂parameter.
pub fn add_force_field_group(
    physics: &PhysicsConfig,
    effect_grads: &EffectGrads,
    terms: ForceFieldTerms,
    params: ParamSet,
    grads: ParamSet,
) -> Result<(ParamSet, ParamSet), OptimError> {
    let values = force_field_values(&physics.effects.force_field);
    // EffectGrads carries ∂L/∂(each term) in the field's own layout.
    let gradients = force_field_values(&effect_grads.force_field);
    Ok((
        params.with_group(
            FORCE_FIELD_GROUP,
            terms
                .indices()
                .map(|i| values[i] / FORCE_FIELD_SCALES[i])
                .collect(),
        )?,
        grads.with_group(
            FORCE_FIELD_GROUP,
            terms
                .indices()
                .map(|i| gradients[i] * FORCE_FIELD_SCALES[i])
                .collect(),
        )?,
    ))
}

/// Writes the stepped body-force terms back, each made admissible
/// ([`admissible_force_field_value`]).
pub fn write_back_force_field(
    physics: &mut PhysicsConfig,
    params: &ParamSet,
    terms: ForceFieldTerms,
) {
    let Some(scaled) = params.get(FORCE_FIELD_GROUP) else {
        return;
    };
    for (&theta, i) in scaled.iter().zip(terms.indices()) {
        let value = admissible_force_field_value(physics, i, theta * FORCE_FIELD_SCALES[i]);
        set_force_field_value(&mut physics.effects.force_field, i, value);
    }
}

/// `value` for term `i` of the body force within what `physics`' substep
/// takes: drags and the spring non-negative (a negative one would feed
/// energy in) and within [`FORCE_FIELD_STIFFNESS_SHARE`] of the stability
/// limit `PhysicsConfig::validate` enforces.
pub fn admissible_force_field_value(physics: &PhysicsConfig, i: usize, value: f64) -> f64 {
    let dt = physics.dt;
    match i {
        0..=2 => value,
        3..=5 => value.clamp(0.0, FORCE_FIELD_STIFFNESS_SHARE / dt),
        _ => value.clamp(0.0, FORCE_FIELD_STIFFNESS_SHARE / (dt * dt)),
    }
}

/// [`write_back`] of the terms in `physics`.
fn write_back_physics(physics: &mut PhysicsConfig, params: &ParamSet) {
    if let Some(logs) = params.get(EFFECTS_GROUP) {
        let on: Vec<&Coefficient> = switched_on(&physics.effects).collect();
        for (c, log) in on.into_iter().zip(logs) {
            (c.write)(&mut physics.effects, log.exp());
        }
    }
    if let (Some(tilt), Some(h)) = (Tilt::of(physics), params.get(TILT_GROUP))
        && h.len() == 2
    {
        physics.gravity = tilt.gravity([h[0], h[1]]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tilted(h: [f64; 2]) -> PhysicsConfig {
        let mut physics = PhysicsConfig::volumetric([0.0; 3], 1.0, [0.0, 0.0, 1.0]);
        let tilt = Tilt {
            up: [0.0, 0.0, 1.0],
            east: [1.0, 0.0, 0.0],
            north: [0.0, 1.0, 0.0],
            magnitude: 9.81,
            h,
        };
        physics.gravity = tilt.gravity(h);
        physics
    }

    #[test]
    fn tilt_round_trips_through_its_components() {
        let physics = tilted([0.08, -0.05]);
        let tilt = Tilt::of(&physics).expect("tilted");
        assert!((tilt.h[0] - 0.08).abs() < 1e-12 && (tilt.h[1] + 0.05).abs() < 1e-12);
        assert!((tilt.magnitude - 9.81).abs() < 1e-12);
        assert!(Tilt::of(&tilted([0.0, 0.0])).is_none(), "untilted is off");
    }

    /// ∂L/∂h by the chain rule against central differences of a linear
    /// L(g) = a·g through the map h ↦ g; FD step 1e-6 on components
    /// ≈ 0.1, so 1e-8 relative leaves the O(h²) truncation far below.
    #[test]
    fn tilt_gradient_matches_finite_differences() {
        const FD_RTOL: f64 = 1e-8;
        let a = [0.3, -1.2, 0.7];
        let physics = tilted([0.08, -0.05]);
        let tilt = Tilt::of(&physics).expect("tilted");
        let analytic = tilt.gradient(a);
        for k in 0..2 {
            let loss = |d: f64| {
                let mut h = tilt.h;
                h[k] += d;
                let g = tilt.gravity(h);
                (0..3).map(|i| a[i] * g[i]).sum::<f64>()
            };
            let numeric = (loss(1e-6) - loss(-1e-6)) / 2e-6;
            let rel = (analytic[k] - numeric).abs() / numeric.abs();
            assert!(rel < FD_RTOL, "h[{k}]: {} vs {numeric}", analytic[k]);
        }
    }

    /// A density axis turns within the plane of a flat object, in a sense
    /// fixed by the particles alone.
    #[test]
    fn density_axis_turns_within_a_flat_objects_plane() {
        let particles: Vec<[f64; 3]> = (0..50)
            .map(|i| {
                let t = f64::from(i);
                [
                    0.2 * (t * 0.37).sin(),
                    0.15 * (t * 0.73).cos(),
                    0.002 * (t * 1.3).sin(),
                ]
            })
            .collect();
        let b = turn_direction(&particles, [1.0, 0.0, 0.0]);
        assert!(b[2].abs() < 0.05, "stays in the plane: {b:?}");
        assert!((b[1].abs() - 1.0).abs() < 0.01, "turns toward y: {b:?}");
        let flipped: Vec<[f64; 3]> = particles.iter().map(|p| [p[0], p[1], -p[2]]).collect();
        assert_eq!(
            turn_direction(&flipped, [1.0, 0.0, 0.0])[1].signum(),
            b[1].signum()
        );
        assert_eq!(turn_direction(&particles, [0.0, 0.0, 1.0])[2], 0.0);
    }

    #[test]
    fn groups_round_trip_and_untouched_effects_stay_off() {
        let mut physics = tilted([0.1, 0.0]);
        physics.effects.air_drag_quadratic = 150.0;
        let (params, grads) = add_physics_groups(
            &physics,
            &EffectGrads::default(),
            ParamSet::new(),
            ParamSet::new(),
        )
        .expect("groups");
        assert_eq!(params.get(EFFECTS_GROUP).map(<[f64]>::len), Some(1));
        assert_eq!(grads.get(TILT_GROUP).map(<[f64]>::len), Some(2));
        let before = physics.clone();
        write_back_physics(&mut physics, &params);
        assert!((physics.effects.air_drag_quadratic - 150.0).abs() < 1e-9);
        assert_eq!(physics.effects.air_drag_linear, 0.0);
        for a in 0..3 {
            assert!((physics.gravity[a] - before.gravity[a]).abs() < 1e-12);
        }
    }

    /// The damping group holds ln c with gradient c ∂L/∂c, and writing it
    /// back keeps c within [MIN_PARTICLE_DAMPING, the category default].
    #[test]
    fn damping_group_is_the_log_rate_and_stays_below_the_default() {
        let mut physics = PhysicsConfig::thin_object([0.0; 3], 1.0, [0.0, 0.0, 1.0]);
        let grads = EffectGrads {
            particle_damping: -0.25,
            ..EffectGrads::default()
        };
        let (params, g) =
            add_damping_group(&physics, &grads, ParamSet::new(), ParamSet::new()).expect("group");
        assert_eq!(params.get(DAMPING_GROUP), Some(&[20f64.ln()][..]));
        assert_eq!(g.get(DAMPING_GROUP), Some(&[20.0 * -0.25][..]));
        let set = |log: f64| {
            ParamSet::new()
                .with_group(DAMPING_GROUP, vec![log])
                .expect("set")
        };
        write_back_damping(&mut physics, &set(5f64.ln()), 20.0);
        assert!((physics.particle_damping - 5.0).abs() < 1e-12);
        write_back_damping(&mut physics, &set(40f64.ln()), 20.0);
        assert_eq!(physics.particle_damping, 20.0, "never above the default");
        write_back_damping(&mut physics, &set(-10.0), 20.0);
        assert_eq!(physics.particle_damping, MIN_PARTICLE_DAMPING);
    }
}
