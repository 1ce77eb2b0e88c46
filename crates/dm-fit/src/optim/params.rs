//! [`ParamSet`]: ordered, named groups of `f64` values.
//!
//! A group is one "parameter" in the method's sense (e.g. `youngs_raw` holds
//! the raw Young's modulus of every material patch; a residual-network layer
//! holds its weights). Gradients are stored in a `ParamSet` of the same
//! layout (same names, order and lengths), which the optimiser checks.
//! Group order is significant: it fixes the order of the global
//! concatenation and of serialised checkpoints.

use serde::{Deserialize, Serialize};

use super::OptimError;

/// One named parameter group.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ParamGroup {
    pub name: String,
    pub values: Vec<f64>,
}

/// Ordered named parameter groups with unique names.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ParamSet {
    groups: Vec<ParamGroup>,
}

impl ParamSet {
    /// An empty set.
    pub fn new() -> Self {
        Self::default()
    }

    /// Builder form of [`ParamSet::push`].
    pub fn with_group(
        mut self,
        name: impl Into<String>,
        values: Vec<f64>,
    ) -> Result<Self, OptimError> {
        self.push(name, values)?;
        Ok(self)
    }

    /// Appends a group; names must be unique because groups are looked up
    /// and reported by name.
    pub fn push(&mut self, name: impl Into<String>, values: Vec<f64>) -> Result<(), OptimError> {
        let name = name.into();
        if self.index_of(&name).is_some() {
            return Err(OptimError::DuplicateGroup { name });
        }
        self.groups.push(ParamGroup { name, values });
        Ok(())
    }

    /// Number of groups.
    pub fn len(&self) -> usize {
        self.groups.len()
    }

    pub fn is_empty(&self) -> bool {
        self.groups.is_empty()
    }

    /// Total number of scalars over all groups.
    pub fn scalar_count(&self) -> usize {
        self.groups.iter().map(|group| group.values.len()).sum()
    }

    /// Position of the group called `name`.
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.groups.iter().position(|group| group.name == name)
    }

    pub fn get(&self, name: &str) -> Option<&[f64]> {
        self.index_of(name)
            .map(|i| self.groups[i].values.as_slice())
    }

    pub fn get_mut(&mut self, name: &str) -> Option<&mut [f64]> {
        self.index_of(name)
            .map(|i| self.groups[i].values.as_mut_slice())
    }

    /// The groups in order.
    pub fn groups(&self) -> &[ParamGroup] {
        &self.groups
    }

    /// The groups in order, mutable values (names and lengths stay fixed so
    /// the layout cannot drift away from the optimiser state).
    pub fn groups_mut(&mut self) -> impl Iterator<Item = (&str, &mut [f64])> {
        self.groups
            .iter_mut()
            .map(|group| (group.name.as_str(), group.values.as_mut_slice()))
    }

    /// Group names in order.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.groups.iter().map(|group| group.name.as_str())
    }

    /// A set with the same layout and every value zero (e.g. a gradient
    /// accumulator or fresh optimiser moments).
    pub fn zeros_like(&self) -> Self {
        Self {
            groups: self
                .groups
                .iter()
                .map(|group| ParamGroup {
                    name: group.name.clone(),
                    values: vec![0.0; group.values.len()],
                })
                .collect(),
        }
    }

    /// All values concatenated in group order.
    pub fn flatten(&self) -> Vec<f64> {
        self.groups
            .iter()
            .flat_map(|group| group.values.iter().copied())
            .collect()
    }

    /// Checks that `other` has the same group names, order and lengths.
    /// `what` names the other set in the error (e.g. "gradients").
    pub fn check_same_layout(&self, other: &ParamSet, what: &str) -> Result<(), OptimError> {
        if self.groups.len() != other.groups.len() {
            return Err(OptimError::LayoutMismatch {
                detail: format!(
                    "{what} have {} groups, expected {}",
                    other.groups.len(),
                    self.groups.len()
                ),
            });
        }
        for (position, (mine, theirs)) in self.groups.iter().zip(&other.groups).enumerate() {
            if mine.name != theirs.name {
                return Err(OptimError::LayoutMismatch {
                    detail: format!(
                        "{what} group {position} is `{}`, expected `{}`",
                        theirs.name, mine.name
                    ),
                });
            }
            if mine.values.len() != theirs.values.len() {
                return Err(OptimError::LayoutMismatch {
                    detail: format!(
                        "{what} group `{}` has {} values, expected {}",
                        mine.name,
                        theirs.values.len(),
                        mine.values.len()
                    ),
                });
            }
        }
        Ok(())
    }

    /// Errors on the first non-finite value, naming its group, so that a NaN
    /// never silently reaches the parameters.
    pub fn check_finite_gradients(&self) -> Result<(), OptimError> {
        for group in &self.groups {
            if let Some((index, &value)) = group
                .values
                .iter()
                .enumerate()
                .find(|(_, value)| !value.is_finite())
            {
                return Err(OptimError::NonFiniteGradient {
                    group: group.name.clone(),
                    index,
                    value,
                });
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn duplicate_names_are_refused() {
        let set = ParamSet::new().with_group("a", vec![1.0]).expect("first a");
        let err = set.with_group("a", vec![2.0]).expect_err("second a");
        assert_eq!(err, OptimError::DuplicateGroup { name: "a".into() });
    }

    #[test]
    fn layout_check_names_the_mismatch() {
        let params = ParamSet::new()
            .with_group("a", vec![1.0, 2.0])
            .and_then(|s| s.with_group("b", vec![3.0]))
            .expect("params");
        assert!(
            params
                .check_same_layout(&params.zeros_like(), "gradients")
                .is_ok()
        );
        let short = ParamSet::new()
            .with_group("a", vec![1.0])
            .and_then(|s| s.with_group("b", vec![3.0]))
            .expect("short");
        let err = params
            .check_same_layout(&short, "gradients")
            .expect_err("mismatch");
        assert!(
            err.to_string().contains("`a` has 1 values, expected 2"),
            "{err}"
        );
        let reordered = ParamSet::new()
            .with_group("b", vec![3.0])
            .and_then(|s| s.with_group("a", vec![1.0, 2.0]))
            .expect("reordered");
        assert!(params.check_same_layout(&reordered, "gradients").is_err());
        assert_eq!(params.flatten(), vec![1.0, 2.0, 3.0]);
        assert_eq!(params.scalar_count(), 3);
    }
}
