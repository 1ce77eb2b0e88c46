//! The whole differentiable render: project → bin → rasterize, and back.

use dm_mpm::real::Real;
use dm_view::Camera;

use crate::SplatError;
use crate::gaussians::{GaussianGrads, Gaussians};
use crate::project::{CameraParams, Projected, project_gaussians};
use crate::project_backward::project_backward;
use crate::rasterize::{Rasterized, rasterize};
use crate::rasterize_backward::{ProjectedGrads, rasterize_backward};
use crate::tiles::TileBins;

/// gsplat's default near plane (metres): Gaussians closer than this to the
/// camera plane are culled (the projection Jacobian blows up as z → 0).
pub const DEFAULT_NEAR_PLANE: f64 = 0.01;
/// 3DGS's screen-space low-pass, added to the 2D covariance diagonal (px²).
pub const DEFAULT_LOW_PASS: f64 = 0.3;

/// Options of a render.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderSettings {
    /// RGB behind all splats.
    pub background: [f64; 3],
    pub near_plane: f64,
    pub low_pass: f64,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            background: [0.0; 3],
            near_plane: DEFAULT_NEAR_PLANE,
            low_pass: DEFAULT_LOW_PASS,
        }
    }
}

impl RenderSettings {
    fn validate(&self) -> Result<(), SplatError> {
        if !self.background.iter().all(|c| c.is_finite()) {
            return Err(SplatError::InvalidSettings(format!(
                "background must be finite, got {:?}",
                self.background
            )));
        }
        if !(self.near_plane.is_finite() && self.near_plane > 0.0) {
            return Err(SplatError::InvalidSettings(format!(
                "near plane must be finite and positive, got {}",
                self.near_plane
            )));
        }
        if !(self.low_pass.is_finite() && self.low_pass >= 0.0) {
            return Err(SplatError::InvalidSettings(format!(
                "low-pass must be finite and non-negative, got {}",
                self.low_pass
            )));
        }
        Ok(())
    }
}

/// A rendered image plus what [`render_backward`] needs.
#[derive(Debug, Clone)]
pub struct RenderOutput<T: Real> {
    pub raster: Rasterized<T>,
    pub projected: Projected<T>,
    pub bins: TileBins,
}

impl<T: Real> RenderOutput<T> {
    /// Row-major RGB.
    pub fn image(&self) -> &[[T; 3]] {
        &self.raster.image
    }

    /// Per-pixel coverage `1 − T_final` (the rendered silhouette).
    pub fn alpha(&self) -> Vec<T> {
        self.raster
            .final_transmittance
            .iter()
            .map(|t| T::one() - *t)
            .collect()
    }
}

fn check_camera(camera: &Camera) -> Result<(), SplatError> {
    if camera.width == 0 || camera.height == 0 {
        return Err(SplatError::EmptyImage {
            width: camera.width,
            height: camera.height,
        });
    }
    Ok(())
}

/// Renders `gaussians` seen by `camera`.
pub fn render<T: Real>(
    gaussians: &Gaussians<T>,
    camera: &Camera,
    settings: &RenderSettings,
) -> Result<RenderOutput<T>, SplatError> {
    gaussians.validate()?;
    settings.validate()?;
    check_camera(camera)?;
    let cam = CameraParams::<T>::new(camera);
    let projected = project_gaussians(
        gaussians,
        &cam,
        T::lit(settings.near_plane),
        T::lit(settings.low_pass),
    );
    let bins = TileBins::build(&projected, cam.tiles_x(), cam.tiles_y());
    let raster = rasterize(
        &projected,
        &gaussians.colors,
        &bins,
        camera.width,
        camera.height,
        settings.background.map(T::lit),
    );
    Ok(RenderOutput {
        raster,
        projected,
        bins,
    })
}

/// Gradients of a loss with respect to every Gaussian parameter, given
/// `grad_image = ∂L/∂image` for the render `forward` of the same inputs.
pub fn render_backward<T: Real>(
    gaussians: &Gaussians<T>,
    camera: &Camera,
    settings: &RenderSettings,
    forward: &RenderOutput<T>,
    grad_image: &[[T; 3]],
) -> Result<GaussianGrads<T>, SplatError> {
    let projected_grads = render_backward_projected(gaussians, settings, forward, grad_image)?;
    let cam = CameraParams::<T>::new(camera);
    Ok(project_backward(
        gaussians,
        &cam,
        T::lit(settings.near_plane),
        T::lit(settings.low_pass),
        &forward.projected,
        &projected_grads,
    ))
}

/// The rasterizer half of [`render_backward`]: gradients with respect to the
/// projected quantities.
pub fn render_backward_projected<T: Real>(
    gaussians: &Gaussians<T>,
    settings: &RenderSettings,
    forward: &RenderOutput<T>,
    grad_image: &[[T; 3]],
) -> Result<ProjectedGrads<T>, SplatError> {
    let expected = forward.raster.image.len();
    if grad_image.len() != expected {
        return Err(SplatError::GradientSize {
            got: grad_image.len(),
            expected,
        });
    }
    if gaussians.len() != forward.projected.len() {
        return Err(SplatError::LengthMismatch(format!(
            "{} Gaussians, forward pass rendered {}",
            gaussians.len(),
            forward.projected.len()
        )));
    }
    Ok(rasterize_backward(
        &forward.projected,
        &gaussians.colors,
        &forward.bins,
        &forward.raster,
        settings.background.map(T::lit),
        grad_image,
    ))
}
