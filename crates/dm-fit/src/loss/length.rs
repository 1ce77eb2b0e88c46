//! Local length preservation (method.md §7): neighbouring particles keep
//! their frame-0 distance.
//!
//! This regularises *stretching* (and compression) of the simulated object:
//! the one-directional Chamfer term only pulls surface particles towards
//! observed points, and the track term only constrains the matched
//! particles, so without it the fit could pull a few particles far from
//! their neighbours. It is a soft prior (see `LossWeights::length`), not
//! a rigidity constraint: it costs nothing for rigid motions and is cheap
//! for bending, which changes pair lengths only to second order.

use dm_mpm::neighbors::PointIndex;

use super::{LossError, LossValue, check_finite, check_len, norm2, sub};

/// How neighbouring pairs are chosen at frame 0.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum PairSelection {
    /// Every pair of particles closer than this radius (metres).
    Radius(f64),
    /// Each particle with its `k` nearest others (ties → lower index); a
    /// pair found from both ends is kept once.
    Nearest(usize),
}

impl Default for PairSelection {
    /// Six nearest neighbours.
    fn default() -> Self {
        Self::Nearest(6)
    }
}

/// Particle pairs `(p, q)`, `p < q`, with their frame-0 rest lengths.
#[derive(Debug, Clone, PartialEq)]
pub struct LengthPreservation {
    pairs: Vec<(usize, usize)>,
    rest: Vec<f64>,
    particle_count: usize,
}

impl LengthPreservation {
    /// Pairs from the frame-0 particles, sorted by `(p, q)` (deterministic:
    /// independent of the k-d tree's internal order).
    pub fn new(rest_particles: &[[f64; 3]], selection: PairSelection) -> Result<Self, LossError> {
        check_finite("rest_particles", rest_particles, |_| true)?;
        let index = PointIndex::new(rest_particles);
        let mut pairs: Vec<(usize, usize)> = Vec::new();
        match selection {
            PairSelection::Radius(radius) => {
                if !(radius.is_finite() && radius > 0.0) {
                    return Err(LossError::InvalidArgument {
                        argument: "selection",
                        reason: format!("radius must be finite and > 0, got {radius}"),
                    });
                }
                for (p, x) in rest_particles.iter().enumerate() {
                    pairs.extend(
                        index
                            .within(x, radius)
                            .into_iter()
                            .filter(|&(q, d)| q > p && d < radius)
                            .map(|(q, _)| (p, q)),
                    );
                }
            }
            PairSelection::Nearest(k) => {
                if k == 0 {
                    return Err(LossError::InvalidArgument {
                        argument: "selection",
                        reason: "k must be at least 1".into(),
                    });
                }
                for (p, x) in rest_particles.iter().enumerate() {
                    pairs.extend(
                        index
                            .nearest(x, k + 1)
                            .into_iter()
                            .filter(|&(q, _)| q != p)
                            .take(k)
                            .map(|(q, _)| (p.min(q), p.max(q))),
                    );
                }
            }
        }
        pairs.sort_unstable();
        pairs.dedup();
        let rest = pairs
            .iter()
            .map(|&(p, q)| norm2(&sub(&rest_particles[p], &rest_particles[q])).sqrt())
            .collect();
        Ok(Self {
            pairs,
            rest,
            particle_count: rest_particles.len(),
        })
    }

    /// The pairs `(p, q)`, `p < q`, sorted.
    pub fn pairs(&self) -> &[(usize, usize)] {
        &self.pairs
    }

    /// Rest length of each pair, metres.
    pub fn rest_lengths(&self) -> &[f64] {
        &self.rest
    }

    pub fn particle_count(&self) -> usize {
        self.particle_count
    }

    /// `L_length = (1/P) Σ_{(p,q)} (|x_p − x_q| − L0_pq)²` over the P pairs,
    /// with `∂L/∂x_p = (2/P)(l − L0)(x_p − x_q)/l = −∂L/∂x_q` per pair.
    /// A pair collapsed to a point (`l = 0`, a kink) contributes a zero
    /// gradient (a subgradient). No pairs → value 0, zero gradient.
    pub fn loss(&self, predicted: &[[f64; 3]]) -> Result<LossValue, LossError> {
        check_len("predicted", self.particle_count, predicted.len())?;
        check_finite("predicted", predicted, |_| true)?;
        let mut out = LossValue::zero(predicted.len());
        if self.pairs.is_empty() {
            return Ok(out);
        }
        let scale = 1.0 / self.pairs.len() as f64;
        for (&(p, q), &rest) in self.pairs.iter().zip(&self.rest) {
            let d = sub(&predicted[p], &predicted[q]);
            let length = norm2(&d).sqrt();
            let stretch = length - rest;
            out.value += scale * stretch * stretch;
            if length > 0.0 {
                let factor = 2.0 * scale * stretch / length;
                for a in 0..3 {
                    out.grad[p][a] += factor * d[a];
                    out.grad[q][a] -= factor * d[a];
                }
            }
        }
        Ok(out)
    }
}
