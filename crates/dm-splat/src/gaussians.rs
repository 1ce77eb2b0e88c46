//! Struct-of-arrays Gaussian parameters and their gradients.

use dm_mpm::real::Real;
use nalgebra::{Matrix3, Vector3};

use crate::SplatError;

/// Quaternions shorter than this are rejected: their direction (the rotation)
/// is round-off.
pub const MIN_QUATERNION_NORM: f64 = 1e-12;

/// A set of 3D Gaussians, one entry per Gaussian in every array.
///
/// Colours are degree-0 (view-independent RGB, display values in `[0, 1]`,
/// not clamped). Rotations are quaternions `(w, x, y, z)`; rendering uses
/// `q / |q|` and differentiates through the normalisation, so an optimiser
/// may step them freely (they are stored unit after construction).
#[derive(Debug, Clone, PartialEq)]
pub struct Gaussians<T: Real> {
    /// World-space centres (metres).
    pub means: Vec<Vector3<T>>,
    /// Natural log of the three standard deviations along the local axes.
    pub log_scales: Vec<Vector3<T>>,
    /// `(w, x, y, z)`.
    pub rotations: Vec<[T; 4]>,
    /// Opacity before the sigmoid.
    pub opacity_logits: Vec<T>,
    /// Linear RGB.
    pub colors: Vec<Vector3<T>>,
}

impl<T: Real> Default for Gaussians<T> {
    fn default() -> Self {
        Self {
            means: Vec::new(),
            log_scales: Vec::new(),
            rotations: Vec::new(),
            opacity_logits: Vec::new(),
            colors: Vec::new(),
        }
    }
}

impl<T: Real> Gaussians<T> {
    pub fn len(&self) -> usize {
        self.means.len()
    }

    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// Appends one Gaussian.
    pub fn push(
        &mut self,
        mean: Vector3<T>,
        log_scale: Vector3<T>,
        rotation: [T; 4],
        opacity_logit: T,
        color: Vector3<T>,
    ) {
        self.means.push(mean);
        self.log_scales.push(log_scale);
        self.rotations.push(rotation);
        self.opacity_logits.push(opacity_logit);
        self.colors.push(color);
    }

    /// Checks equal lengths, finite values and non-degenerate quaternions.
    pub fn validate(&self) -> Result<(), SplatError> {
        let n = self.len();
        let lens = [
            self.log_scales.len(),
            self.rotations.len(),
            self.opacity_logits.len(),
            self.colors.len(),
        ];
        if lens.iter().any(|&l| l != n) {
            return Err(SplatError::LengthMismatch(format!(
                "means {n}, log_scales {}, rotations {}, opacity_logits {}, colors {}",
                lens[0], lens[1], lens[2], lens[3]
            )));
        }
        let finite3 = |v: &Vector3<T>| v.iter().all(|c| c.finite());
        for i in 0..n {
            let field = if !finite3(&self.means[i]) {
                Some("mean")
            } else if !finite3(&self.log_scales[i]) {
                Some("log_scale")
            } else if !self.rotations[i].iter().all(|c| c.finite()) {
                Some("rotation")
            } else if !self.opacity_logits[i].finite() {
                Some("opacity_logit")
            } else if !finite3(&self.colors[i]) {
                Some("color")
            } else {
                None
            };
            if let Some(field) = field {
                return Err(SplatError::NonFinite { index: i, field });
            }
            let norm2: f64 = self.rotations[i].iter().map(|c| c.to_f64().powi(2)).sum();
            if norm2.sqrt() < MIN_QUATERNION_NORM {
                return Err(SplatError::ZeroQuaternion { index: i });
            }
        }
        Ok(())
    }

    /// Sigmoid of the opacity logit of Gaussian `i`.
    pub fn opacity(&self, i: usize) -> T {
        sigmoid(self.opacity_logits[i])
    }

    /// The same Gaussians in another float type.
    pub fn cast<U: Real>(&self) -> Gaussians<U> {
        let v = |v: &Vector3<T>| v.map(|c| U::lit(c.to_f64()));
        Gaussians {
            means: self.means.iter().map(v).collect(),
            log_scales: self.log_scales.iter().map(v).collect(),
            rotations: self
                .rotations
                .iter()
                .map(|q| q.map(|c| U::lit(c.to_f64())))
                .collect(),
            opacity_logits: self
                .opacity_logits
                .iter()
                .map(|c| U::lit(c.to_f64()))
                .collect(),
            colors: self.colors.iter().map(v).collect(),
        }
    }
}

/// Gradients of a scalar loss with respect to every parameter of
/// [`Gaussians`], same layout.
#[derive(Debug, Clone, PartialEq)]
pub struct GaussianGrads<T: Real> {
    pub means: Vec<Vector3<T>>,
    pub log_scales: Vec<Vector3<T>>,
    pub rotations: Vec<[T; 4]>,
    pub opacity_logits: Vec<T>,
    pub colors: Vec<Vector3<T>>,
}

impl<T: Real> GaussianGrads<T> {
    pub fn zeros(n: usize) -> Self {
        Self {
            means: vec![Vector3::zeros(); n],
            log_scales: vec![Vector3::zeros(); n],
            rotations: vec![[T::zero(); 4]; n],
            opacity_logits: vec![T::zero(); n],
            colors: vec![Vector3::zeros(); n],
        }
    }

    pub fn len(&self) -> usize {
        self.means.len()
    }

    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }
}

#[inline]
pub fn sigmoid<T: Real>(x: T) -> T {
    T::one() / (T::one() + (-x).exp())
}

/// Inverse of [`sigmoid`] for `p` in `(0, 1)`.
#[inline]
pub fn logit(p: f64) -> f64 {
    (p / (1.0 - p)).ln()
}

/// Rotation matrix of a unit quaternion `(w, x, y, z)`.
#[inline]
pub fn quat_to_matrix<T: Real>(q: &[T; 4]) -> Matrix3<T> {
    let [w, x, y, z] = *q;
    let two = T::lit(2.0);
    let one = T::one();
    Matrix3::new(
        one - two * (y * y + z * z),
        two * (x * y - w * z),
        two * (x * z + w * y),
        two * (x * y + w * z),
        one - two * (x * x + z * z),
        two * (y * z - w * x),
        two * (x * z - w * y),
        two * (y * z + w * x),
        one - two * (x * x + y * y),
    )
}

/// `q / |q|` and `|q|`.
#[inline]
pub fn normalize_quat<T: Real>(q: &[T; 4]) -> ([T; 4], T) {
    let norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    (q.map(|c| c / norm), norm)
}
