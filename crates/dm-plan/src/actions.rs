//! Hand motions as few numbers: each hand grasps the object at a point and
//! moves through K knots (offsets from that point) reached at equally
//! spaced frames of the horizon, with a smoothstep between consecutive
//! knots (zero velocity at every knot). A hand is one anchor, or several
//! it carries rigidly (a gripper's fingers: fixed offsets from its point).
//! An anchor's position is linear in the knots, so a gradient with respect
//! to the anchors of each frame maps onto the knots through the same
//! weights ([`ActionPlan::knot_weights`]).

use serde::{Deserialize, Serialize};

/// One hand: where it grasps, and its knots (metres, relative to the grasp point).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HandPlan {
    pub grasp: [f64; 3],
    pub knots: Vec<[f64; 3]>,
    /// The anchors the hand carries, as offsets from its point (metres;
    /// none: one anchor at the point).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub offsets: Vec<[f64; 3]>,
}

impl HandPlan {
    /// Anchors this hand moves.
    pub fn anchor_count(&self) -> usize {
        self.offsets.len().max(1)
    }

    /// The anchors when the hand's point is at `point`.
    fn anchors_at(&self, point: [f64; 3]) -> impl Iterator<Item = [f64; 3]> + '_ {
        let single = self.offsets.is_empty().then_some([0.0; 3]);
        single
            .into_iter()
            .chain(self.offsets.iter().copied())
            .map(move |o| std::array::from_fn(|a| point[a] + o[a]))
    }
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
                    offsets: Vec::new(),
                })
                .collect(),
            horizon,
        }
    }

    /// Rigid hands resting where they are: each range `[start, end)` of
    /// `anchors` is one hand (its point the anchors' centroid), the ranges
    /// in order and covering every anchor, so the plan's anchors keep
    /// `anchors`' order.
    pub fn rigid_at_rest(
        anchors: &[[f64; 3]],
        ranges: &[[usize; 2]],
        knots: usize,
        horizon: usize,
    ) -> Result<Self, String> {
        let mut next = 0;
        for &[start, end] in ranges {
            if start != next || end <= start {
                return Err(format!(
                    "hand ranges must be non-empty, in order and contiguous from anchor 0; [{start}, {end}) follows anchor {next}"
                ));
            }
            next = end;
        }
        if next != anchors.len() {
            return Err(format!(
                "hand ranges cover {next} anchors; the simulation has {}",
                anchors.len()
            ));
        }
        let hands = ranges
            .iter()
            .map(|&[start, end]| {
                let group = &anchors[start..end];
                let n = group.len() as f64;
                let centre: [f64; 3] =
                    std::array::from_fn(|a| group.iter().map(|p| p[a]).sum::<f64>() / n);
                HandPlan {
                    grasp: centre,
                    knots: vec![[0.0; 3]; knots],
                    offsets: group
                        .iter()
                        .map(|p| std::array::from_fn(|a| p[a] - centre[a]))
                        .collect(),
                }
            })
            .collect();
        Ok(Self { hands, horizon })
    }

    pub fn knot_count(&self) -> usize {
        self.hands.first().map_or(0, |h| h.knots.len())
    }

    /// Anchors the plan moves (each hand's, hand by hand).
    pub fn anchor_count(&self) -> usize {
        self.hands.iter().map(HandPlan::anchor_count).sum()
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

    /// Each hand's point at `frame`.
    pub fn hand_points(&self, frame: usize) -> Vec<[f64; 3]> {
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

    /// Every anchor at `frame`, hand by hand.
    pub fn anchors(&self, frame: usize) -> Vec<[f64; 3]> {
        self.hand_points(frame)
            .into_iter()
            .zip(&self.hands)
            .flat_map(|(p, h)| h.anchors_at(p))
            .collect()
    }

    /// Anchors of frames 0..=horizon.
    pub fn path(&self) -> Vec<Vec<[f64; 3]>> {
        (0..=self.horizon).map(|t| self.anchors(t)).collect()
    }

    /// Adds anchor gradients (`per_frame[t][anchor]`, frames 0..=horizon,
    /// anchors as [`Self::anchors`] orders them) to the knots' gradient (as
    /// [`Self::params`] orders it): a rigid hand's knot collects its
    /// anchors' gradients.
    pub fn knot_gradient(&self, per_frame: &[Vec<[f64; 3]>]) -> Vec<f64> {
        let k = self.knot_count();
        let hand_of: Vec<usize> = self
            .hands
            .iter()
            .enumerate()
            .flat_map(|(h, hand)| std::iter::repeat_n(h, hand.anchor_count()))
            .collect();
        let mut grad = vec![0.0; self.hands.len() * k * 3];
        for (t, anchors) in per_frame.iter().enumerate() {
            for (j, w) in self.knot_weights(t as f64) {
                for (&h, g) in hand_of.iter().zip(anchors) {
                    for a in 0..3 {
                        grad[(h * k + j) * 3 + a] += w * g[a];
                    }
                }
            }
        }
        grad
    }

    /// Keeps every knot inside `workspace`, shrunk by a rigid hand's
    /// offsets so that each of its anchors stays inside too (every anchor
    /// is a convex combination of the hand's grasp point and knots, plus
    /// its offset). A hand wider than the workspace is centred in it.
    pub fn project(&mut self, workspace: &Workspace) {
        for hand in &mut self.hands {
            let mut shrunk = *workspace;
            for o in &hand.offsets {
                for a in 0..3 {
                    shrunk.lo[a] = shrunk.lo[a].max(workspace.lo[a] - o[a]);
                    shrunk.hi[a] = shrunk.hi[a].min(workspace.hi[a] - o[a]);
                }
            }
            for a in 0..3 {
                if shrunk.lo[a] > shrunk.hi[a] {
                    let middle = 0.5 * (shrunk.lo[a] + shrunk.hi[a]);
                    (shrunk.lo[a], shrunk.hi[a]) = (middle, middle);
                }
            }
            let grasp = hand.grasp;
            for knot in &mut hand.knots {
                let p = shrunk.clamp(std::array::from_fn(|a| grasp[a] + knot[a]));
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
        let plan = ActionPlan::at_rest(&[[0.0; 3], [1.0, 0.0, 0.0]], 4, 17);
        check_knot_gradient(plan);
        // A single anchor and a rigid hand of three.
        let anchors = [[0.0; 3], [1.0, 0.0, 0.0], [1.1, 0.0, 0.0], [1.0, 0.2, 0.1]];
        let rigid = ActionPlan::rigid_at_rest(&anchors, &[[0, 1], [1, 4]], 4, 17).expect("ranges");
        check_knot_gradient(rigid);
    }

    fn check_knot_gradient(mut plan: ActionPlan) {
        let params: Vec<f64> = (0..plan.params().len())
            .map(|i| (i as f64 * 0.37).sin() * 0.05)
            .collect();
        plan = plan.with_params(&params);
        let upstream: Vec<Vec<[f64; 3]>> = (0..=plan.horizon)
            .map(|t| {
                (0..plan.anchor_count())
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

    /// A rigid hand starts where its anchors are, keeps their offsets at
    /// every frame, and stays inside the workspace with all of them.
    #[test]
    fn a_rigid_hand_moves_its_anchors_together_inside_the_workspace() {
        let anchors = [
            [0.0, 0.1, 0.0],
            [0.04, 0.1, 0.0],
            [0.3, 0.1, 0.0],
            [0.3, 0.1, 0.05],
        ];
        let mut plan =
            ActionPlan::rigid_at_rest(&anchors, &[[0, 2], [2, 4]], 2, 10).expect("ranges");
        assert_eq!(plan.anchor_count(), 4);
        for (a, b) in plan.anchors(0).iter().zip(&anchors) {
            assert!(
                (0..3).all(|c| (a[c] - b[c]).abs() < 1e-15),
                "{a:?} vs {b:?}"
            );
        }
        plan.hands[0].knots = vec![[0.5, 0.0, 0.0], [0.5, -0.5, 0.0]];
        plan.hands[1].knots = vec![[0.0, 0.0, 0.2], [-0.1, 0.0, 0.2]];
        let workspace = Workspace {
            lo: [-0.1, 0.05, -0.1],
            hi: [0.4, 0.3, 0.1],
        };
        plan.project(&workspace);
        for t in 0..=plan.horizon {
            let now = plan.anchors(t);
            for (h, [start, end]) in [[0, 2], [2, 4]].into_iter().enumerate() {
                let point = plan.hand_points(t)[h];
                for i in start..end {
                    let offset = plan.hands[h].offsets[i - start];
                    assert!(
                        (0..3).all(|c| (now[i][c] - point[c] - offset[c]).abs() < 1e-12),
                        "frame {t}: anchor {i} left its hand"
                    );
                    assert!(
                        (0..3).all(|c| now[i][c] >= workspace.lo[c] - 1e-12
                            && now[i][c] <= workspace.hi[c] + 1e-12),
                        "frame {t}: anchor {i} at {:?} outside the workspace",
                        now[i]
                    );
                }
            }
        }
        // The clamp moved the hands as far as the workspace lets every
        // anchor go: the first hand's second anchor ends on the x limit.
        assert!((plan.anchors(5)[1][0] - workspace.hi[0]).abs() < 1e-12);
        for ranges in [
            &[[0, 2], [3, 4]][..],
            &[[0, 2]],
            &[[0, 0], [0, 4]],
            &[[0, 5]],
        ] {
            assert!(
                ActionPlan::rigid_at_rest(&anchors, ranges, 2, 10).is_err(),
                "{ranges:?} accepted"
            );
        }
    }
}
