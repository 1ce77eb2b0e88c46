//! Metric scale of a monocular depth map against reference depth (method.md §8).
//!
//! Monocular depth networks give depth up to an unknown scale (and, for
//! affine-invariant ones, a shift). Where some reference depth exists on the
//! object (a sensor frame, lifted tracks, a fitted mesh), the metric map is
//! `scale · mono + shift`, with the parameters minimising the **median**
//! absolute residual over the masked object pixels. The median ignores up to
//! half the pixels being wrong (mask bleed, depth edges, specularities),
//! where least squares is dragged by a single one.
//!
//! The objective is piecewise linear in the scale and may have several local
//! minima, so the fit scans a log-spaced grid over four decades around the
//! ratio of medians, then refines the best bracket with golden-section
//! search. For a given scale the best shift is the median of
//! `reference − scale · mono` (the L1 location), so the shift needs no search.

use ndarray::ArrayView2;

/// Grid points of the coarse log-scale scan.
const GRID_POINTS: usize = 400;
/// The scan covers the ratio of medians times / divided by this factor.
const GRID_SPAN: f64 = 100.0;
/// Golden-section iterations; each shrinks the bracket by 0.618, so 80
/// iterations take the 2.3 % grid step far below f64 resolution.
const GOLDEN_ITERATIONS: usize = 80;
/// Fewer valid pixel pairs than this give no meaningful median.
pub const MIN_SAMPLES: usize = 8;

/// Which parameters the fit estimates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DepthModel {
    /// `metric = scale · mono` (metric-up-to-scale networks).
    Scale,
    /// `metric = scale · mono + shift` (affine-invariant networks).
    ScaleShift,
}

/// A fitted scale (and shift).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ScaleFit {
    pub scale: f64,
    /// Metres; 0 for [`DepthModel::Scale`].
    pub shift_m: f64,
    /// The objective at the optimum: median |reference − (scale · mono + shift)|.
    pub median_abs_residual_m: f64,
    /// Pixel pairs used.
    pub samples: usize,
}

impl ScaleFit {
    /// The metric depth of a monocular value.
    pub fn apply(&self, mono: f64) -> f64 {
        self.scale * mono + self.shift_m
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ScaleFitError {
    #[error("scale fit: {mono} monocular values but {reference} reference values")]
    LengthMismatch { mono: usize, reference: usize },
    #[error(
        "scale fit: only {found} valid pixel pairs (finite, reference depth > 0) on the object; need at least {MIN_SAMPLES}"
    )]
    TooFewSamples { found: usize },
    #[error("scale fit: the monocular depth is constant on the object, so no scale is defined")]
    DegenerateMono,
}

/// The valid `(mono, reference)` pairs of two maps under a mask: both finite,
/// reference > 0 (0 marks a missing sensor reading).
pub fn masked_pairs(
    mono: ArrayView2<'_, f32>,
    reference: ArrayView2<'_, f32>,
    mask: ArrayView2<'_, bool>,
) -> (Vec<f64>, Vec<f64>) {
    let mut pairs = (Vec::new(), Vec::new());
    if mono.dim() != reference.dim() || mono.dim() != mask.dim() {
        return pairs;
    }
    for ((&m, &r), &inside) in mono.iter().zip(reference.iter()).zip(mask.iter()) {
        if inside && m.is_finite() && r.is_finite() && r > 0.0 {
            pairs.0.push(f64::from(m));
            pairs.1.push(f64::from(r));
        }
    }
    pairs
}

/// Fits `reference ≈ scale · mono (+ shift)` by minimising the median
/// absolute residual. Non-finite pairs and reference values ≤ 0 are skipped.
pub fn fit_depth_scale(
    mono: &[f64],
    reference: &[f64],
    model: DepthModel,
) -> Result<ScaleFit, ScaleFitError> {
    if mono.len() != reference.len() {
        return Err(ScaleFitError::LengthMismatch {
            mono: mono.len(),
            reference: reference.len(),
        });
    }
    let (mono, reference): (Vec<f64>, Vec<f64>) = mono
        .iter()
        .zip(reference)
        .filter(|(m, r)| m.is_finite() && r.is_finite() && **r > 0.0)
        .map(|(m, r)| (*m, *r))
        .unzip();
    if mono.len() < MIN_SAMPLES {
        return Err(ScaleFitError::TooFewSamples { found: mono.len() });
    }
    let mut scratch = Vec::with_capacity(mono.len());
    // Centre of the scan: the ratio of medians (of spreads, when a shift
    // absorbs the offset), which is right when there are no outliers.
    let centre = match model {
        DepthModel::Scale => median(&mut mono.clone()).abs(),
        DepthModel::ScaleShift => median_abs_deviation(&mono, &mut scratch),
    };
    let reference_level = match model {
        DepthModel::Scale => median(&mut reference.clone()),
        DepthModel::ScaleShift => median_abs_deviation(&reference, &mut scratch),
    };
    if centre <= f64::EPSILON * reference_level.abs().max(1.0) || !centre.is_finite() {
        return Err(ScaleFitError::DegenerateMono);
    }
    let centre = (reference_level / centre).abs().max(f64::MIN_POSITIVE);
    let mut objective =
        |log_scale: f64| evaluate(&mono, &reference, log_scale.exp(), model, &mut scratch).0;

    let (low, high) = (centre.ln() - GRID_SPAN.ln(), centre.ln() + GRID_SPAN.ln());
    let step = (high - low) / (GRID_POINTS - 1) as f64;
    let (mut best_index, mut best_value) = (0, f64::INFINITY);
    for index in 0..GRID_POINTS {
        let value = objective(low + step * index as f64);
        if value < best_value {
            (best_index, best_value) = (index, value);
        }
    }
    let best_log = low + step * best_index as f64;
    let (mut a, mut b) = (best_log - step, best_log + step);
    let inverse_phi = (5f64.sqrt() - 1.0) / 2.0;
    let mut c = b - inverse_phi * (b - a);
    let mut d = a + inverse_phi * (b - a);
    let (mut fc, mut fd) = (objective(c), objective(d));
    for _ in 0..GOLDEN_ITERATIONS {
        if fc <= fd {
            (b, d, fd) = (d, c, fc);
            c = b - inverse_phi * (b - a);
            fc = objective(c);
        } else {
            (a, c, fc) = (c, d, fd);
            d = a + inverse_phi * (b - a);
            fd = objective(d);
        }
    }
    // The golden bracket never leaves the grid's best cell; keep whichever
    // of the grid point and the refined point is better.
    let refined = (a + b) / 2.0;
    let log_scale = if objective(refined) <= best_value {
        refined
    } else {
        best_log
    };
    let scale = log_scale.exp();
    let (median_abs_residual_m, shift_m) = evaluate(&mono, &reference, scale, model, &mut scratch);
    Ok(ScaleFit {
        scale,
        shift_m,
        median_abs_residual_m,
        samples: mono.len(),
    })
}

/// (median |residual|, best shift) at a scale.
fn evaluate(
    mono: &[f64],
    reference: &[f64],
    scale: f64,
    model: DepthModel,
    scratch: &mut Vec<f64>,
) -> (f64, f64) {
    scratch.clear();
    scratch.extend(mono.iter().zip(reference).map(|(m, r)| r - scale * m));
    let shift = match model {
        DepthModel::Scale => 0.0,
        DepthModel::ScaleShift => median(scratch),
    };
    for residual in scratch.iter_mut() {
        *residual = (*residual - shift).abs();
    }
    (median(scratch), shift)
}

/// Median absolute deviation from the median (a robust spread).
fn median_abs_deviation(values: &[f64], scratch: &mut Vec<f64>) -> f64 {
    scratch.clear();
    scratch.extend_from_slice(values);
    let centre = median(scratch);
    for value in scratch.iter_mut() {
        *value = (*value - centre).abs();
    }
    median(scratch)
}

/// The lower median (reorders `values`); NaN-free input.
fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let middle = (values.len() - 1) / 2;
    *values.select_nth_unstable_by(middle, f64::total_cmp).1
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Monocular values on an object 0.5–1.5 (network units), reference =
    /// planted affine map + 2 mm sensor noise, `outlier_fraction` of the
    /// reference replaced by arbitrary depths in 0.1–5 m.
    fn planted(scale: f64, shift: f64, outlier_fraction: f64, seed: u64) -> (Vec<f64>, Vec<f64>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let count = 5000;
        let mono: Vec<f64> = (0..count).map(|_| rng.random_range(0.5..1.5)).collect();
        let reference = mono
            .iter()
            .map(|&m| {
                if rng.random_bool(outlier_fraction) {
                    rng.random_range(0.1..5.0)
                } else {
                    scale * m + shift + rng.random_range(-0.002..0.002)
                }
            })
            .collect();
        (mono, reference)
    }

    #[test]
    fn recovers_planted_scale_within_one_percent_with_twenty_percent_outliers() {
        for (seed, planted_scale) in [(1, 0.73), (2, 1.9), (3, 3.4)] {
            let (mono, reference) = planted(planted_scale, 0.0, 0.2, seed);
            let fit = fit_depth_scale(&mono, &reference, DepthModel::Scale).expect("fit");
            let error = (fit.scale / planted_scale - 1.0).abs();
            assert!(
                error < 0.01,
                "seed {seed}: scale {} vs {planted_scale} ({:.3} %)",
                fit.scale,
                100.0 * error
            );
        }
    }

    #[test]
    fn recovers_planted_scale_and_shift_with_twenty_percent_outliers() {
        let (planted_scale, planted_shift) = (1.6, 0.35);
        let (mono, reference) = planted(planted_scale, planted_shift, 0.2, 11);
        let fit = fit_depth_scale(&mono, &reference, DepthModel::ScaleShift).expect("fit");
        assert!((fit.scale / planted_scale - 1.0).abs() < 0.01, "{fit:?}");
        // Shift within 1 cm: 1 % of the 1–3 m depth range.
        assert!((fit.shift_m - planted_shift).abs() < 0.01, "{fit:?}");
    }

    #[test]
    fn least_squares_would_fail_where_the_median_succeeds() {
        // Guards the test's power: the outliers must move a least-squares fit
        // well beyond the 1 % tolerance, or the test above proves nothing.
        let planted_scale = 0.73;
        let (mono, reference) = planted(planted_scale, 0.0, 0.2, 1);
        let least_squares = mono.iter().zip(&reference).map(|(m, r)| m * r).sum::<f64>()
            / mono.iter().map(|m| m * m).sum::<f64>();
        assert!(
            (least_squares / planted_scale - 1.0).abs() > 0.05,
            "{least_squares}"
        );
    }

    #[test]
    fn rejects_too_few_and_degenerate_samples() {
        assert_eq!(
            fit_depth_scale(&[1.0; 3], &[2.0; 3], DepthModel::Scale),
            Err(ScaleFitError::TooFewSamples { found: 3 })
        );
        assert_eq!(
            fit_depth_scale(&[1.0; 20], &[2.0, 2.5].repeat(10), DepthModel::ScaleShift),
            Err(ScaleFitError::DegenerateMono)
        );
        assert!(matches!(
            fit_depth_scale(&[1.0; 3], &[2.0; 4], DepthModel::Scale),
            Err(ScaleFitError::LengthMismatch { .. })
        ));
    }

    #[test]
    fn masked_pairs_skip_missing_reference_and_outside_pixels() {
        let mono = ndarray::arr2(&[[1.0f32, 2.0], [3.0, f32::NAN]]);
        let reference = ndarray::arr2(&[[2.0f32, 0.0], [6.0, 1.0]]);
        let mask = ndarray::arr2(&[[true, true], [false, true]]);
        let (m, r) = masked_pairs(mono.view(), reference.view(), mask.view());
        assert_eq!((m, r), (vec![1.0], vec![2.0]));
    }
}
