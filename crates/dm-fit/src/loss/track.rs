//! Track loss: visible tracked points against the particles they were
//! matched to at frame 0 (method.md §7 "3D track alignment", matching as in
//! the §9 Track metric).

use dm_mpm::neighbors::PointIndex;

use super::{LossError, LossValue, check_finite, check_len, norm2, sub};

/// Each tracked point's particle: the particle nearest to it at frame 0
/// (ties → lowest particle index), fixed for the whole fit.
///
/// Several tracked points may share a particle; their gradients add up.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TrackMatch {
    particle_of_point: Vec<usize>,
    particle_count: usize,
}

impl TrackMatch {
    /// Matches every tracked point (visible at frame 0 or not: its frame-0
    /// position must still be finite) to its nearest frame-0 particle.
    pub fn new(
        first_frame_particles: &[[f64; 3]],
        observed_first_frame: &[[f64; 3]],
    ) -> Result<Self, LossError> {
        check_finite("first_frame_particles", first_frame_particles, |_| true)?;
        check_finite("observed_first_frame", observed_first_frame, |_| true)?;
        if first_frame_particles.is_empty() && !observed_first_frame.is_empty() {
            return Err(LossError::Empty {
                argument: "first_frame_particles",
            });
        }
        let index = PointIndex::new(first_frame_particles);
        let particle_of_point = observed_first_frame
            .iter()
            .map(|o| {
                index
                    .nearest(o, 1)
                    .first()
                    .map(|&(i, _)| i)
                    .ok_or(LossError::Empty {
                        argument: "first_frame_particles",
                    })
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            particle_of_point,
            particle_count: first_frame_particles.len(),
        })
    }

    /// The matched particle of each tracked point.
    pub fn particles(&self) -> &[usize] {
        &self.particle_of_point
    }

    pub fn point_count(&self) -> usize {
        self.particle_of_point.len()
    }

    pub fn particle_count(&self) -> usize {
        self.particle_count
    }

    fn check(
        &self,
        predicted: &[[f64; 3]],
        observed: &[[f64; 3]],
        visible: &[bool],
    ) -> Result<(), LossError> {
        check_len("predicted", self.particle_count, predicted.len())?;
        check_len("observed", self.point_count(), observed.len())?;
        check_len("visible", self.point_count(), visible.len())?;
        check_finite("observed", observed, |k| visible[k])?;
        check_finite("predicted", predicted, |_| true)
    }

    /// `L_track = (1/V) Σ_{k visible} |x_{m(k)} − o_k|²`, V the number of
    /// visible points, with `∂L/∂x_{m(k)} += (2/V)(x_{m(k)} − o_k)`.
    ///
    /// Squared distance, so the training loss is smooth (its gradient
    /// vanishes at the optimum instead of keeping unit length); the
    /// evaluation metric is the plain mean distance, [`Self::track_error`].
    /// No visible point → value 0 and a zero gradient.
    pub fn track_loss(
        &self,
        predicted: &[[f64; 3]],
        observed: &[[f64; 3]],
        visible: &[bool],
    ) -> Result<LossValue, LossError> {
        self.check(predicted, observed, visible)?;
        let mut out = LossValue::zero(predicted.len());
        let count = visible.iter().filter(|&&v| v).count();
        if count == 0 {
            return Ok(out);
        }
        let scale = 1.0 / count as f64;
        for (k, (&p, o)) in self.particle_of_point.iter().zip(observed).enumerate() {
            if !visible[k] {
                continue;
            }
            let d = sub(&predicted[p], o);
            out.value += scale * norm2(&d);
            for a in 0..3 {
                out.grad[p][a] += 2.0 * scale * d[a];
            }
        }
        Ok(out)
    }

    /// The §9 Track metric of one frame: mean Euclidean distance over the
    /// visible points, metres; `None` when none is visible.
    pub fn track_error(
        &self,
        predicted: &[[f64; 3]],
        observed: &[[f64; 3]],
        visible: &[bool],
    ) -> Result<Option<f64>, LossError> {
        self.check(predicted, observed, visible)?;
        let (sum, count) = self
            .particle_of_point
            .iter()
            .zip(observed)
            .zip(visible)
            .filter(|&(_, &v)| v)
            .fold((0.0, 0usize), |(s, c), ((&p, o), _)| {
                (s + norm2(&sub(&predicted[p], o)).sqrt(), c + 1)
            });
        Ok((count > 0).then(|| sum / count as f64))
    }
}
