//! Helpers shared by the dm-splat test crates.
#![allow(dead_code)] // each test crate uses a different subset

use dm_splat::Gaussians;
use dm_splat::gaussians::logit;
use dm_view::Camera;
use nalgebra::{Point3, Vector3};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

pub fn uniform(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    lo + (hi - lo) * rng.random::<f64>()
}

/// A quaternion of random direction and length in [0.7, 1.3] (not unit, so
/// the normalisation is exercised too).
pub fn random_quat(rng: &mut ChaCha8Rng) -> [f64; 4] {
    loop {
        let q = [0; 4].map(|_| uniform(rng, -1.0, 1.0));
        let n = q.iter().map(|c| c * c).sum::<f64>().sqrt();
        if n > 0.1 && n <= 1.0 {
            let len = uniform(rng, 0.7, 1.3);
            return q.map(|c| c / n * len);
        }
    }
}

/// Small test camera looking at the origin from ~0.8 m.
pub fn camera(width: u32, height: u32) -> Camera {
    Camera::look_at(
        Point3::new(0.5, -0.6, 0.3),
        Point3::new(0.0, 0.0, 0.0),
        Vector3::z(),
        width,
        height,
        40.0,
    )
}

/// `n` random Gaussians in a 0.12 m ball around the origin, σ 1.5–5 cm,
/// opacity in `opacity` range.
pub fn random_gaussians(rng: &mut ChaCha8Rng, n: usize, opacity: (f64, f64)) -> Gaussians<f64> {
    let mut g = Gaussians::default();
    for _ in 0..n {
        let mean = Vector3::from_fn(|_, _| uniform(rng, -0.12, 0.12));
        let log_scale = Vector3::from_fn(|_, _| uniform(rng, 0.015f64.ln(), 0.05f64.ln()));
        let color = Vector3::from_fn(|_, _| uniform(rng, 0.0, 1.0));
        g.push(
            mean,
            log_scale,
            random_quat(rng),
            logit(uniform(rng, opacity.0, opacity.1)),
            color,
        );
    }
    g
}

/// Central-difference gradient of `objective` at `x` with step `h`.
pub fn fd_gradient(objective: impl Fn(&[f64]) -> f64, x: &[f64], h: f64) -> Vec<f64> {
    let mut probe = x.to_vec();
    (0..x.len())
        .map(|i| {
            probe[i] = x[i] + h;
            let up = objective(&probe);
            probe[i] = x[i] - h;
            let down = objective(&probe);
            probe[i] = x[i];
            (up - down) / (2.0 * h)
        })
        .collect()
}

/// `max_i |a_i − b_i| / max(max|a|, max|b|, floor)`: relative to the
/// gradient's scale, so entries that happen to be near zero do not blow it up.
pub fn grad_rel_err(analytic: &[f64], fd: &[f64]) -> f64 {
    assert_eq!(analytic.len(), fd.len());
    let amax = |v: &[f64]| v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let diff = analytic
        .iter()
        .zip(fd)
        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    diff / amax(analytic).max(amax(fd)).max(1e-12)
}

/// Packs all parameters of the Gaussians into one vector (per Gaussian:
/// mean, log-scale, quaternion, opacity logit, colour).
pub fn pack(g: &Gaussians<f64>) -> Vec<f64> {
    let mut x = Vec::with_capacity(14 * g.len());
    for i in 0..g.len() {
        x.extend(g.means[i].iter());
        x.extend(g.log_scales[i].iter());
        x.extend(g.rotations[i]);
        x.push(g.opacity_logits[i]);
        x.extend(g.colors[i].iter());
    }
    x
}

pub fn unpack(x: &[f64]) -> Gaussians<f64> {
    let mut g = Gaussians::default();
    for c in x.chunks_exact(14) {
        g.push(
            Vector3::new(c[0], c[1], c[2]),
            Vector3::new(c[3], c[4], c[5]),
            [c[6], c[7], c[8], c[9]],
            c[10],
            Vector3::new(c[11], c[12], c[13]),
        );
    }
    g
}

pub fn pack_grads(g: &dm_splat::GaussianGrads<f64>) -> Vec<f64> {
    let mut x = Vec::with_capacity(14 * g.len());
    for i in 0..g.len() {
        x.extend(g.means[i].iter());
        x.extend(g.log_scales[i].iter());
        x.extend(g.rotations[i]);
        x.push(g.opacity_logits[i]);
        x.extend(g.colors[i].iter());
    }
    x
}
