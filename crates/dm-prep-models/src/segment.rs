//! SAM 2-style segmentation: an image encoder and a prompt decoder
//! (manifest entries `sam2_image_encoder`, `sam2_prompt_decoder`).
//!
//! Frame 0 is segmented from the user's box or point prompt. The clip is
//! propagated by re-prompting each later frame with the previous mask: its
//! bounding box (grown by [`PROPAGATION_MARGIN`]) as the box prompt and its
//! low-resolution logits as `mask_input`. SAM 2's memory-attention video
//! predictor is not an exportable single graph; re-prompting keeps the
//! adapter to the two image-predictor graphs every exporter produces.

use std::path::Path;

use dm_bundle::mask_box;
use image::{GrayImage, Luma, RgbImage};
use ndarray::{Array2, Array3, ArrayD, Axis, IxDyn, s};

use crate::{InputGeometry, Manifest, ModelError, OnnxModel, image_planes, sample_bilinear};

pub const ENCODER_ID: &str = "sam2_image_encoder";
pub const DECODER_ID: &str = "sam2_prompt_decoder";
/// The decoder's low-resolution mask side (a quarter of the 1024 input).
const LOW_RES: usize = 256;
/// Propagation box growth, as a fraction of the previous box's size per side:
/// the object moves between frames.
pub const PROPAGATION_MARGIN: f64 = 0.15;
/// SAM's point labels.
const LABEL_FOREGROUND: f32 = 1.0;
const LABEL_BOX_MIN: f32 = 2.0;
const LABEL_BOX_MAX: f32 = 3.0;
const LABEL_PADDING: f32 = -1.0;

/// A prompt in original-frame pixels.
#[derive(Clone, Debug, PartialEq)]
pub enum Prompt {
    /// Corners (x0, y0), (x1, y1).
    Box { min: [f64; 2], max: [f64; 2] },
    /// Foreground points.
    Points(Vec<[f64; 2]>),
}

/// One frame's result.
#[derive(Clone, Debug)]
pub struct FrameMask {
    /// 255 = object, original resolution.
    pub mask: GrayImage,
    /// The chosen candidate's low-resolution logits (256 × 256).
    pub logits: Array2<f32>,
    /// The decoder's predicted IoU of the chosen candidate.
    pub score: f32,
}

#[derive(Debug)]
pub struct Segmenter {
    encoder: OnnxModel,
    decoder: OnnxModel,
}

impl Segmenter {
    pub fn load(
        manifest: &Manifest,
        models_dir: &Path,
        threads: usize,
    ) -> Result<Self, ModelError> {
        Ok(Self {
            encoder: OnnxModel::load(manifest, ENCODER_ID, models_dir, threads)?,
            decoder: OnnxModel::load(manifest, DECODER_ID, models_dir, threads)?,
        })
    }

    /// Segments one frame; `previous` logits, when given, seed the decoder.
    pub fn segment_frame(
        &mut self,
        image: &RgbImage,
        prompt: &Prompt,
        previous: Option<&Array2<f32>>,
    ) -> Result<FrameMask, ModelError> {
        let (planes, geometry) = image_planes(image, &self.encoder.entry.preprocess);
        let features = self
            .encoder
            .run(vec![("image", planes.insert_axis(Axis(0)).into_dyn())])?;
        let feature = |name: &str| -> Result<ArrayD<f32>, ModelError> {
            let index = self
                .encoder
                .entry
                .outputs
                .iter()
                .position(|spec| spec.name == name)
                .ok_or_else(|| bad(&self.encoder, format!("the encoder has no output `{name}`")))?;
            Ok(features[index].clone())
        };
        let (coords, labels) = prompt_arrays(prompt, &geometry, &self.decoder)?;
        let (mask_input, has_mask) = match previous {
            Some(logits) if logits.dim() == (LOW_RES, LOW_RES) => (logits.clone(), 1.0),
            _ => (Array2::zeros((LOW_RES, LOW_RES)), 0.0),
        };
        let outputs = self.decoder.run(vec![
            ("image_embed", feature("image_embed")?),
            ("high_res_feats_0", feature("high_res_feats_0")?),
            ("high_res_feats_1", feature("high_res_feats_1")?),
            ("point_coords", coords.into_dyn()),
            ("point_labels", labels.into_dyn()),
            (
                "mask_input",
                mask_input
                    .into_shape_with_order((1, 1, LOW_RES, LOW_RES))
                    .map_err(|e| bad(&self.decoder, e.to_string()))?
                    .into_dyn(),
            ),
            ("has_mask_input", ArrayD::from_elem(IxDyn(&[1]), has_mask)),
        ])?;
        let masks = outputs[0]
            .view()
            .into_dimensionality::<ndarray::Ix4>()
            .map_err(|e| bad(&self.decoder, format!("output `masks`: {e}")))?;
        let scores = outputs[1]
            .view()
            .into_dimensionality::<ndarray::Ix2>()
            .map_err(|e| bad(&self.decoder, format!("output `iou_predictions`: {e}")))?;
        let candidates = masks.dim().1;
        if candidates == 0
            || scores.dim().1 != candidates
            || masks.dim().2 != LOW_RES
            || masks.dim().3 != LOW_RES
        {
            return Err(bad(
                &self.decoder,
                format!(
                    "masks {:?} and iou_predictions {:?} do not agree",
                    masks.dim(),
                    scores.dim()
                ),
            ));
        }
        // Highest predicted IoU; ties keep the first candidate.
        let best = (0..candidates).fold(0, |best, k| {
            if scores[[0, k]] > scores[[0, best]] {
                k
            } else {
                best
            }
        });
        let logits = masks.slice(s![0, best, .., ..]).to_owned();
        Ok(FrameMask {
            mask: upsample_mask(&logits, &geometry),
            logits,
            score: scores[[0, best]],
        })
    }

    /// Segments a clip: `prompt` on frame 0, then each frame re-prompted from
    /// the previous mask (module docs). An empty previous mask falls back to
    /// the original prompt.
    pub fn segment_clip(
        &mut self,
        frames: &[RgbImage],
        prompt: &Prompt,
    ) -> Result<Vec<GrayImage>, ModelError> {
        let mut masks = Vec::with_capacity(frames.len());
        let mut previous: Option<FrameMask> = None;
        for frame in frames {
            let (frame_prompt, seed) = match previous
                .as_ref()
                .and_then(|p| mask_box(&p.mask).map(|b| (b, p)))
            {
                Some((bounds, p)) => (grow_box(bounds, frame.dimensions()), Some(&p.logits)),
                None => (prompt.clone(), None),
            };
            let result = self.segment_frame(frame, &frame_prompt, seed)?;
            masks.push(result.mask.clone());
            previous = Some(result);
        }
        Ok(masks)
    }
}

fn bad(model: &OnnxModel, problem: String) -> ModelError {
    ModelError::BadInput {
        model: format!("{} ({})", model.entry.model, model.path.display()),
        problem,
    }
}

/// SAM's (1, P, 2) coordinates in the input frame and (1, P) labels.
fn prompt_arrays(
    prompt: &Prompt,
    geometry: &InputGeometry,
    decoder: &OnnxModel,
) -> Result<(Array3<f32>, Array2<f32>), ModelError> {
    let mut points: Vec<([f64; 2], f32)> = match prompt {
        Prompt::Box { min, max } => {
            if !(min[0] < max[0] && min[1] < max[1]) {
                return Err(bad(decoder, format!("box prompt {min:?}–{max:?} is empty")));
            }
            vec![(*min, LABEL_BOX_MIN), (*max, LABEL_BOX_MAX)]
        }
        Prompt::Points(points) if points.is_empty() => {
            return Err(bad(decoder, "point prompt has no points".into()));
        }
        Prompt::Points(points) => points.iter().map(|&p| (p, LABEL_FOREGROUND)).collect(),
    };
    if points
        .iter()
        .any(|(p, _)| !p[0].is_finite() || !p[1].is_finite())
    {
        return Err(bad(decoder, "prompt coordinates must be finite".into()));
    }
    if matches!(prompt, Prompt::Points(_)) {
        // SAM's decoder expects a padding point when no box is given.
        points.push(([0.0, 0.0], LABEL_PADDING));
    }
    let count = points.len();
    let mut coords = Array3::zeros((1, count, 2));
    let mut labels = Array2::zeros((1, count));
    for (k, (point, label)) in points.iter().enumerate() {
        let scaled = if *label == LABEL_PADDING {
            *point
        } else {
            geometry.to_input(*point)
        };
        coords[[0, k, 0]] = scaled[0] as f32;
        coords[[0, k, 1]] = scaled[1] as f32;
        labels[[0, k]] = *label;
    }
    Ok((coords, labels))
}

/// Low-resolution logits (input frame / 4) → original-resolution mask.
fn upsample_mask(logits: &Array2<f32>, geometry: &InputGeometry) -> GrayImage {
    let per_low_res = f64::from(geometry.input.0) / LOW_RES as f64;
    GrayImage::from_fn(geometry.original.0, geometry.original.1, |x, y| {
        let input = geometry.to_input([f64::from(x) + 0.5, f64::from(y) + 0.5]);
        let logit = sample_bilinear(
            logits.view(),
            input[0] / per_low_res,
            input[1] / per_low_res,
        );
        Luma([if logit > 0.0 { 255 } else { 0 }])
    })
}

fn grow_box((min, max): ([f64; 2], [f64; 2]), (width, height): (u32, u32)) -> Prompt {
    let margin = [
        (max[0] - min[0]) * PROPAGATION_MARGIN,
        (max[1] - min[1]) * PROPAGATION_MARGIN,
    ];
    Prompt::Box {
        min: [(min[0] - margin[0]).max(0.0), (min[1] - margin[1]).max(0.0)],
        max: [
            (max[0] + margin[0]).min(f64::from(width)),
            (max[1] + margin[1]).min(f64::from(height)),
        ],
    }
}
