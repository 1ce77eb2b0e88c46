//! What a plan is scored by. The optimisers minimise, at the last frame,
//! the symmetric squared Chamfer distance between the goal and the
//! predicted surface plus, where the goal has correspondences, the mean
//! squared Track distance (m²), and a penalty on hand speeds above the
//! limit and on knot-to-knot jerks. Reports use the metrics' distances:
//! the one-directional L1 Chamfer from the goal to the surface
//! (docs/metrics.md) and the mean Track distance.

use dm_model::metrics::chamfer_to;
use dm_mpm::neighbors::PointIndex;
use serde::{Deserialize, Serialize};

use crate::actions::ActionPlan;

/// Weights and limits of the planning cost.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CostWeights {
    /// Symmetric squared Chamfer, per m².
    pub chamfer: f64,
    /// Mean squared Track distance, per m².
    pub track: f64,
    /// Hands faster than this (m/s) are penalised.
    pub max_speed_m_s: f64,
    /// Weight of the squared speed excess, per (m/s)².
    pub speed: f64,
    /// Weight of the squared second difference of the knots, per m².
    pub smoothness: f64,
}

impl Default for CostWeights {
    fn default() -> Self {
        Self {
            chamfer: 1.0,
            track: 1.0,
            max_speed_m_s: 0.5,
            speed: 1e-2,
            smoothness: 1e-2,
        }
    }
}

/// The goal as the planning world sees it.
#[derive(Debug)]
pub struct TerminalCost {
    goal: Vec<[f64; 3]>,
    goal_index: PointIndex,
    /// Planning-world particle of each goal point (correspondences).
    goal_particles: Option<Vec<usize>>,
    surface_count: usize,
    weights: CostWeights,
}

/// The distances of a final state to the goal, metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Scores {
    /// One-directional L1 Chamfer from the goal to the surface particles
    /// (the metrics' Chamfer term).
    pub final_chamfer_m: f64,
    /// The mean of both directions (goal → surface, surface → goal), L1:
    /// also low only when no part of the object is away from the goal.
    pub final_symmetric_chamfer_m: f64,
    /// Mean distance of corresponding particles to their goal points (goals
    /// with correspondences).
    pub final_track_m: Option<f64>,
}

/// The scores of `surface` (the object's surface particles) and of the
/// particles `corresponding[k]` of `positions`, the k-th goal point's.
pub fn scores(
    goal: &[[f64; 3]],
    surface: &[[f64; 3]],
    positions: &[[f64; 3]],
    corresponding: Option<&[usize]>,
) -> Scores {
    let to_surface = chamfer_to(surface, goal);
    Scores {
        final_chamfer_m: to_surface,
        final_symmetric_chamfer_m: 0.5 * (to_surface + chamfer_to(goal, surface)),
        final_track_m: corresponding.map(|ids| {
            goal.iter()
                .zip(ids)
                .map(|(g, &p)| norm2(sub(positions[p], *g)).sqrt())
                .sum::<f64>()
                / ids.len().max(1) as f64
        }),
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn norm2(d: [f64; 3]) -> f64 {
    d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
}

impl TerminalCost {
    pub fn new(
        goal: Vec<[f64; 3]>,
        goal_particles: Option<Vec<usize>>,
        surface_count: usize,
        weights: CostWeights,
    ) -> Self {
        Self {
            goal_index: PointIndex::new(&goal),
            goal,
            goal_particles,
            surface_count,
            weights,
        }
    }

    /// The cost of a final state and its gradient with respect to every
    /// particle's position.
    pub fn value_and_gradient(&self, positions: &[[f64; 3]]) -> (f64, Vec<[f64; 3]>) {
        let mut grad = vec![[0.0; 3]; positions.len()];
        let surface = &positions[..self.surface_count.min(positions.len())];
        let w = self.weights;
        let mut value = 0.0;
        if !surface.is_empty() && !self.goal.is_empty() {
            // Goal → surface.
            let index = PointIndex::new(surface);
            let scale = w.chamfer / self.goal.len() as f64;
            for g in &self.goal {
                if let Some(&(s, _)) = index.nearest(g, 1).first() {
                    let d = sub(surface[s], *g);
                    value += scale * norm2(d);
                    for a in 0..3 {
                        grad[s][a] += 2.0 * scale * d[a];
                    }
                }
            }
            // Surface → goal.
            let scale = w.chamfer / surface.len() as f64;
            for (s, p) in surface.iter().enumerate() {
                if let Some(&(k, _)) = self.goal_index.nearest(p, 1).first() {
                    let d = sub(*p, self.goal[k]);
                    value += scale * norm2(d);
                    for a in 0..3 {
                        grad[s][a] += 2.0 * scale * d[a];
                    }
                }
            }
        }
        if let Some(particles) = &self.goal_particles {
            let scale = w.track / particles.len().max(1) as f64;
            for (g, &p) in self.goal.iter().zip(particles) {
                let d = sub(positions[p], *g);
                value += scale * norm2(d);
                for a in 0..3 {
                    grad[p][a] += 2.0 * scale * d[a];
                }
            }
        }
        (value, grad)
    }

    /// The distances of a final state of the planning world to the goal.
    pub fn scores(&self, positions: &[[f64; 3]]) -> Scores {
        let surface = &positions[..self.surface_count.min(positions.len())];
        scores(
            &self.goal,
            surface,
            positions,
            self.goal_particles.as_deref(),
        )
    }
}

/// The speed and smoothness penalty of a plan and its gradient with
/// respect to the knots (as [`ActionPlan::params`] orders them).
pub fn plan_penalty(plan: &ActionPlan, frame_dt: f64, weights: &CostWeights) -> (f64, Vec<f64>) {
    let k = plan.knot_count();
    let mut grad = vec![0.0; plan.hands.len() * k * 3];
    let mut value = 0.0;
    for (h, hand) in plan.hands.iter().enumerate() {
        let mut previous = [0.0; 3];
        let mut start = 0.0;
        for (j, knot) in hand.knots.iter().enumerate() {
            let end = plan.knot_frame(j);
            let duration = ((end - start) * frame_dt).max(1e-12);
            let d = sub(*knot, previous);
            let length = norm2(d).sqrt();
            // Peak speed of a smoothstep segment: 1.5 × its mean speed.
            let excess = 1.5 * length / duration - weights.max_speed_m_s;
            if excess > 0.0 && length > 0.0 {
                value += weights.speed * excess * excess;
                let scale = weights.speed * 2.0 * excess * 1.5 / duration / length;
                for a in 0..3 {
                    grad[(h * k + j) * 3 + a] += scale * d[a];
                    if j > 0 {
                        grad[(h * k + j - 1) * 3 + a] -= scale * d[a];
                    }
                }
            }
            previous = *knot;
            start = end;
        }
        for j in 1..k.saturating_sub(1) {
            let before = hand.knots[j - 1];
            let after = hand.knots[j + 1];
            let here = hand.knots[j];
            let second: [f64; 3] = std::array::from_fn(|a| after[a] - 2.0 * here[a] + before[a]);
            value += weights.smoothness * norm2(second);
            for a in 0..3 {
                let g = 2.0 * weights.smoothness * second[a];
                grad[(h * k + j + 1) * 3 + a] += g;
                grad[(h * k + j) * 3 + a] -= 2.0 * g;
                grad[(h * k + j - 1) * 3 + a] += g;
            }
        }
    }
    (value, grad)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn finite_difference(f: &dyn Fn(&[f64]) -> f64, x: &[f64], i: usize) -> f64 {
        let h = 1e-7;
        let mut up = x.to_vec();
        up[i] += h;
        let mut down = x.to_vec();
        down[i] -= h;
        (f(&up) - f(&down)) / (2.0 * h)
    }

    /// Analytic gradients against central differences in f64. Tolerance
    /// 1e-5 relative: the terms are piecewise quadratic, and the nearest
    /// neighbours do not change within ±1e-7 m on these points.
    #[test]
    fn terminal_and_penalty_gradients_match_finite_differences() {
        let positions: Vec<[f64; 3]> = (0..12)
            .map(|i| {
                let t = i as f64;
                [0.03 * t, 0.02 * (t * 1.3).sin(), 0.01 * (t * 0.7).cos()]
            })
            .collect();
        let goal: Vec<[f64; 3]> = (0..7).map(|k| [0.05 * k as f64, 0.04, 0.02]).collect();
        let cost = TerminalCost::new(
            goal,
            Some(vec![0, 2, 4, 6, 8, 10, 11]),
            9,
            CostWeights::default(),
        );
        let flat: Vec<f64> = positions.iter().flatten().copied().collect();
        let value = |x: &[f64]| {
            let p: Vec<[f64; 3]> = x.chunks(3).map(|c| [c[0], c[1], c[2]]).collect();
            cost.value_and_gradient(&p).0
        };
        let (_, grad) = cost.value_and_gradient(&positions);
        for i in 0..flat.len() {
            let fd = finite_difference(&value, &flat, i);
            assert!(
                (fd - grad[i / 3][i % 3]).abs() < 1e-5 * (1.0 + fd.abs()),
                "x[{i}]: {fd} vs {}",
                grad[i / 3][i % 3]
            );
        }

        let plan = ActionPlan::at_rest(&[[0.0; 3], [0.2, 0.0, 0.0]], 4, 20);
        let params: Vec<f64> = (0..plan.params().len())
            .map(|i| 0.08 * ((i as f64) * 1.7).sin())
            .collect();
        let weights = CostWeights {
            max_speed_m_s: 0.2,
            ..CostWeights::default()
        };
        let value = |x: &[f64]| plan_penalty(&plan.with_params(x), 1.0 / 30.0, &weights).0;
        let (v, grad) = plan_penalty(&plan.with_params(&params), 1.0 / 30.0, &weights);
        assert!(
            v > 0.0,
            "the test plan must exceed the speed limit somewhere"
        );
        for i in 0..params.len() {
            let fd = finite_difference(&value, &params, i);
            assert!(
                (fd - grad[i]).abs() < 1e-5 * (1.0 + fd.abs()),
                "knot param {i}: {fd} vs {}",
                grad[i]
            );
        }
    }
}
