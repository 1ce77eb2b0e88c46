//! Smooth random scalar fields (a few random Fourier modes) for spatially
//! varying material.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A smooth zero-mean field with unit standard deviation over space,
/// wavelengths between `min_wavelength` and 4x that.
#[derive(Clone, Debug)]
pub struct SmoothField {
    modes: Vec<([f64; 3], f64)>,
}

impl SmoothField {
    pub fn new(seed: u64, min_wavelength: f64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let modes = (0..12)
            .map(|_| {
                let dir = loop {
                    let d = [0, 1, 2].map(|_| 2.0 * rng.random::<f64>() - 1.0);
                    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                    if n > 0.1 && n <= 1.0 {
                        break d.map(|c| c / n);
                    }
                };
                let wavelength = min_wavelength * (1.0 + 3.0 * rng.random::<f64>());
                let k = std::f64::consts::TAU / wavelength;
                (
                    dir.map(|c| c * k),
                    std::f64::consts::TAU * rng.random::<f64>(),
                )
            })
            .collect();
        Self { modes }
    }

    pub fn at(&self, p: [f64; 3]) -> f64 {
        let sum: f64 = self
            .modes
            .iter()
            .map(|(k, phase)| (k[0] * p[0] + k[1] * p[1] + k[2] * p[2] + phase).cos())
            .sum();
        // Each cosine has variance 1/2.
        sum / (self.modes.len() as f64 * 0.5).sqrt()
    }
}
