//! Turns of the residual's frame about the gravity axis, for training the
//! network to correct the same way whichever horizontal direction the
//! object moves in.
//!
//! Why: a clip shows a few motion directions, and the held-out frames may
//! move another way (the `lift` action lifts, then carries sideways). The
//! physics the residual stands in for (drag, set, damping) does not depend
//! on the horizontal direction, but a network trained on one direction has
//! no reason to correct another. Evaluating it in a randomly turned frame
//! during training (inputs turned, output turned back) asks it to.

use crate::features::FrameInputs;

/// A rotation by `angle` about the line through `pivot` along `axis`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Turn {
    axis: [f64; 3],
    pivot: [f64; 3],
    cos: f64,
    sin: f64,
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

impl Turn {
    /// `None` when `axis` has no direction (zero or not finite).
    pub fn new(axis: [f64; 3], pivot: [f64; 3], angle: f64) -> Option<Self> {
        let norm = dot(axis, axis).sqrt();
        if !(norm.is_finite() && norm > 0.0 && angle.is_finite()) {
            return None;
        }
        Some(Self {
            axis: axis.map(|c| c / norm),
            pivot,
            cos: angle.cos(),
            sin: angle.sin(),
        })
    }

    /// The turn back.
    pub fn inverse(&self) -> Self {
        Self {
            sin: -self.sin,
            ..*self
        }
    }

    /// R·v (Rodrigues).
    pub fn vector(&self, v: [f64; 3]) -> [f64; 3] {
        let k = self.axis;
        let kxv = cross(k, v);
        let along = dot(k, v) * (1.0 - self.cos);
        [0, 1, 2].map(|a| v[a] * self.cos + kxv[a] * self.sin + k[a] * along)
    }

    /// pivot + R·(p − pivot).
    pub fn point(&self, p: [f64; 3]) -> [f64; 3] {
        let r = self.vector([0, 1, 2].map(|a| p[a] - self.pivot[a]));
        [0, 1, 2].map(|a| self.pivot[a] + r[a])
    }

    pub fn vectors(&self, vs: &[[f64; 3]]) -> Vec<[f64; 3]> {
        vs.iter().map(|&v| self.vector(v)).collect()
    }

    pub fn points(&self, ps: &[[f64; 3]]) -> Vec<[f64; 3]> {
        ps.iter().map(|&p| self.point(p)).collect()
    }

    /// The residual's inputs seen from the turned frame.
    pub fn inputs(&self, inputs: &FrameInputs) -> FrameInputs {
        FrameInputs {
            x_tilde: self.points(&inputs.x_tilde),
            v_tilde: self.vectors(&inputs.v_tilde),
            x_start: self.points(&inputs.x_start),
            history: inputs
                .history
                .iter()
                .map(|(x, v)| (self.points(x), self.vectors(v)))
                .collect(),
        }
    }
}
