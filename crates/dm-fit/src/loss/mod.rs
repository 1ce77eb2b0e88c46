//! Fitting losses of the dynamics stages (method.md §7):
//!
//! `L_dyn = w_track L_track + w_shape L_shape + w_length L_length`
//!
//! * [`TrackMatch::track_loss`]: visible tracked points against the
//!   particle each was matched to (once, at frame 0);
//! * [`shape_loss`]: one-directional Chamfer, observed → predicted surface
//!   particles;
//! * [`LengthPreservation::loss`]: local length preservation between
//!   neighbouring particles (a stretching regulariser).
//!
//! Every term works on one frame, in `f64`, on `[f64; 3]` slices (the caller
//! converts from the simulator's storage), and returns a [`LossValue`]: the
//! value *and* its hand-written gradient with respect to that frame's
//! predicted particle positions, one `[f64; 3]` per particle. Those
//! gradients seed the simulator's adjoint.
//!
//! The data terms use *squared* distances (smooth, so the adjoint sees a
//! gradient that shrinks as the fit improves); the evaluation metrics of
//! method.md §9 (`dm_model::metrics`) use plain distances.
//! [`TrackMatch::track_error`] and [`chamfer_error`] give those plain
//! distances for reporting during a fit.
//!
//! Invisible points are ignored and may hold any value (including NaN).
//! Input-dependent failures (slice lengths that disagree, non-finite
//! positions where they are used, an empty particle set) are reported as
//! [`LossError`]s, never panics.

pub mod length;
pub mod shape;
pub mod track;

pub use length::{LengthPreservation, PairSelection};
pub use shape::{chamfer_error, shape_loss};
pub use track::TrackMatch;

use dm_bundle::Tracks;

/// Errors of the loss functions.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LossError {
    /// Two inputs that must agree in length do not.
    #[error("`{argument}` has {actual} entries, expected {expected}")]
    LengthMismatch {
        argument: &'static str,
        expected: usize,
        actual: usize,
    },
    /// A position that the loss uses is NaN or infinite.
    #[error("`{argument}` has a non-finite position at index {index}")]
    NonFinite {
        argument: &'static str,
        index: usize,
    },
    /// Points must be matched to particles but there are none.
    #[error("`{argument}` is empty, so nothing can be matched to it")]
    Empty { argument: &'static str },
    /// A parameter is out of its valid range.
    #[error("invalid `{argument}`: {reason}")]
    InvalidArgument {
        argument: &'static str,
        reason: String,
    },
}

/// A loss value and its gradient with respect to the predicted particle
/// positions of one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct LossValue {
    pub value: f64,
    /// `∂value/∂x_p`, one entry per predicted particle.
    pub grad: Vec<[f64; 3]>,
}

impl LossValue {
    /// Value 0 and a zero gradient over `particle_count` particles.
    pub fn zero(particle_count: usize) -> Self {
        Self {
            value: 0.0,
            grad: vec![[0.0; 3]; particle_count],
        }
    }

    /// `self += weight · other` (value and gradient).
    pub fn add_scaled(&mut self, weight: f64, other: &LossValue) -> Result<(), LossError> {
        check_len("other.grad", self.grad.len(), other.grad.len())?;
        self.value += weight * other.value;
        for (g, o) in self.grad.iter_mut().zip(&other.grad) {
            for a in 0..3 {
                g[a] += weight * o[a];
            }
        }
        Ok(())
    }
}

/// Weights of the three terms of `L_dyn`.
///
/// Defaults (method.md gives no values; these are ours):
/// * `track = 1.0`, `shape = 1.0`: both are mean *squared* distances in m²
///   over the same visible observed points, so they share units and scale;
///   equal weights let neither data term dominate.
/// * `length = 0.1`: also m² (mean squared deviation from the rest length),
///   but it is a prior, not data. It must only stop the fit from stretching
///   the object where observations are sparse or occluded (Chamfer only
///   pulls particles *towards* observed points, it never penalises surface
///   particles drifting away from them), so it is kept an order of
///   magnitude below the data terms, which then decide wherever they
///   disagree with it.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LossWeights {
    pub track: f64,
    pub shape: f64,
    pub length: f64,
}

impl Default for LossWeights {
    fn default() -> Self {
        Self {
            track: 1.0,
            shape: 1.0,
            length: 0.1,
        }
    }
}

impl LossWeights {
    fn validate(&self) -> Result<(), LossError> {
        for (argument, w) in [
            ("weights.track", self.track),
            ("weights.shape", self.shape),
            ("weights.length", self.length),
        ] {
            if !(w.is_finite() && w >= 0.0) {
                return Err(LossError::InvalidArgument {
                    argument,
                    reason: format!("weight must be finite and >= 0, got {w}"),
                });
            }
        }
        Ok(())
    }
}

/// The observed points of one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct ObservedFrame {
    /// World metres, one per tracked point.
    pub points: Vec<[f64; 3]>,
    /// Seen by at least one camera: used by the shape (Chamfer) term.
    pub visible: Vec<bool>,
    /// Visible *and* trustworthy for supervising motion: used by the track
    /// term.
    pub track_valid: Vec<bool>,
}

impl ObservedFrame {
    /// From raw slices, using `visible` for both terms.
    pub fn new(points: Vec<[f64; 3]>, visible: Vec<bool>) -> Result<Self, LossError> {
        check_len("visible", points.len(), visible.len())?;
        Ok(Self {
            track_valid: visible.clone(),
            points,
            visible,
        })
    }

    /// Frame `frame` of a bundle's tracks: `visible` is the visibility flag,
    /// `track_valid` is visibility and `object_motion_valid` together.
    pub fn from_tracks(tracks: &Tracks, frame: usize) -> Result<Self, LossError> {
        let frames = tracks.frame_count();
        if frame >= frames {
            return Err(LossError::InvalidArgument {
                argument: "frame",
                reason: format!("frame {frame} out of range for {frames} frames"),
            });
        }
        let n = tracks.object_point_count();
        for (argument, shape) in [
            ("tracks.object_visibility", tracks.object_visibility.shape()),
            (
                "tracks.object_motion_valid",
                tracks.object_motion_valid.shape(),
            ),
        ] {
            if shape[0] != frames || shape[1] != n {
                return Err(LossError::LengthMismatch {
                    argument,
                    expected: frames * n,
                    actual: shape[0] * shape[1],
                });
            }
        }
        let p = &tracks.object_points;
        let points = (0..n)
            .map(|k| {
                [
                    f64::from(p[[frame, k, 0]]),
                    f64::from(p[[frame, k, 1]]),
                    f64::from(p[[frame, k, 2]]),
                ]
            })
            .collect();
        let visible: Vec<bool> = (0..n)
            .map(|k| tracks.object_visibility[[frame, k]])
            .collect();
        let track_valid = (0..n)
            .map(|k| visible[k] && tracks.object_motion_valid[[frame, k]])
            .collect();
        Ok(Self {
            points,
            visible,
            track_valid,
        })
    }
}

/// What stays fixed over a fit: the frame-0 track matching, the length
/// pairs, and how many of the particles (the first ones) are surface
/// particles.
#[derive(Debug, Clone, Copy)]
pub struct LossTerms<'a> {
    pub track: &'a TrackMatch,
    pub length: &'a LengthPreservation,
    pub surface_count: usize,
}

/// `L_dyn` of one frame: the weighted total and the unweighted terms.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameLoss {
    /// `weights.track · track + weights.shape · shape + weights.length · length`,
    /// with its gradient.
    pub total: LossValue,
    /// Unweighted term values (for logging).
    pub track: f64,
    pub shape: f64,
    pub length: f64,
}

/// Combines the three terms for one predicted frame. A term whose weight is
/// exactly 0 is skipped (its value is reported as 0).
pub fn frame_loss(
    weights: &LossWeights,
    terms: &LossTerms<'_>,
    predicted: &[[f64; 3]],
    observed: &ObservedFrame,
) -> Result<FrameLoss, LossError> {
    weights.validate()?;
    check_len(
        "observed.visible",
        observed.points.len(),
        observed.visible.len(),
    )?;
    check_len(
        "observed.track_valid",
        observed.points.len(),
        observed.track_valid.len(),
    )?;
    let mut total = LossValue::zero(predicted.len());
    let mut values = [0.0; 3];
    if weights.track != 0.0 {
        let term = terms
            .track
            .track_loss(predicted, &observed.points, &observed.track_valid)?;
        total.add_scaled(weights.track, &term)?;
        values[0] = term.value;
    }
    if weights.shape != 0.0 {
        let term = shape_loss(
            predicted,
            terms.surface_count,
            &observed.points,
            &observed.visible,
        )?;
        total.add_scaled(weights.shape, &term)?;
        values[1] = term.value;
    }
    if weights.length != 0.0 {
        let term = terms.length.loss(predicted)?;
        total.add_scaled(weights.length, &term)?;
        values[2] = term.value;
    }
    Ok(FrameLoss {
        total,
        track: values[0],
        shape: values[1],
        length: values[2],
    })
}

pub(crate) fn check_len(
    argument: &'static str,
    expected: usize,
    actual: usize,
) -> Result<(), LossError> {
    if expected == actual {
        Ok(())
    } else {
        Err(LossError::LengthMismatch {
            argument,
            expected,
            actual,
        })
    }
}

/// Errors on the first non-finite point among those `used` selects.
pub(crate) fn check_finite(
    argument: &'static str,
    points: &[[f64; 3]],
    used: impl Fn(usize) -> bool,
) -> Result<(), LossError> {
    match points
        .iter()
        .enumerate()
        .find(|&(i, p)| used(i) && !p.iter().all(|c| c.is_finite()))
    {
        Some((index, _)) => Err(LossError::NonFinite { argument, index }),
        None => Ok(()),
    }
}

pub(crate) fn sub(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn norm2(d: &[f64; 3]) -> f64 {
    d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
}
