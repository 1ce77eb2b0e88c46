//! Image metrics of the benchmark (method.md §9) and its masking rule.
//!
//! Images are 8-bit RGB read as values in [0, 1] (value / 255), computed in
//! f64. The definitions follow scikit-image so that numbers compare with
//! published ones:
//! * PSNR = 10 log10(1 / MSE) over every pixel and channel (data range 1);
//!   +∞ for identical images.
//! * SSIM = `structural_similarity(gaussian_weights=True, sigma=1.5,
//!   use_sample_covariance=False, data_range=1, channel_axis=2)`: per channel,
//!   local means, variances and covariance under an 11×11 Gaussian window
//!   (σ 1.5, truncated at 3.5 σ, normalised), the SSIM map over the *valid*
//!   window positions only (scikit-image filters with reflection but then
//!   crops the 5-pixel border, which leaves exactly the valid positions),
//!   its mean, then the mean over channels.
//! * IoU of two masks (non-zero = inside); NaN when both are empty.

use image::{GrayImage, Rgb, RgbImage};

/// Gaussian window of SSIM: σ and radius (scikit-image: `int(3.5 σ + 0.5)`).
pub const SSIM_SIGMA: f64 = 1.5;
pub const SSIM_RADIUS: usize = 5;
pub const SSIM_K1: f64 = 0.01;
pub const SSIM_K2: f64 = 0.03;

/// Why an image metric could not be computed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ImageMetricError {
    #[error("{metric}: image sizes differ ({a:?} vs {b:?})")]
    SizeMismatch {
        metric: &'static str,
        a: (u32, u32),
        b: (u32, u32),
    },
    #[error("{metric}: a {size:?} image is smaller than the {window}x{window} window")]
    TooSmall {
        metric: &'static str,
        size: (u32, u32),
        window: usize,
    },
    #[error("{metric}: empty image")]
    Empty { metric: &'static str },
}

fn same_size(metric: &'static str, a: (u32, u32), b: (u32, u32)) -> Result<(), ImageMetricError> {
    if a != b {
        return Err(ImageMetricError::SizeMismatch { metric, a, b });
    }
    if a.0 == 0 || a.1 == 0 {
        return Err(ImageMetricError::Empty { metric });
    }
    Ok(())
}

/// Peak signal-to-noise ratio in dB for data range 1; +∞ when identical.
pub fn psnr(a: &RgbImage, b: &RgbImage) -> Result<f64, ImageMetricError> {
    same_size("PSNR", a.dimensions(), b.dimensions())?;
    let squared_error: f64 = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(&x, &y)| (f64::from(x) / 255.0 - f64::from(y) / 255.0).powi(2))
        .sum();
    let mse = squared_error / a.as_raw().len() as f64;
    Ok(if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    })
}

/// The normalised 1D Gaussian of the SSIM window (2 · radius + 1 taps).
fn gaussian_taps() -> [f64; 2 * SSIM_RADIUS + 1] {
    let mut taps = [0.0; 2 * SSIM_RADIUS + 1];
    for (i, tap) in taps.iter_mut().enumerate() {
        let x = i as f64 - SSIM_RADIUS as f64;
        *tap = (-0.5 * x * x / (SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let sum: f64 = taps.iter().sum();
    taps.map(|t| t / sum)
}

/// Separable Gaussian filter over valid positions: a `w × h` plane becomes
/// `(w − 2r) × (h − 2r)`.
fn filter_valid(plane: &[f64], w: usize, h: usize, taps: &[f64]) -> Vec<f64> {
    let window = taps.len();
    let (ow, oh) = (w + 1 - window, h + 1 - window);
    // Rows first (full height), then columns.
    let mut rows = vec![0.0; ow * h];
    for y in 0..h {
        let line = &plane[y * w..(y + 1) * w];
        for x in 0..ow {
            rows[y * ow + x] = taps
                .iter()
                .zip(&line[x..x + window])
                .map(|(t, v)| t * v)
                .sum();
        }
    }
    let mut out = vec![0.0; ow * oh];
    for y in 0..oh {
        for x in 0..ow {
            out[y * ow + x] = taps
                .iter()
                .enumerate()
                .map(|(k, t)| t * rows[(y + k) * ow + x])
                .sum();
        }
    }
    out
}

/// Mean SSIM of one channel plane pair.
fn ssim_plane(a: &[f64], b: &[f64], w: usize, h: usize, taps: &[f64]) -> f64 {
    let c1 = (SSIM_K1 * 1.0).powi(2);
    let c2 = (SSIM_K2 * 1.0).powi(2);
    let product =
        |f: fn(f64, f64) -> f64| -> Vec<f64> { a.iter().zip(b).map(|(&x, &y)| f(x, y)).collect() };
    let mu_a = filter_valid(a, w, h, taps);
    let mu_b = filter_valid(b, w, h, taps);
    let aa = filter_valid(&product(|x, _| x * x), w, h, taps);
    let bb = filter_valid(&product(|_, y| y * y), w, h, taps);
    let ab = filter_valid(&product(|x, y| x * y), w, h, taps);
    let n = mu_a.len();
    let mut total = 0.0;
    for i in 0..n {
        let (ma, mb) = (mu_a[i], mu_b[i]);
        let var_a = aa[i] - ma * ma;
        let var_b = bb[i] - mb * mb;
        let cov = ab[i] - ma * mb;
        total += ((2.0 * ma * mb + c1) * (2.0 * cov + c2))
            / ((ma * ma + mb * mb + c1) * (var_a + var_b + c2));
    }
    total / n as f64
}

/// Structural similarity as scikit-image computes it with
/// `gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
/// data_range=1`, averaged over the three channels.
pub fn ssim(a: &RgbImage, b: &RgbImage) -> Result<f64, ImageMetricError> {
    same_size("SSIM", a.dimensions(), b.dimensions())?;
    let window = 2 * SSIM_RADIUS + 1;
    let (w, h) = (a.width() as usize, a.height() as usize);
    if w < window || h < window {
        return Err(ImageMetricError::TooSmall {
            metric: "SSIM",
            size: a.dimensions(),
            window,
        });
    }
    let taps = gaussian_taps();
    let plane = |image: &RgbImage, c: usize| -> Vec<f64> {
        image.pixels().map(|p| f64::from(p.0[c]) / 255.0).collect()
    };
    let total: f64 = (0..3)
        .map(|c| ssim_plane(&plane(a, c), &plane(b, c), w, h, &taps))
        .sum();
    Ok(total / 3.0)
}

/// Intersection over union of the non-zero pixels of two masks; NaN when
/// both are empty (nothing to compare: the frame is left out of means).
pub fn iou(a: &GrayImage, b: &GrayImage) -> Result<f64, ImageMetricError> {
    same_size("IoU", a.dimensions(), b.dimensions())?;
    let (mut inter, mut union) = (0usize, 0usize);
    for (x, y) in a.as_raw().iter().zip(b.as_raw()) {
        let (x, y) = (*x > 0, *y > 0);
        inter += usize::from(x && y);
        union += usize::from(x || y);
    }
    Ok(if union == 0 {
        f64::NAN
    } else {
        inter as f64 / union as f64
    })
}

/// The benchmark's image pair (method.md §9): the ground truth is the
/// observed image × the object mask on black; the prediction is the render
/// (already on black); hand pixels are black in both.
pub fn benchmark_pair(
    observed: &RgbImage,
    object_mask: &GrayImage,
    hand_mask: &GrayImage,
    rendered: &RgbImage,
) -> Result<(RgbImage, RgbImage), ImageMetricError> {
    let size = observed.dimensions();
    for other in [
        object_mask.dimensions(),
        hand_mask.dimensions(),
        rendered.dimensions(),
    ] {
        same_size("masking", size, other)?;
    }
    let black = Rgb([0, 0, 0]);
    let mut truth = observed.clone();
    let mut prediction = rendered.clone();
    for (x, y, pixel) in truth.enumerate_pixels_mut() {
        let hand = hand_mask.get_pixel(x, y).0[0] > 0;
        if hand || object_mask.get_pixel(x, y).0[0] == 0 {
            *pixel = black;
        }
        if hand {
            prediction.put_pixel(x, y, black);
        }
    }
    Ok((truth, prediction))
}

/// `mask` with the pixels of `hand` cleared (the hand-removal rule applied
/// to the rendered alpha before IoU).
pub fn without_hand(mask: &GrayImage, hand: &GrayImage) -> Result<GrayImage, ImageMetricError> {
    same_size("masking", mask.dimensions(), hand.dimensions())?;
    let mut out = mask.clone();
    for (value, h) in out.iter_mut().zip(hand.as_raw()) {
        if *h > 0 {
            *value = 0;
        }
    }
    Ok(out)
}
