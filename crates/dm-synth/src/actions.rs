//! Scripted hand interactions: each hand is a small cluster of anchor
//! points grasping the object's top surface, moved along smooth
//! minimum-jerk paths (translation plus a twist about the vertical axis).

use crate::shapes::Preset;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Action {
    /// One hand lifts part of the object, then carries it sideways.
    Lift,
    /// One hand drags the object across the floor.
    Push,
    /// Two hands lift and pull apart.
    Stretch,
    /// One hand lifts and twists about the vertical.
    Twist,
}

impl Action {
    pub const ALL: [Action; 4] = [Action::Lift, Action::Push, Action::Stretch, Action::Twist];

    pub fn name(self) -> &'static str {
        match self {
            Action::Lift => "lift",
            Action::Push => "push",
            Action::Stretch => "stretch",
            Action::Twist => "twist",
        }
    }
}

/// One motion segment: between `start_s` and `end_s` the hand moves by
/// `translation` and turns by `twist_deg` about +z through its grasp point.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Segment {
    pub start_s: f64,
    pub end_s: f64,
    pub translation: [f64; 3],
    pub twist_deg: f64,
}

/// A scripted hand.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HandScript {
    pub name: String,
    /// Grasp point on the object (centre of the anchor cluster at rest).
    pub grasp: [f64; 3],
    /// Anchor points at rest.
    pub anchors: Vec<[f64; 3]>,
    pub segments: Vec<Segment>,
}

/// Minimum-jerk profile on [0, 1].
fn min_jerk(tau: f64) -> f64 {
    let t = tau.clamp(0.0, 1.0);
    t * t * t * (10.0 - 15.0 * t + 6.0 * t * t)
}

impl HandScript {
    /// The hand's pose at time `t` (seconds): where its grasp point is,
    /// and how far it has turned about +z (radians).
    pub fn pose_at(&self, t: f64) -> ([f64; 3], f64) {
        let mut offset = [0.0; 3];
        let mut angle = 0.0f64;
        for seg in &self.segments {
            let s = min_jerk((t - seg.start_s) / (seg.end_s - seg.start_s));
            for a in 0..3 {
                offset[a] += s * seg.translation[a];
            }
            angle += s * seg.twist_deg.to_radians();
        }
        let mut pivot = self.grasp;
        for a in 0..3 {
            pivot[a] += offset[a];
        }
        (pivot, angle)
    }

    /// Anchor positions at time `t` (seconds).
    pub fn anchors_at(&self, t: f64) -> Vec<[f64; 3]> {
        let (pivot, angle) = self.pose_at(t);
        let (sin, cos) = angle.sin_cos();
        self.anchors
            .iter()
            .map(|p| {
                let r = [
                    p[0] - self.grasp[0],
                    p[1] - self.grasp[1],
                    p[2] - self.grasp[2],
                ];
                [
                    pivot[0] + cos * r[0] - sin * r[1],
                    pivot[1] + sin * r[0] + cos * r[1],
                    pivot[2] + r[2],
                ]
            })
            .collect()
    }
}

/// Height of the object's top surface above (x, y).
fn top_height(preset: Preset, x: f64, y: f64) -> f64 {
    let (_, hi) = preset.bounds();
    let mut z = hi[2] + 0.01;
    while z > 0.0 && preset.sdf([x, y, z]) > 0.0 {
        z -= 0.0005;
    }
    z.max(0.0)
}

/// Radius of the ring of anchors around a scripted hand's grasp point, metres.
pub const GRIP_RING_RADIUS_M: f64 = 0.012;

/// A cluster of anchors around the grasp point: a centre and a ring,
/// slightly inside the top surface (as fingertips pressing in).
fn anchor_cluster(preset: Preset, x: f64, y: f64, count: usize) -> ([f64; 3], Vec<[f64; 3]>) {
    let top = top_height(preset, x, y);
    let depth = match preset {
        Preset::Cloth => 0.004,
        Preset::Rope => 0.008,
        Preset::Toy => 0.01,
    };
    let grasp = [x, y, top - depth];
    let radius = GRIP_RING_RADIUS_M;
    let mut anchors = vec![grasp];
    for i in 0..count.saturating_sub(1) {
        let a = std::f64::consts::TAU * i as f64 / (count - 1) as f64;
        let (px, py) = (x + radius * a.cos(), y + radius * a.sin());
        let z = (top_height(preset, px, py) - depth).max(grasp[2] - 0.01);
        anchors.push([px, py, z]);
    }
    (grasp, anchors)
}

/// The hands for a preset and action. `second_hand_holds` adds a second
/// hand that grasps the opposite side and keeps still (for one-hand actions).
pub fn plan(
    preset: Preset,
    action: Action,
    second_hand_holds: bool,
    duration_s: f64,
) -> Vec<HandScript> {
    const ANCHORS_PER_HAND: usize = 8;
    let t1 = 0.1;
    let t2 = 0.55 * duration_s;
    let t3 = 0.95 * duration_s;
    let seg = |start: f64, end: f64, tr: [f64; 3], twist: f64| Segment {
        start_s: start,
        end_s: end,
        translation: tr,
        twist_deg: twist,
    };
    // (grasp x, y) of the main hand and of the opposite side.
    let (main_xy, opposite_xy) = match (preset, action) {
        (Preset::Rope, Action::Push) => ((0.0, 0.0), (-0.2, 0.0)),
        (Preset::Rope, _) => ((0.19, 0.0), (-0.19, 0.0)),
        (Preset::Cloth, Action::Twist) => ((0.0, 0.0), (-0.12, -0.12)),
        (Preset::Cloth, Action::Push) => ((0.12, 0.0), (-0.12, 0.0)),
        (Preset::Cloth, _) => ((0.12, 0.12), (-0.12, -0.12)),
        (Preset::Toy, Action::Stretch) => ((0.0, 0.05), (0.0, -0.05)),
        (Preset::Toy, Action::Push) => ((0.03, 0.0), (-0.03, 0.0)),
        (Preset::Toy, _) => ((0.0, 0.0), (-0.05, 0.0)),
    };
    let main_segments = match action {
        Action::Lift => vec![
            seg(t1, t2, [-0.04, 0.0, 0.14], 0.0),
            seg(t2, t3, [0.0, 0.08, -0.03], 0.0),
        ],
        Action::Push => vec![
            seg(t1, t2, [0.0, 0.09, 0.005], 0.0),
            seg(t2, t3, [0.06, 0.0, 0.0], 0.0),
        ],
        Action::Stretch => vec![
            seg(t1, t2, [0.02, 0.0, 0.10], 0.0),
            seg(t2, t3, [0.03, 0.0, -0.02], 0.0),
        ],
        Action::Twist => vec![
            seg(t1, t2, [0.0, 0.0, 0.08], 60.0),
            seg(t2, t3, [0.0, 0.03, 0.0], -45.0),
        ],
    };
    let mut hands = Vec::new();
    let (grasp, anchors) = anchor_cluster(preset, main_xy.0, main_xy.1, ANCHORS_PER_HAND);
    hands.push(HandScript {
        name: "right".into(),
        grasp,
        anchors,
        segments: main_segments,
    });
    if action == Action::Stretch || second_hand_holds {
        let (grasp, anchors) =
            anchor_cluster(preset, opposite_xy.0, opposite_xy.1, ANCHORS_PER_HAND);
        // In a stretch the second hand mirrors the first along the grasp axis.
        let segments = if action == Action::Stretch {
            hands[0]
                .segments
                .iter()
                .map(|s| {
                    let mirror = |v: [f64; 3]| {
                        let axis = [main_xy.0 - opposite_xy.0, main_xy.1 - opposite_xy.1];
                        let n = (axis[0] * axis[0] + axis[1] * axis[1]).sqrt().max(1e-9);
                        let along = (v[0] * axis[0] + v[1] * axis[1]) / n;
                        [-along * axis[0] / n, -along * axis[1] / n, v[2]]
                    };
                    seg(s.start_s, s.end_s, mirror(s.translation), -s.twist_deg)
                })
                .collect()
        } else {
            Vec::new()
        };
        hands.push(HandScript {
            name: "left".into(),
            grasp,
            anchors,
            segments,
        });
    }
    hands
}
