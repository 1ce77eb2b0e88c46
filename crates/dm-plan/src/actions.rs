//! Hand motions as few numbers: each hand grasps the object at a point and
//! moves through K knots (offsets from that point) reached at equally
//! spaced frames of the horizon, with a smoothstep between consecutive
//! knots (zero velocity at every knot). An anchor's position is linear in
//! the knots, so a gradient with respect to the anchors of each frame maps
//! onto the knots through the same weights ([`ActionPlan::knot_weights`]).

use serde::{Deserialize, Serialize};

/// One hand: where it grasps, and its knots (metres, relative to the grasp point).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HandPlan {
    pub grasp: [f64; 3],
    pub knots: Vec<[f64; 3]>,
}

/// The hands' motion over `horizon` frames (frame 0 is the start).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ActionPlan {
    pub hands: Vec<HandPlan>,
    pub horizon: usize,
}

/// Axis-aligned box the hands must stay in, metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Workspace {
    pub lo: [f64; 3],
    pub hi: [f64; 3],
}

impl Workspace {
    pub fn clamp(&self, p: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|a| p[a].clamp(self.lo[a], self.hi[a]))
    }

    /// The part of this box inside the box `[lo, hi]`.
    pub fn within(&self, lo: [f64; 3], hi: [f64; 3]) -> Self {
        Self {
            lo: std::array::from_fn(|a| self.lo[a].max(lo[a])),
            hi: std::array::from_fn(|a| self.hi[a].min(hi[a])),
        }
    }
}

impl ActionPlan {
    /// Hands resting at their grasp points, `knots` knots each.
    pub fn at_rest(grasps: &[[f64; 3]], knots: usize, horizon: usize) -> Self {
        Self {
            hands: grasps
                .iter()
                .map(|&grasp| HandPlan {
                    grasp,
                    knots: vec![[0.0; 3]; knots],
                })
                .collect(),
            horizon,
        }
    }

    pub fn knot_count(&self) -> usize {
        self.hands.first().map_or(0, |h| h.knots.len())
    }

    /// The knots flattened hand by hand (the optimisers' parameters).
    pub fn params(&self) -> Vec<f64> {
        self.hands
            .iter()
            .flat_map(|h| h.knots.iter().flatten().copied())
            .collect()
    }

    /// This plan with the knots `params` (as [`Self::params`] orders them).
    pub fn with_params(&self, params: &[f64]) -> Self {
        let mut out = self.clone();
        let mut values = params.iter().copied();
        for hand in &mut out.hands {
            for knot in &mut hand.knots {
                for c in knot.iter_mut() {
                    *c = values.next().unwrap_or(0.0);
                }
            }
        }
        out
    }

    /// Frame at which knot `j` (0-based) is reached.
    pub fn knot_frame(&self, j: usize) -> f64 {
        self.horizon as f64 * (j + 1) as f64 / self.knot_count().max(1) as f64
    }

    /// `(knot, weight)` pairs with anchor offset(frame) = Σ weight·knot
    /// (at most two; before the first knot the other end is the grasp
    /// point, offset zero).
    pub fn knot_weights(&self, frame: f64) -> Vec<(usize, f64)> {
        let k = self.knot_count();
        if k == 0 {
            return Vec::new();
        }
        let frame = frame.clamp(0.0, self.horizon as f64);
        let mut previous = 0.0;
        for j in 0..k {
            let end = self.knot_frame(j);
            if frame <= end || j + 1 == k {
                let u = ((frame - previous) / (end - previous).max(1e-12)).clamp(0.0, 1.0);
                let s = u * u * (3.0 - 2.0 * u);
                return if j == 0 {
                    vec![(0, s)]
                } else {
                    vec![(j - 1, 1.0 - s), (j, s)]
                };
            }
            previous = end;
        }
        Vec::new()
    }

    /// Anchor of every hand at `frame`.
    pub fn anchors(&self, frame: usize) -> Vec<[f64; 3]> {
        let weights = self.knot_weights(frame as f64);
        self.hands
            .iter()
            .map(|h| {
                let mut p = h.grasp;
                for &(j, w) in &weights {
                    for a in 0..3 {
                        p[a] += w * h.knots[j][a];
                    }
                }
                p
            })
            .collect()
    }

    /// Anchors of frames 0..=horizon.
    pub fn path(&self) -> Vec<Vec<[f64; 3]>> {
        (0..=self.horizon).map(|t| self.anchors(t)).collect()
    }

    /// Adds anchor gradients (`per_frame[t][hand]`, frames 0..=horizon) to
    /// the knots' gradient (as [`Self::params`] orders it).
    pub fn knot_gradient(&self, per_frame: &[Vec<[f64; 3]>]) -> Vec<f64> {
        let k = self.knot_count();
        let mut grad = vec![0.0; self.hands.len() * k * 3];
        for (t, hands) in per_frame.iter().enumerate() {
            for (j, w) in self.knot_weights(t as f64) {
                for (h, g) in hands.iter().enumerate() {
                    for a in 0..3 {
                        grad[(h * k + j) * 3 + a] += w * g[a];
                    }
                }
            }
        }
        grad
    }

    /// Keeps every knot (hence every anchor, a convex combination of the
    /// grasp point and knots) inside `workspace`.
    pub fn project(&mut self, workspace: &Workspace) {
        for hand in &mut self.hands {
            let grasp = hand.grasp;
            for knot in &mut hand.knots {
                let p = workspace.clamp(std::array::from_fn(|a| grasp[a] + knot[a]));
                *knot = std::array::from_fn(|a| p[a] - grasp[a]);
            }
        }
    }

    /// Fastest hand speed along the plan (m/s) with `frame_dt` seconds per
    /// frame: a smoothstep segment peaks at 1.5× its mean speed.
    pub fn peak_speed(&self, frame_dt: f64) -> f64 {
        let mut peak: f64 = 0.0;
        for hand in &self.hands {
            let mut previous = [0.0; 3];
            let mut start = 0.0;
            for (j, knot) in hand.knots.iter().enumerate() {
                let end = self.knot_frame(j);
                let length = (0..3)
                    .map(|a| (knot[a] - previous[a]).powi(2))
                    .sum::<f64>()
                    .sqrt();
                peak = peak.max(1.5 * length / ((end - start) * frame_dt).max(1e-12));
                previous = *knot;
                start = end;
            }
        }
        peak
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn anchors_start_at_the_grasp_and_pass_through_the_knots() {
        let mut plan = ActionPlan::at_rest(&[[0.1, 0.2, 0.3]], 3, 30);
        plan.hands[0].knots = vec![[0.03, 0.0, 0.0], [0.03, 0.06, 0.0], [0.0, 0.0, 0.09]];
        assert_eq!(plan.anchors(0), vec![[0.1, 0.2, 0.3]]);
        for (j, frame) in [(0, 10), (1, 20), (2, 30)] {
            let a = plan.anchors(frame)[0];
            for c in 0..3 {
                assert!(
                    (a[c] - (plan.hands[0].grasp[c] + plan.hands[0].knots[j][c])).abs() < 1e-12
                );
            }
        }
        // The weights at any frame sum to the interpolation between knots.
        let w: f64 = plan.knot_weights(15.0).iter().map(|x| x.1).sum();
        assert!((w - 1.0).abs() < 1e-12);
    }

    #[test]
    fn knot_gradient_is_the_transpose_of_the_anchor_map() {
        let mut plan = ActionPlan::at_rest(&[[0.0; 3], [1.0, 0.0, 0.0]], 4, 17);
        let params: Vec<f64> = (0..plan.params().len())
            .map(|i| (i as f64 * 0.37).sin() * 0.05)
            .collect();
        plan = plan.with_params(&params);
        let upstream: Vec<Vec<[f64; 3]>> = (0..=17)
            .map(|t| {
                (0..2)
                    .map(|h| [t as f64 * 0.1, -(h as f64), 0.5 + t as f64])
                    .collect()
            })
            .collect();
        let value = |p: &ActionPlan| -> f64 {
            p.path()
                .iter()
                .zip(&upstream)
                .map(|(a, g)| {
                    a.iter()
                        .zip(g)
                        .map(|(x, y)| (0..3).map(|c| x[c] * y[c]).sum::<f64>())
                        .sum::<f64>()
                })
                .sum()
        };
        let grad = plan.knot_gradient(&upstream);
        let h = 1e-6;
        for i in 0..params.len() {
            let mut up = params.clone();
            up[i] += h;
            let mut down = params.clone();
            down[i] -= h;
            let fd = (value(&plan.with_params(&up)) - value(&plan.with_params(&down))) / (2.0 * h);
            assert!(
                (fd - grad[i]).abs() < 1e-6 * (1.0 + fd.abs()),
                "param {i}: {fd} vs {}",
                grad[i]
            );
        }
    }
}
