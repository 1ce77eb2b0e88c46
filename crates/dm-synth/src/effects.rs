//! Hidden physical effects a synthetic scene can carry, the diagnosis's
//! library among them. `NAME[:MAGNITUDE]` on the CLI.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EffectName {
    /// Linear air drag; magnitude = rate k in a = −k v (1/s).
    AirDrag,
    /// Quadratic air drag; magnitude = k in a = −k |v| v (1/m). Diagnosed
    /// as `air_drag` (the library's drag candidate carries both terms).
    AirDragQuadratic,
    /// Coulomb friction on the floor; magnitude = coefficient μ.
    FloorFriction,
    /// Plastic yield; magnitude = yield stretch y (singular values of F are
    /// kept in [1/(1+y), 1+y], the rest becomes permanent set).
    Plasticity,
    /// A stiffer ball inside the object; magnitude = stiffness factor.
    StiffInclusion,
    /// Strain-rate damping; magnitude = viscosity η (Pa·s) in the Cauchy
    /// stress σ_v = 2η sym(∇v), solved implicitly on the grid (dm-mpm
    /// `viscosity.rs`), so any η is stable.
    ViscousDamping,
    /// Gravity tilted against the recorded ground plane; magnitude = tilt
    /// angle in degrees (azimuth drawn from the seed; the floor stays where
    /// the bundle says).
    GroundTilt,
    /// The recorded hand track lags the hands that drove the object;
    /// magnitude = lag in seconds (recorded(t) = true(t − lag)).
    ActuatorLag,
    /// Mass density varying linearly along the object's longest axis;
    /// magnitude = a, density ∝ 1 + a·s with s from 0 at one end to 1 at
    /// the other (end drawn from the seed), so one end is (1 + a)× heavier.
    DensityVariation,
    /// A steady horizontal push on every particle, outside the diagnosis
    /// library; magnitude = acceleration (m/s²), direction drawn from the
    /// seed.
    Wind,
    /// A spring pulling every particle towards a fixed point, outside the
    /// library; magnitude = stiffness κ in a = −κ (x − p) (1/s²), the point
    /// drawn from the seed beside the object.
    Attractor,
    /// Linear drag along one world axis only, outside the library;
    /// magnitude = rate d in a_i = −d v_i (1/s), the axis drawn from the
    /// seed.
    AnisotropicDrag,
}

impl EffectName {
    /// The diagnosis library's effects (what `dm-diagnose` can name).
    pub const ALL: [EffectName; 9] = [
        EffectName::AirDrag,
        EffectName::AirDragQuadratic,
        EffectName::FloorFriction,
        EffectName::Plasticity,
        EffectName::StiffInclusion,
        EffectName::ViscousDamping,
        EffectName::GroundTilt,
        EffectName::ActuatorLag,
        EffectName::DensityVariation,
    ];

    /// Effects the library has no candidate for: a diagnosis can only
    /// discover them as an open-ended force term.
    pub const OUTSIDE_LIBRARY: [EffectName; 3] = [
        EffectName::Wind,
        EffectName::Attractor,
        EffectName::AnisotropicDrag,
    ];

    /// Whether the diagnosis library has a candidate for this effect.
    pub fn in_library(self) -> bool {
        !Self::OUTSIDE_LIBRARY.contains(&self)
    }

    pub fn name(self) -> &'static str {
        match self {
            EffectName::AirDrag => "air_drag",
            EffectName::AirDragQuadratic => "air_drag_quadratic",
            EffectName::FloorFriction => "floor_friction",
            EffectName::Plasticity => "plasticity",
            EffectName::StiffInclusion => "stiff_inclusion",
            EffectName::ViscousDamping => "viscous_damping",
            EffectName::GroundTilt => "ground_tilt",
            EffectName::ActuatorLag => "actuator_lag",
            EffectName::DensityVariation => "density_variation",
            EffectName::Wind => "wind",
            EffectName::Attractor => "attractor",
            EffectName::AnisotropicDrag => "anisotropic_drag",
        }
    }

    /// The diagnosis library's name for this hidden effect (`air_drag`
    /// covers its linear and quadratic forms; an effect outside the
    /// library keeps its own name, which no candidate has).
    pub fn library_name(self) -> &'static str {
        match self {
            EffectName::AirDragQuadratic => "air_drag",
            other => other.name(),
        }
    }

    /// Magnitude used when none is given: clearly visible in a 2–3 s clip.
    pub fn default_magnitude(self) -> f64 {
        match self {
            EffectName::AirDrag => 4.0,
            EffectName::AirDragQuadratic => 10.0,
            EffectName::FloorFriction => 0.8,
            EffectName::Plasticity => 0.03,
            EffectName::StiffInclusion => 10.0,
            EffectName::ViscousDamping => 1.0e4,
            EffectName::GroundTilt => 6.0,
            EffectName::ActuatorLag => 0.1,
            EffectName::DensityVariation => 3.0,
            EffectName::Wind => 1.0,
            EffectName::Attractor => 10.0,
            EffectName::AnisotropicDrag => 20.0,
        }
    }

    /// The magnitude range the diagnosis tests draw from (docs/diagnose.md
    /// says why each is detectable).
    pub fn test_range(self) -> [f64; 2] {
        match self {
            EffectName::AirDrag => [15.0, 30.0],
            EffectName::AirDragQuadratic => [100.0, 200.0],
            EffectName::FloorFriction => [0.6, 1.0],
            EffectName::Plasticity => [0.02, 0.04],
            EffectName::StiffInclusion => [8.0, 15.0],
            // Kelvin–Voigt times η/E of 0.03–0.4 s on the presets. Below
            // 1e4 a pushed rope moves < 3 mm (docs/RESULTS.md).
            EffectName::ViscousDamping => [1.0e4, 3.0e4],
            EffectName::GroundTilt => [5.0, 10.0],
            EffectName::ActuatorLag => [0.08, 0.15],
            EffectName::DensityVariation => [2.0, 4.0],
            // About the horizontal pull of a 3–9° tilt.
            EffectName::Wind => [0.5, 1.5],
            // 0.5–1.5 m/s² at the point's 0.1 m from the object's centre.
            EffectName::Attractor => [5.0, 15.0],
            // As the library's air drag.
            EffectName::AnisotropicDrag => [15.0, 30.0],
        }
    }

    /// The action a diagnosis test films this effect with, where the
    /// seed's own action would barely excite it: Coulomb friction acts only
    /// while the object slides on the floor (at μ = 0.6 a lifted toy moves
    /// 3.7 mm on average, a pushed one 19.7 mm; docs/RESULTS.md).
    pub fn exciting_action(self) -> Option<crate::Action> {
        match self {
            EffectName::FloorFriction => Some(crate::Action::Push),
            _ => None,
        }
    }
}

/// An effect with its magnitude.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EffectSpec {
    pub name: EffectName,
    pub magnitude: f64,
}

impl std::str::FromStr for EffectSpec {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        let (name, magnitude) = match text.split_once(':') {
            Some((n, m)) => (n, Some(m)),
            None => (text, None),
        };
        let every = EffectName::ALL
            .into_iter()
            .chain(EffectName::OUTSIDE_LIBRARY);
        let name = every.clone().find(|e| e.name() == name).ok_or_else(|| {
            let known: Vec<&str> = every.map(|e| e.name()).collect();
            format!("unknown effect `{name}`; known: {}", known.join(", "))
        })?;
        let magnitude = match magnitude {
            None => name.default_magnitude(),
            Some(m) => m
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite() && *v > 0.0)
                .ok_or_else(|| format!("effect magnitude `{m}` must be a positive number"))?,
        };
        Ok(EffectSpec { name, magnitude })
    }
}

impl std::fmt::Display for EffectSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}:{}", self.name.name(), self.magnitude)
    }
}

impl EffectSpec {
    /// The truth file's `{"name", "params"}` object.
    /// `extra` holds what the truth simulation drew from the seed (the
    /// inclusion's centre, the tilt's gravity, the heavy end's axis).
    pub fn params(
        &self,
        inclusion: Option<([f64; 3], f64)>,
        extra: &BTreeMap<String, serde_json::Value>,
    ) -> BTreeMap<String, serde_json::Value> {
        let mut p = extra.clone();
        let key = match self.name {
            EffectName::AirDrag => "linear_per_s",
            EffectName::AirDragQuadratic => "quadratic_per_m",
            EffectName::FloorFriction => "coefficient",
            EffectName::Plasticity => "yield_stretch",
            EffectName::StiffInclusion => "stiffness_factor",
            EffectName::ViscousDamping => "viscosity_pa_s",
            EffectName::GroundTilt => "tilt_deg",
            EffectName::ActuatorLag => "lag_s",
            EffectName::DensityVariation => "heavy_end_excess",
            EffectName::Wind => "magnitude_m_s2",
            EffectName::Attractor => "stiffness_per_s2",
            EffectName::AnisotropicDrag => "rate_per_s",
        };
        p.insert(key.to_string(), serde_json::json!(self.magnitude));
        if let Some((centre, radius)) = inclusion {
            p.insert("centre_m".into(), serde_json::json!(centre));
            p.insert("radius_m".into(), serde_json::json!(radius));
        }
        p
    }
}

/// A hidden-effect draw for diagnosis tests: a preset, and an
/// effect from the library with a magnitude uniform in its
/// [`EffectName::test_range`] — all from `seed`.
pub fn draw_hidden_effect(seed: u64) -> (crate::Preset, EffectSpec) {
    draw_hidden_effect_among(seed, &EffectName::ALL)
}

/// [`draw_hidden_effect`] among `names` only (the effects a foreign engine
/// can express); with every name it is `draw_hidden_effect` itself.
pub fn draw_hidden_effect_among(seed: u64, names: &[EffectName]) -> (crate::Preset, EffectSpec) {
    use rand::{RngExt, SeedableRng};
    assert!(!names.is_empty(), "an effect to draw from");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(crate::splitmix(seed ^ 0x00e7_7ec7));
    let presets = [
        crate::Preset::Rope,
        crate::Preset::Cloth,
        crate::Preset::Toy,
    ];
    let preset = presets[rng.random_range(0..presets.len())];
    let name = names[rng.random_range(0..names.len())];
    let [lo, hi] = name.test_range();
    let magnitude = lo + (hi - lo) * rng.random::<f64>();
    (preset, EffectSpec { name, magnitude })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_library_name_parses_with_its_default() {
        for name in EffectName::ALL {
            let spec: EffectSpec = name.name().parse().expect("known name");
            assert_eq!(spec.magnitude, name.default_magnitude());
            let [lo, hi] = name.test_range();
            assert!(0.0 < lo && lo < hi, "{}", name.name());
        }
        for name in EffectName::OUTSIDE_LIBRARY {
            let spec: EffectSpec = format!("{}:2", name.name()).parse().expect("known name");
            assert_eq!((spec.name, spec.magnitude), (name, 2.0));
            assert!(!name.in_library());
        }
        assert!("ground_tilt:-3".parse::<EffectSpec>().is_err());
        assert!("gravity_wobble".parse::<EffectSpec>().is_err());
    }

    #[test]
    fn hidden_effect_draws_are_seeded_and_in_range() {
        let mut seen = std::collections::BTreeSet::new();
        for seed in 0..200 {
            let (preset, spec) = draw_hidden_effect(seed);
            assert_eq!((preset, spec), draw_hidden_effect(seed));
            let [lo, hi] = spec.name.test_range();
            assert!(lo <= spec.magnitude && spec.magnitude <= hi);
            seen.insert(spec.name.name());
        }
        assert_eq!(seen.len(), EffectName::ALL.len());
    }

    #[test]
    fn draws_among_some_effects_keep_to_them() {
        let names = [EffectName::GroundTilt, EffectName::AirDrag];
        let mut seen = std::collections::BTreeSet::new();
        for seed in 0..100 {
            let (_, spec) = draw_hidden_effect_among(seed, &names);
            assert!(
                names.contains(&spec.name),
                "seed {seed}: {}",
                spec.name.name()
            );
            seen.insert(spec.name.name());
        }
        assert_eq!(seen.len(), names.len());
    }
}
