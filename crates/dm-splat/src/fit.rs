//! Fitting Gaussians to posed images (the first-frame appearance fit of
//! method.md §6): 3DGS's loss `(1 − λ) L1 + λ (1 − SSIM)` with λ = 0.2,
//! minimised by Adam over means, log-scales, rotations, opacity logits and
//! colours.
//!
//! Masking (method.md §6): each view's target already has its background
//! pixels set to the renderer background; pixels of weight 0 (the hand)
//! are excluded by replacing the render there with the background too
//! before both terms, so they contribute neither loss nor gradient.
//!
//! Every step uses every view (full batch, views in order), so a fit is a
//! pure function of its inputs: no random view sampling to seed, and the
//! rasterizer's sums have a fixed order, so results do not depend on the
//! thread count. No densification or pruning: the Gaussian count stays the
//! one of the initialisation, which keeps the LBS binding to the particles
//! one to one with what was initialised.

use dm_view::Camera;
use nalgebra::Vector3;

use crate::SplatError;
use crate::gaussians::{GaussianGrads, Gaussians, normalize_quat};
use crate::render::{RenderSettings, render, render_backward};
use crate::ssim::ssim_rgb;

/// 3DGS's weight of the D-SSIM term.
pub const DEFAULT_LAMBDA_DSSIM: f64 = 0.2;
/// Adam moments as in 3DGS (β₁, β₂).
const ADAM_BETA1: f64 = 0.9;
const ADAM_BETA2: f64 = 0.999;

/// One posed image to fit.
#[derive(Debug, Clone)]
pub struct FitView {
    pub name: String,
    pub camera: Camera,
    /// Row-major RGB in `[0, 1]`, background pixels already set to the
    /// renderer background.
    pub target: Vec<[f32; 3]>,
    /// Per pixel: 1 supervised, 0 excluded (hand pixels).
    pub weight: Vec<f32>,
}

impl FitView {
    fn check(&self) -> Result<(), SplatError> {
        let n = self.camera.width as usize * self.camera.height as usize;
        if self.target.len() != n || self.weight.len() != n {
            return Err(SplatError::InvalidSettings(format!(
                "fit view {}: target has {} pixels and weight {}, the camera {}",
                self.name,
                self.target.len(),
                self.weight.len(),
                n
            )));
        }
        Ok(())
    }
}

/// Adam step sizes per parameter group. Means decay exponentially from
/// `means` to `means_final` over the fit (3DGS's schedule); the others
/// are constant.
#[derive(Debug, Clone, PartialEq)]
pub struct LearningRates {
    /// Metres per step at the start.
    pub means: f64,
    pub means_final: f64,
    pub log_scales: f64,
    pub rotations: f64,
    pub opacity_logits: f64,
    pub colors: f64,
    /// Adam's ε. 3DGS uses 1e-15, which makes every Gaussian with any
    /// gradient at all step by the full rate — including ones hidden
    /// behind the surface, whose gradients are scaled by a transmittance
    /// of 1e-3 or less: with few views they then drift to colours no
    /// camera checks, which a held-out camera sees. ε sits between the
    /// gradients of visible Gaussians and those of hidden ones (see
    /// [`LearningRates::for_spacing`]).
    pub adam_epsilon: f64,
}

impl LearningRates {
    /// Rates for a scene whose Gaussians are about `spacing` metres apart,
    /// for fits of a few dozen to a few hundred full-batch steps from a
    /// good initialisation (Gaussians on the particles, colours from the
    /// images). Means start at 2 % of the spacing per step and decay to
    /// 0.02 % (3DGS: 1.6e-4 → 1.6e-6 of the scene extent over 30 000
    /// steps); faster means fitted the training views better and the
    /// held-out one worse (toy: 0.1 × spacing cost 0.5–1 dB held out).
    /// Colours move faster than 3DGS's SH rate (2.5e-3 of an SH unit ≈
    /// 7e-4 RGB) since the fit is short. ε = 1e-7: image gradients of
    /// visible Gaussians are ~1e-6–1e-5 (mean over ~1e5 pixel channels),
    /// those of Gaussians behind the surface 1e-3 of that or less.
    pub fn for_spacing(spacing: f64) -> Self {
        Self {
            means: 0.02 * spacing,
            means_final: 0.0002 * spacing,
            log_scales: 0.01,
            rotations: 0.005,
            opacity_logits: 0.05,
            colors: 0.01,
            adam_epsilon: 1e-7,
        }
    }
}

/// Options of a fit.
#[derive(Debug, Clone, PartialEq)]
pub struct FitSettings {
    pub iterations: usize,
    pub lambda_dssim: f64,
    pub learning_rates: LearningRates,
    pub render: RenderSettings,
}

/// The loss after one step's forward pass (before its update).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitStep {
    pub iteration: usize,
    /// Mean over views of `(1 − λ) L1 + λ (1 − SSIM)`.
    pub loss: f64,
    pub l1: f64,
    pub dssim: f64,
}

/// Loss of one view and its gradient with respect to the rendered image.
#[derive(Debug, Clone)]
pub struct ViewLoss {
    pub loss: f64,
    pub l1: f64,
    pub dssim: f64,
    pub grad_image: Vec<[f64; 3]>,
}

/// `(1 − λ) mean|r' − t| + λ (1 − SSIM(r', t))` with `r' = w r + (1 − w) b`
/// (the render with excluded pixels replaced by the background `b`), and
/// its gradient with respect to `r`. `l1` and the SSIM are means over all
/// pixels and channels, as in 3DGS.
pub fn view_loss(
    rendered: &[[f64; 3]],
    view: &FitView,
    background: [f64; 3],
    lambda_dssim: f64,
) -> ViewLoss {
    let width = view.camera.width as usize;
    let height = view.camera.height as usize;
    let n = rendered.len();
    let masked: Vec<[f64; 3]> = rendered
        .iter()
        .zip(&view.weight)
        .map(|(r, &w)| {
            let w = f64::from(w);
            [0, 1, 2].map(|c| w * r[c] + (1.0 - w) * background[c])
        })
        .collect();
    let target: Vec<[f64; 3]> = view.target.iter().map(|t| t.map(f64::from)).collect();
    let l1_scale = 1.0 / (3 * n).max(1) as f64;
    let mut l1 = 0.0;
    let mut grad_masked = vec![[0.0; 3]; n];
    for p in 0..n {
        for c in 0..3 {
            let d = masked[p][c] - target[p][c];
            l1 += d.abs();
            grad_masked[p][c] = (1.0 - lambda_dssim) * l1_scale * d.signum();
        }
    }
    l1 *= l1_scale;
    let (ssim, grad_ssim) = ssim_rgb(&masked, &target, width, height, lambda_dssim != 0.0);
    if let Some(grad_ssim) = grad_ssim {
        for (g, s) in grad_masked.iter_mut().zip(grad_ssim) {
            for c in 0..3 {
                g[c] -= lambda_dssim * s[c];
            }
        }
    }
    let grad_image = grad_masked
        .iter()
        .zip(&view.weight)
        .map(|(g, &w)| g.map(|v| v * f64::from(w)))
        .collect();
    let dssim = 1.0 - ssim;
    ViewLoss {
        loss: (1.0 - lambda_dssim) * l1 + lambda_dssim * dssim,
        l1,
        dssim,
        grad_image,
    }
}

/// Adam moments of one parameter group.
#[derive(Debug, Clone)]
struct AdamGroup {
    m: Vec<f64>,
    v: Vec<f64>,
}

impl AdamGroup {
    fn new(n: usize) -> Self {
        Self {
            m: vec![0.0; n],
            v: vec![0.0; n],
        }
    }

    /// One bias-corrected Adam update of `param` (entry `k` of the group).
    #[inline]
    fn update(&mut self, k: usize, param: &mut f32, grad: f64, lr: f64, eps: f64, step: i32) {
        if !grad.is_finite() {
            return;
        }
        self.m[k] = ADAM_BETA1 * self.m[k] + (1.0 - ADAM_BETA1) * grad;
        self.v[k] = ADAM_BETA2 * self.v[k] + (1.0 - ADAM_BETA2) * grad * grad;
        let m_hat = self.m[k] / (1.0 - ADAM_BETA1.powi(step));
        let v_hat = self.v[k] / (1.0 - ADAM_BETA2.powi(step));
        *param -= (lr * m_hat / (v_hat.sqrt() + eps)) as f32;
    }

    fn update_vec3(
        &mut self,
        params: &mut [Vector3<f32>],
        grads: &[Vector3<f32>],
        lr: f64,
        eps: f64,
        step: i32,
    ) {
        for (i, (p, g)) in params.iter_mut().zip(grads).enumerate() {
            for c in 0..3 {
                self.update(3 * i + c, &mut p[c], f64::from(g[c]), lr, eps, step);
            }
        }
    }
}

/// Adds `other` into `sum`.
fn accumulate(sum: &mut GaussianGrads<f32>, other: &GaussianGrads<f32>) {
    let add3 = |a: &mut [Vector3<f32>], b: &[Vector3<f32>]| {
        for (x, y) in a.iter_mut().zip(b) {
            *x += y;
        }
    };
    add3(&mut sum.means, &other.means);
    add3(&mut sum.log_scales, &other.log_scales);
    add3(&mut sum.colors, &other.colors);
    for (x, y) in sum.rotations.iter_mut().zip(&other.rotations) {
        for c in 0..4 {
            x[c] += y[c];
        }
    }
    for (x, y) in sum.opacity_logits.iter_mut().zip(&other.opacity_logits) {
        *x += y;
    }
}

/// The mean loss over `views` and its gradient with respect to every
/// Gaussian parameter.
pub fn loss_and_gradients(
    gaussians: &Gaussians<f32>,
    views: &[FitView],
    lambda_dssim: f64,
    settings: &RenderSettings,
) -> Result<(FitStep, GaussianGrads<f32>), SplatError> {
    let mut total = GaussianGrads::zeros(gaussians.len());
    let mut step = FitStep {
        iteration: 0,
        loss: 0.0,
        l1: 0.0,
        dssim: 0.0,
    };
    let per_view = 1.0 / views.len().max(1) as f64;
    for view in views {
        let forward = render(gaussians, &view.camera, settings)?;
        let rendered: Vec<[f64; 3]> = forward.image().iter().map(|p| p.map(f64::from)).collect();
        let loss = view_loss(&rendered, view, settings.background, lambda_dssim);
        step.loss += per_view * loss.loss;
        step.l1 += per_view * loss.l1;
        step.dssim += per_view * loss.dssim;
        let grad_image: Vec<[f32; 3]> = loss
            .grad_image
            .iter()
            .map(|g| g.map(|v| (v * per_view) as f32))
            .collect();
        let grads = render_backward(gaussians, &view.camera, settings, &forward, &grad_image)?;
        accumulate(&mut total, &grads);
    }
    Ok((step, total))
}

/// Fits `gaussians` to `views` in place; returns the loss of every step.
/// `on_step` is called after each step (progress).
pub fn fit_gaussians(
    gaussians: &mut Gaussians<f32>,
    views: &[FitView],
    settings: &FitSettings,
    on_step: &mut dyn FnMut(&FitStep),
) -> Result<Vec<FitStep>, SplatError> {
    if views.is_empty() {
        return Err(SplatError::InvalidSettings("no views to fit".into()));
    }
    if !(0.0..=1.0).contains(&settings.lambda_dssim) {
        return Err(SplatError::InvalidSettings(format!(
            "lambda_dssim must be in [0, 1], got {}",
            settings.lambda_dssim
        )));
    }
    for view in views {
        view.check()?;
    }
    gaussians.validate()?;
    let n = gaussians.len();
    let mut adam_means = AdamGroup::new(3 * n);
    let mut adam_scales = AdamGroup::new(3 * n);
    let mut adam_rotations = AdamGroup::new(4 * n);
    let mut adam_opacity = AdamGroup::new(n);
    let mut adam_colors = AdamGroup::new(3 * n);
    let lr = &settings.learning_rates;
    let mut history = Vec::with_capacity(settings.iterations);
    for iteration in 0..settings.iterations {
        let (mut step, grads) =
            loss_and_gradients(gaussians, views, settings.lambda_dssim, &settings.render)?;
        step.iteration = iteration;
        let t = i32::try_from(iteration + 1).unwrap_or(i32::MAX);
        // Log-linear decay of the mean step (3DGS's expon_lr_func).
        let progress = iteration as f64 / settings.iterations.max(2).saturating_sub(1) as f64;
        let lr_means = (lr.means.ln() * (1.0 - progress) + lr.means_final.ln() * progress).exp();
        let eps = lr.adam_epsilon;
        adam_means.update_vec3(&mut gaussians.means, &grads.means, lr_means, eps, t);
        adam_scales.update_vec3(
            &mut gaussians.log_scales,
            &grads.log_scales,
            lr.log_scales,
            eps,
            t,
        );
        adam_colors.update_vec3(&mut gaussians.colors, &grads.colors, lr.colors, eps, t);
        // Display colours: the targets are in [0, 1], so nothing outside helps.
        for c in &mut gaussians.colors {
            *c = c.map(|v| v.clamp(0.0, 1.0));
        }
        for (i, (q, g)) in gaussians
            .rotations
            .iter_mut()
            .zip(&grads.rotations)
            .enumerate()
        {
            for c in 0..4 {
                adam_rotations.update(4 * i + c, &mut q[c], f64::from(g[c]), lr.rotations, eps, t);
            }
        }
        for (i, (o, g)) in gaussians
            .opacity_logits
            .iter_mut()
            .zip(&grads.opacity_logits)
            .enumerate()
        {
            adam_opacity.update(i, o, f64::from(*g), lr.opacity_logits, eps, t);
        }
        // Keep quaternions unit: the LBS bridge composes rotations with them.
        for q in &mut gaussians.rotations {
            let (unit, norm) = normalize_quat(q);
            if norm > 1e-6 {
                *q = unit;
            }
        }
        on_step(&step);
        history.push(step);
    }
    Ok(history)
}
