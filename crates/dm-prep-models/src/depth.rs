//! Monocular depth (manifest entries `depth_anything3`, `moge2`): one frame →
//! a depth map at the frame's resolution in the network's units, made
//! metric with [`crate::scale`].

use std::path::Path;

use image::RgbImage;
use ndarray::{Array2, ArrayView2, Axis, s};

use crate::scale::{DepthModel, ScaleFit, ScaleFitError, fit_depth_scale, masked_pairs};
use crate::{Manifest, ModelError, OnnxModel, image_planes, sample_bilinear};

pub const DEPTH_ANYTHING_ID: &str = "depth_anything3";
pub const MOGE_ID: &str = "moge2";
/// MoGe's validity output counts a pixel as valid above this.
const MOGE_MASK_THRESHOLD: f32 = 0.5;

/// How an entry's outputs hold depth.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum DepthOutput {
    /// `depth` (1, H, W).
    Map,
    /// `points` (1, H, W, 3) with z as depth, `mask` (1, H, W) validity.
    PointsAndMask,
}

#[derive(Debug)]
pub struct DepthEstimator {
    model: OnnxModel,
    output: DepthOutput,
}

impl DepthEstimator {
    /// Loads `id` (a depth entry: [`DEPTH_ANYTHING_ID`] or [`MOGE_ID`]).
    pub fn load(
        manifest: &Manifest,
        id: &str,
        models_dir: &Path,
        threads: usize,
    ) -> Result<Self, ModelError> {
        let model = OnnxModel::load(manifest, id, models_dir, threads)?;
        let names: Vec<&str> = model
            .entry
            .outputs
            .iter()
            .map(|spec| spec.name.as_str())
            .collect();
        let output = match names.as_slice() {
            ["depth"] => DepthOutput::Map,
            ["points", "mask"] => DepthOutput::PointsAndMask,
            _ => {
                return Err(ModelError::BadManifest {
                    path: manifest.entry_path(id),
                    field: "outputs".into(),
                    problem: format!(
                        "{names:?}: a depth entry has outputs [depth] or [points, mask]"
                    ),
                });
            }
        };
        Ok(Self { model, output })
    }

    /// Depth in network units at the frame's resolution; NaN where invalid.
    pub fn estimate(&mut self, image: &RgbImage) -> Result<Array2<f32>, ModelError> {
        let (planes, geometry) = image_planes(image, &self.model.entry.preprocess);
        let outputs = self
            .model
            .run(vec![("image", planes.insert_axis(Axis(0)).into_dyn())])?;
        let bad = |problem: String| ModelError::BadInput {
            model: format!("{} ({})", self.model.entry.model, self.model.path.display()),
            problem,
        };
        let network_map: Array2<f32> = match self.output {
            DepthOutput::Map => outputs[0]
                .view()
                .into_dimensionality::<ndarray::Ix3>()
                .map_err(|e| bad(format!("output `depth`: {e}")))?
                .index_axis(Axis(0), 0)
                .to_owned(),
            DepthOutput::PointsAndMask => {
                let points = outputs[0]
                    .view()
                    .into_dimensionality::<ndarray::Ix4>()
                    .map_err(|e| bad(format!("output `points`: {e}")))?;
                let mask = outputs[1]
                    .view()
                    .into_dimensionality::<ndarray::Ix3>()
                    .map_err(|e| bad(format!("output `mask`: {e}")))?;
                if mask.dim().1 != points.dim().1 || mask.dim().2 != points.dim().2 {
                    return Err(bad(format!(
                        "points {:?} and mask {:?} differ",
                        points.dim(),
                        mask.dim()
                    )));
                }
                let mut z = points.slice(s![0, .., .., 2]).to_owned();
                z.zip_mut_with(&mask.index_axis(Axis(0), 0), |depth, &valid| {
                    if valid <= MOGE_MASK_THRESHOLD {
                        *depth = f32::NAN;
                    }
                });
                z
            }
        };
        let (h, w) = network_map.dim();
        if (w as u32, h as u32) != geometry.input {
            return Err(bad(format!(
                "depth map is {w}×{h}, the input was {:?}",
                geometry.input
            )));
        }
        let (width, height) = geometry.original;
        Ok(Array2::from_shape_fn(
            (height as usize, width as usize),
            |(y, x)| {
                let input = geometry.to_input([x as f64 + 0.5, y as f64 + 0.5]);
                sample_bilinear(network_map.view(), input[0], input[1])
            },
        ))
    }
}

/// Fits the metric scale (and shift) of `mono` against `reference` depth
/// (metres, 0 = missing) on the `mask`ed object (crate::scale).
pub fn fit_metric_scale(
    mono: ArrayView2<'_, f32>,
    reference: ArrayView2<'_, f32>,
    mask: ArrayView2<'_, bool>,
    model: DepthModel,
) -> Result<ScaleFit, ScaleFitError> {
    let (m, r) = masked_pairs(mono, reference, mask);
    fit_depth_scale(&m, &r, model)
}

/// `mono` made metric by a fit (applied to every frame of a clip).
pub fn apply_scale(mono: ArrayView2<'_, f32>, fit: &ScaleFit) -> Array2<f32> {
    mono.mapv(|value| fit.apply(f64::from(value)) as f32)
}
