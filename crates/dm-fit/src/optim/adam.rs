//! Adam (Kingma & Ba 2015) over a [`ParamSet`], with bias correction.
//!
//! Parameters are stored unbounded (the model maps them through bounded
//! activations), so the update needs no projection. The whole optimiser —
//! configuration, step count and both moment estimates — is serde
//! serialisable: restoring a checkpoint and continuing gives bitwise the same
//! trajectory as never stopping (the update is a fixed sequence of scalar
//! operations; JSON checkpoints need serde_json's `float_roundtrip` feature to
//! read floats back exactly).
//!
//! Gradient clipping is a separate step ([`super::clip`]) applied by the
//! caller before [`Adam::step`].

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::{OptimError, ParamSet};

/// Adam hyper-parameters; defaults β1 0.9, β2 0.999, ε 1e-8, lr 1e-3.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    /// Step size for every group without an entry in `group_learning_rates`.
    pub learning_rate: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub epsilon: f64,
    /// Per-group step sizes (e.g. material fields vs residual network),
    /// keyed by group name; every key must name a group of the parameters.
    #[serde(default)]
    pub group_learning_rates: BTreeMap<String, f64>,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self {
            learning_rate: 1e-3,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            group_learning_rates: BTreeMap::new(),
        }
    }
}

impl AdamConfig {
    /// Defaults with the given global learning rate.
    pub fn with_learning_rate(learning_rate: f64) -> Self {
        Self {
            learning_rate,
            ..Self::default()
        }
    }

    fn validate(&self) -> Result<(), OptimError> {
        let check_lr = |option: &'static str, lr: f64| {
            if lr.is_finite() && lr >= 0.0 {
                Ok(())
            } else {
                Err(OptimError::InvalidOption {
                    option,
                    problem: format!("must be finite and non-negative, got {lr}"),
                })
            }
        };
        check_lr("learning_rate", self.learning_rate)?;
        for &lr in self.group_learning_rates.values() {
            check_lr("group_learning_rates", lr)?;
        }
        for (option, beta) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(0.0..1.0).contains(&beta) {
                return Err(OptimError::InvalidOption {
                    option,
                    problem: format!("must lie in [0, 1), got {beta}"),
                });
            }
        }
        if !(self.epsilon.is_finite() && self.epsilon > 0.0) {
            return Err(OptimError::InvalidOption {
                option: "epsilon",
                problem: format!("must be finite and positive, got {}", self.epsilon),
            });
        }
        Ok(())
    }
}

/// Running moment estimates, laid out like the parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct Moments {
    first: ParamSet,
    second: ParamSet,
}

/// Adam optimiser state (serialisable for checkpoint/resume).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Adam {
    config: AdamConfig,
    step_count: u64,
    /// `None` until the first step, which fixes the parameter layout.
    moments: Option<Moments>,
}

impl Adam {
    /// Checks the settings of an optimiser read from a file, as
    /// [`Adam::new`] checks them (a β₁ of 1, say, would zero the bias
    /// correction).
    pub fn check_config(&self) -> Result<(), OptimError> {
        self.config.validate()
    }

    pub fn new(config: AdamConfig) -> Result<Self, OptimError> {
        config.validate()?;
        Ok(Self {
            config,
            step_count: 0,
            moments: None,
        })
    }

    pub fn config(&self) -> &AdamConfig {
        &self.config
    }

    /// Number of steps taken so far.
    pub fn step_count(&self) -> u64 {
        self.step_count
    }

    /// Changes the global learning rate (schedules); moments are kept.
    pub fn set_learning_rate(&mut self, learning_rate: f64) -> Result<(), OptimError> {
        let mut config = self.config.clone();
        config.learning_rate = learning_rate;
        config.validate()?;
        self.config = config;
        Ok(())
    }

    /// An optimiser with `config` for parameters made of group `name`
    /// alone, carrying on from this one: its step count and its moments
    /// of that group (none if it has not stepped yet). A new stage that
    /// steps only part of the parameters goes on from where the previous
    /// stage left them, instead of a fresh start whose first step moves
    /// every parameter by a full learning rate.
    pub fn continued_for_group(&self, name: &str, config: AdamConfig) -> Result<Self, OptimError> {
        let mut continued = Self::new(config)?;
        if let Some(moments) = &self.moments {
            let only = |set: &ParamSet| -> Result<ParamSet, OptimError> {
                let values = set.get(name).ok_or_else(|| OptimError::LayoutMismatch {
                    detail: format!("the optimiser holds no group `{name}`"),
                })?;
                ParamSet::new().with_group(name, values.to_vec())
            };
            continued.moments = Some(Moments {
                first: only(&moments.first)?,
                second: only(&moments.second)?,
            });
            continued.step_count = self.step_count;
        }
        Ok(continued)
    }

    /// Step size used for group `name`.
    pub fn learning_rate_for(&self, name: &str) -> f64 {
        self.config
            .group_learning_rates
            .get(name)
            .copied()
            .unwrap_or(self.config.learning_rate)
    }

    /// One Adam update of `params` with `grads` (same layout). On error
    /// nothing — neither parameters nor optimiser state — is modified.
    pub fn step(&mut self, params: &mut ParamSet, grads: &ParamSet) -> Result<(), OptimError> {
        params.check_same_layout(grads, "gradients")?;
        grads.check_finite_gradients()?;
        if let Some(moments) = &self.moments {
            moments
                .first
                .check_same_layout(params, "parameters (vs. optimiser state)")?;
            moments
                .second
                .check_same_layout(params, "parameters (vs. optimiser second moments)")?;
        }
        if let Some(unknown) = self
            .config
            .group_learning_rates
            .keys()
            .find(|name| params.index_of(name).is_none())
        {
            return Err(OptimError::LayoutMismatch {
                detail: format!("group_learning_rates names unknown group `{unknown}`"),
            });
        }

        let moments = self.moments.get_or_insert_with(|| Moments {
            first: params.zeros_like(),
            second: params.zeros_like(),
        });
        self.step_count += 1;
        let AdamConfig {
            beta1,
            beta2,
            epsilon,
            ..
        } = self.config;
        // Bias corrections 1 - β^t; t as f64 is exact far beyond any run length.
        let t = self.step_count as f64;
        let correction1 = 1.0 - beta1.powf(t);
        let correction2 = 1.0 - beta2.powf(t);

        let groups = params
            .groups_mut()
            .zip(grads.groups())
            .zip(moments.first.groups_mut())
            .zip(moments.second.groups_mut());
        for ((((name, values), grad), (_, first)), (_, second)) in groups {
            let learning_rate = self
                .config
                .group_learning_rates
                .get(name)
                .copied()
                .unwrap_or(self.config.learning_rate);
            for i in 0..values.len() {
                let g = grad.values[i];
                first[i] = beta1 * first[i] + (1.0 - beta1) * g;
                second[i] = beta2 * second[i] + (1.0 - beta2) * g * g;
                let first_hat = first[i] / correction1;
                let second_hat = second[i] / correction2;
                values[i] -= learning_rate * first_hat / (second_hat.sqrt() + epsilon);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(groups: &[(&str, Vec<f64>)]) -> ParamSet {
        let mut s = ParamSet::new();
        for (name, values) in groups {
            s.push(*name, values.clone()).expect("unique");
        }
        s
    }

    #[test]
    fn invalid_config_is_refused() {
        for config in [
            AdamConfig::with_learning_rate(f64::NAN),
            AdamConfig {
                beta1: 1.0,
                ..AdamConfig::default()
            },
            AdamConfig {
                epsilon: 0.0,
                ..AdamConfig::default()
            },
        ] {
            assert!(Adam::new(config).is_err());
        }
    }

    #[test]
    fn layout_change_after_first_step_is_refused_without_side_effects() {
        let mut adam = Adam::new(AdamConfig::default()).expect("config");
        let mut params = set(&[("a", vec![1.0])]);
        adam.step(&mut params, &set(&[("a", vec![1.0])]))
            .expect("step");
        let snapshot = adam.clone();
        let mut other = set(&[("b", vec![1.0])]);
        assert!(adam.step(&mut other, &set(&[("b", vec![1.0])])).is_err());
        assert_eq!(adam, snapshot);
        let nan = set(&[("a", vec![f64::NAN])]);
        let before = params.clone();
        assert!(matches!(
            adam.step(&mut params, &nan),
            Err(OptimError::NonFiniteGradient { .. })
        ));
        assert_eq!((adam, params), (snapshot, before));
    }

    #[test]
    fn unknown_group_learning_rate_is_refused() {
        let mut config = AdamConfig::default();
        config.group_learning_rates.insert("typo".into(), 0.1);
        let mut adam = Adam::new(config).expect("config");
        let mut params = set(&[("a", vec![1.0])]);
        assert!(adam.step(&mut params, &set(&[("a", vec![1.0])])).is_err());
    }
}
