//! Differentiable SSIM for the appearance fit (the D-SSIM term of 3DGS's
//! loss), with its gradient written by hand beside the forward.
//!
//! As 3DGS's training loss (not the benchmark metric, which is dm-eval's
//! scikit-image SSIM over valid windows): per channel, local statistics
//! under an 11×11 Gaussian window (σ 1.5, normalised) with zero padding
//! ("same" size), the SSIM map at every pixel, its mean over pixels and
//! channels. With `μx = G∗x`, `Exx = G∗x²`, `Exy = G∗(xy)` (likewise y):
//!
//! ```text
//! S = (2 μx μy + C1)(2 (Exy − μx μy) + C2) / ((μx² + μy² + C1)(Exx − μx² + Eyy − μy² + C2))
//! ```
//!
//! Gradient with respect to `x` (the render): with `a = ∂S/∂μx`,
//! `b = ∂S/∂Exx`, `c = ∂S/∂Exy` per pixel (each at fixed other moments),
//! `∂ΣS/∂x_q = (G∗a)_q + 2 x_q (G∗b)_q + y_q (G∗c)_q` — the window is
//! symmetric, so its zero-padded transpose is the same filter.

use rayon::prelude::*;

/// Gaussian window of 3DGS's SSIM: 11 taps, σ 1.5.
pub const SSIM_WINDOW_RADIUS: usize = 5;
pub const SSIM_WINDOW_SIGMA: f64 = 1.5;
/// Stabilisers for data range 1: `(0.01)²` and `(0.03)²`.
pub const SSIM_C1: f64 = 0.01 * 0.01;
pub const SSIM_C2: f64 = 0.03 * 0.03;

/// Normalised 1D Gaussian taps (the 2D window is their outer product).
fn window_taps() -> [f64; 2 * SSIM_WINDOW_RADIUS + 1] {
    let mut taps = [0.0; 2 * SSIM_WINDOW_RADIUS + 1];
    for (k, t) in taps.iter_mut().enumerate() {
        let d = k as f64 - SSIM_WINDOW_RADIUS as f64;
        *t = (-d * d / (2.0 * SSIM_WINDOW_SIGMA * SSIM_WINDOW_SIGMA)).exp();
    }
    let sum: f64 = taps.iter().sum();
    taps.map(|t| t / sum)
}

/// Separable Gaussian blur of a `width × height` plane with zero padding.
fn blur(plane: &[f64], width: usize, height: usize, taps: &[f64]) -> Vec<f64> {
    let r = SSIM_WINDOW_RADIUS as isize;
    let mut horizontal = vec![0.0; plane.len()];
    for y in 0..height {
        let row = &plane[y * width..(y + 1) * width];
        for x in 0..width {
            let mut acc = 0.0;
            for (k, &t) in taps.iter().enumerate() {
                let xx = x as isize + k as isize - r;
                if xx >= 0 && (xx as usize) < width {
                    acc += t * row[xx as usize];
                }
            }
            horizontal[y * width + x] = acc;
        }
    }
    let mut out = vec![0.0; plane.len()];
    for y in 0..height {
        for (k, &t) in taps.iter().enumerate() {
            let yy = y as isize + k as isize - r;
            if yy < 0 || yy as usize >= height {
                continue;
            }
            let src = &horizontal[yy as usize * width..(yy as usize + 1) * width];
            let dst = &mut out[y * width..(y + 1) * width];
            for (d, s) in dst.iter_mut().zip(src) {
                *d += t * s;
            }
        }
    }
    out
}

/// One channel's SSIM sum over pixels and, when asked, its gradient with
/// respect to `x`.
fn channel_ssim(
    x: &[f64],
    y: &[f64],
    width: usize,
    height: usize,
    want_grad: bool,
) -> (f64, Option<Vec<f64>>) {
    let taps = window_taps();
    let square = |v: &[f64]| v.iter().map(|a| a * a).collect::<Vec<_>>();
    let mu_x = blur(x, width, height, &taps);
    let mu_y = blur(y, width, height, &taps);
    let e_xx = blur(&square(x), width, height, &taps);
    let e_yy = blur(&square(y), width, height, &taps);
    let xy: Vec<f64> = x.iter().zip(y).map(|(a, b)| a * b).collect();
    let e_xy = blur(&xy, width, height, &taps);
    let n = x.len();
    let mut total = 0.0;
    let (mut da, mut db, mut dc) = if want_grad {
        (vec![0.0; n], vec![0.0; n], vec![0.0; n])
    } else {
        (Vec::new(), Vec::new(), Vec::new())
    };
    for p in 0..n {
        let (mx, my) = (mu_x[p], mu_y[p]);
        let a1 = 2.0 * mx * my + SSIM_C1;
        let a2 = 2.0 * (e_xy[p] - mx * my) + SSIM_C2;
        let b1 = mx * mx + my * my + SSIM_C1;
        let b2 = (e_xx[p] - mx * mx) + (e_yy[p] - my * my) + SSIM_C2;
        let s = a1 * a2 / (b1 * b2);
        total += s;
        if want_grad {
            da[p] = 2.0 * my * (a2 - a1) / (b1 * b2) - 2.0 * mx * s * (1.0 / b1 - 1.0 / b2);
            db[p] = -s / b2;
            dc[p] = 2.0 * a1 / (b1 * b2);
        }
    }
    if !want_grad {
        return (total, None);
    }
    let ga = blur(&da, width, height, &taps);
    let gb = blur(&db, width, height, &taps);
    let gc = blur(&dc, width, height, &taps);
    let grad = (0..n)
        .map(|q| ga[q] + 2.0 * x[q] * gb[q] + y[q] * gc[q])
        .collect();
    (total, Some(grad))
}

/// Mean SSIM (3DGS's training variant, see the module docs) of the RGB
/// images `x` and `y` (row-major, `width × height`) and, when `want_grad`,
/// its gradient with respect to `x`. Sizes must agree (checked by the
/// caller: [`crate::fit`]); an empty image gives SSIM 1.
pub fn ssim_rgb(
    x: &[[f64; 3]],
    y: &[[f64; 3]],
    width: usize,
    height: usize,
    want_grad: bool,
) -> (f64, Option<Vec<[f64; 3]>>) {
    let n = width * height;
    debug_assert_eq!(x.len(), n);
    debug_assert_eq!(y.len(), n);
    if n == 0 {
        return (1.0, want_grad.then(Vec::new));
    }
    let per_channel: Vec<(f64, Option<Vec<f64>>)> = (0..3)
        .into_par_iter()
        .map(|c| {
            let xc: Vec<f64> = x.iter().map(|v| v[c]).collect();
            let yc: Vec<f64> = y.iter().map(|v| v[c]).collect();
            channel_ssim(&xc, &yc, width, height, want_grad)
        })
        .collect();
    let scale = 1.0 / (3 * n) as f64;
    let mean = per_channel.iter().map(|(s, _)| s).sum::<f64>() * scale;
    let grad = want_grad.then(|| {
        let mut g = vec![[0.0; 3]; n];
        for (c, (_, gc)) in per_channel.iter().enumerate() {
            if let Some(gc) = gc {
                for (dst, src) in g.iter_mut().zip(gc) {
                    dst[c] = src * scale;
                }
            }
        }
        g
    });
    (mean, grad)
}
