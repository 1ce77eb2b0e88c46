//! Stage 3 of the fit (method.md §6–7): RGB-guided refinement. The
//! Gaussians fitted at frame 0 are frozen and skinned to the particles of
//! each simulated frame (LBS); the masked L1 between their render and the
//! observed image of every training camera joins L_dyn with weight
//! `1e-2`, and its gradient flows through the skinning
//! (`dm_splat::lbs_backward`) into the particle positions, and from there
//! through the simulator's adjoint into the material fields and the
//! residual.
//!
//! Targets as in the appearance fit (`dm_appearance::fit::frame_view`):
//! object pixels as observed, every other pixel the renderer background,
//! hand pixels excluded from the loss.

use dm_appearance::SplatFollower;
use dm_appearance::fit::frame_view;
use dm_bundle::Bundle;
use dm_splat::fit::{FitView, view_loss};
use dm_splat::lbs_backward::skin_means_vjp;
use dm_splat::{Gaussians, RenderSettings, render, render_backward};
use nalgebra::Vector3;
use rayon::prelude::*;

use crate::material_fit::{FitError, FrameTerm, TermValue};

/// Weight of L_rgb in stage 3 (method.md §6).
pub const DEFAULT_RGB_WEIGHT: f64 = 1e-2;

/// The photometric term of one stage-3 iteration: call [`FrameTerm::frames`]
/// for frames 1, 2, … in order (the skinning is incremental).
#[derive(Debug)]
pub struct RgbTerm<'a> {
    bundle: &'a Bundle,
    follower: SplatFollower,
    cameras: &'a [usize],
    settings: RenderSettings,
    /// Weight divided by the number of frames and cameras the term averages.
    scale: f64,
    /// Mean masked L1 over the frames and cameras seen so far (unweighted).
    l1_sum: f64,
    terms: usize,
}

impl<'a> RgbTerm<'a> {
    /// The term for a rollout of `steps` frames after frame 0, on the
    /// training `cameras` of the appearance fit; `particles` are the model's
    /// frame-0 particles the Gaussians are bound to.
    pub fn new(
        bundle: &'a Bundle,
        gaussians: Gaussians<f32>,
        particles: &[[f64; 3]],
        cameras: &'a [usize],
        weight: f64,
        steps: usize,
    ) -> Result<Self, FitError> {
        if cameras.is_empty() {
            return Err(FitError::InvalidOption {
                option: "--rgb-iters".into(),
                problem: "the appearance record has no training camera".into(),
            });
        }
        Ok(Self {
            bundle,
            follower: SplatFollower::new(gaussians, particles).map_err(appearance_error)?,
            cameras,
            settings: RenderSettings::default(),
            scale: weight / (steps.max(1) * cameras.len()) as f64,
            l1_sum: 0.0,
            terms: 0,
        })
    }

    /// Mean masked L1 (per pixel and channel) over the views seen so far.
    pub fn mean_l1(&self) -> f64 {
        self.l1_sum / self.terms.max(1) as f64
    }

    fn view(&self, camera: usize, frame: usize) -> Result<FitView, FitError> {
        Ok(frame_view(
            self.bundle,
            camera,
            frame,
            self.settings.background,
        )?)
    }
}

fn appearance_error(e: dm_splat::SplatError) -> FitError {
    FitError::Appearance(e.into())
}

impl RgbTerm<'_> {
    /// Masked L1 of `gaussians` (skinned to `frame`) seen by `camera`, and
    /// its gradient with respect to the Gaussians' means (scaled).
    fn view_term(
        &self,
        gaussians: &Gaussians<f32>,
        camera: usize,
        frame: usize,
    ) -> Result<(f64, Vec<Vector3<f64>>), FitError> {
        let view = self.view(camera, frame)?;
        let forward = render(gaussians, &view.camera, &self.settings).map_err(appearance_error)?;
        let rendered: Vec<[f64; 3]> = forward.image().iter().map(|p| p.map(f64::from)).collect();
        let loss = view_loss(&rendered, &view, self.settings.background, 0.0);
        let grad_image: Vec<[f32; 3]> = loss
            .grad_image
            .iter()
            .map(|g| g.map(|v| (v * self.scale) as f32))
            .collect();
        let grads = render_backward(
            gaussians,
            &view.camera,
            &self.settings,
            &forward,
            &grad_image,
        )
        .map_err(appearance_error)?;
        Ok((
            loss.l1,
            grads.means.iter().map(|g| g.map(f64::from)).collect(),
        ))
    }
}

impl FrameTerm for RgbTerm<'_> {
    /// The skinning advances frame by frame; the (frame, camera) views of
    /// [`FRAMES_AT_ONCE`] frames at a time are rendered and differentiated
    /// in parallel, and the sums are taken in frame and camera order as one
    /// frame at a time would (the result does not depend on the grouping).
    fn frames(
        &mut self,
        first: usize,
        positions: &[Vec<[f64; 3]>],
    ) -> Result<Vec<TermValue>, FitError> {
        let mut out = Vec::with_capacity(positions.len());
        for (group, group_positions) in positions.chunks(FRAMES_AT_ONCE).enumerate() {
            let group_first = first + group * FRAMES_AT_ONCE;
            out.extend(self.frame_group(group_first, group_positions)?);
        }
        Ok(out)
    }
}

/// Frames whose skinned Gaussians are held at once by
/// [`RgbTerm::frames`]: 48 views in parallel with 3 cameras, enough for
/// 16 cores, while the copies stay bounded for large splat sets.
const FRAMES_AT_ONCE: usize = 16;

impl RgbTerm<'_> {
    /// [`FrameTerm::frames`] for one group of frames.
    fn frame_group(
        &mut self,
        first: usize,
        positions: &[Vec<[f64; 3]>],
    ) -> Result<Vec<TermValue>, FitError> {
        let mut skinned = Vec::with_capacity(positions.len());
        for frame_positions in positions {
            let binding = self
                .follower
                .advance_f64(frame_positions)
                .map_err(appearance_error)?;
            skinned.push((binding, self.follower.gaussians().clone()));
        }
        let this = &*self;
        let views: Vec<(f64, Vec<Vector3<f64>>)> = (0..positions.len())
            .flat_map(|i| this.cameras.iter().map(move |&camera| (i, camera)))
            .collect::<Vec<_>>()
            .into_par_iter()
            .map(|(i, camera)| this.view_term(&skinned[i].1, camera, first + i))
            .collect::<Vec<_>>()
            .into_iter()
            // The first failing view's error, whatever the thread count.
            .collect::<Result<_, FitError>>()?;
        let mut views = views.into_iter();
        let mut out = Vec::with_capacity(positions.len());
        for ((binding, gaussians), frame_positions) in skinned.iter().zip(positions) {
            let mut value = 0.0;
            let mut grad_means = vec![Vector3::<f64>::zeros(); gaussians.len()];
            for (l1, grads) in views.by_ref().take(self.cameras.len()) {
                self.l1_sum += l1;
                self.terms += 1;
                value += self.scale * l1;
                for (sum, g) in grad_means.iter_mut().zip(&grads) {
                    *sum += g;
                }
            }
            out.push((
                value,
                skin_means_vjp(binding, &grad_means, frame_positions.len()),
            ));
        }
        Ok(out)
    }
}
