//! Hidden physical effects a synthetic scene can carry (issue 2; the
//! diagnosis issue extends the list). `NAME[:MAGNITUDE]` on the CLI.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EffectName {
    /// Linear air drag; magnitude = rate k in a = −k v (1/s).
    AirDrag,
    /// Coulomb friction on the floor; magnitude = coefficient μ.
    FloorFriction,
    /// Plastic yield; magnitude = yield stretch y (singular values of F are
    /// kept in [1/(1+y), 1+y], the rest becomes permanent set).
    Plasticity,
    /// A stiffer ball inside the object; magnitude = stiffness factor.
    StiffInclusion,
}

impl EffectName {
    pub const ALL: [EffectName; 4] = [
        EffectName::AirDrag,
        EffectName::FloorFriction,
        EffectName::Plasticity,
        EffectName::StiffInclusion,
    ];

    pub fn name(self) -> &'static str {
        match self {
            EffectName::AirDrag => "air_drag",
            EffectName::FloorFriction => "floor_friction",
            EffectName::Plasticity => "plasticity",
            EffectName::StiffInclusion => "stiff_inclusion",
        }
    }

    /// Magnitude used when none is given: clearly visible in a 2–3 s clip.
    pub fn default_magnitude(self) -> f64 {
        match self {
            EffectName::AirDrag => 4.0,
            EffectName::FloorFriction => 0.8,
            EffectName::Plasticity => 0.03,
            EffectName::StiffInclusion => 10.0,
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
        let name = EffectName::ALL
            .into_iter()
            .find(|e| e.name() == name)
            .ok_or_else(|| {
                let known: Vec<&str> = EffectName::ALL.iter().map(|e| e.name()).collect();
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
    pub fn params(
        &self,
        inclusion: Option<([f64; 3], f64)>,
    ) -> BTreeMap<String, serde_json::Value> {
        let mut p = BTreeMap::new();
        let key = match self.name {
            EffectName::AirDrag => "linear_per_s",
            EffectName::FloorFriction => "coefficient",
            EffectName::Plasticity => "yield_stretch",
            EffectName::StiffInclusion => "stiffness_factor",
        };
        p.insert(key.to_string(), serde_json::json!(self.magnitude));
        if let Some((centre, radius)) = inclusion {
            p.insert("centre_m".into(), serde_json::json!(centre));
            p.insert("radius_m".into(), serde_json::json!(radius));
        }
        p
    }
}
