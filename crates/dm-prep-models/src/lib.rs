//! ONNX model adapters (method.md §8): segmentation (SAM 2-style encoder +
//! prompt decoder), point tracking (CoTracker3-style) and monocular depth
//! (Depth Anything 3, MoGe-2), run through ONNX Runtime (`dm-ort`).
//!
//! Every model is described by an entry of `models_manifest/`
//! ([`manifest`]); [`OnnxModel::load`] refuses a file whose inputs/outputs do
//! not match its entry, and a missing file gives a message naming the model,
//! its manifest entry, where to put the file and how to obtain it.
//!
//! [`scale`] makes monocular depth metric (median absolute residual against
//! reference depth).

pub mod depth;
pub mod manifest;
pub mod scale;
pub mod segment;
pub mod track;

use std::path::{Path, PathBuf};

use ort::session::Session;
use ort::value::{TensorElementType, ValueType};

pub use manifest::{Manifest, ModelEntry, TensorSpec, default_models_dir, sha256_file};

use manifest::Dim;

#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error(
        "{model}: model file {} not found (manifest entry `{id}`, {}). Put the file at that path (or pass another models directory). How to obtain it: {obtain}",
        expected.display(), manifest_file.display()
    )]
    Missing {
        model: String,
        id: String,
        manifest_file: PathBuf,
        expected: PathBuf,
        obtain: String,
    },
    #[error(
        "{}: does not match manifest entry `{id}` ({model}, {}): {}",
        path.display(), manifest_file.display(), problems.join("; ")
    )]
    Signature {
        path: PathBuf,
        model: String,
        id: String,
        manifest_file: PathBuf,
        problems: Vec<String>,
    },
    #[error("{}: sha256 {found} differs from manifest entry `{id}` ({}): {expected}", path.display(), manifest_file.display())]
    Checksum {
        path: PathBuf,
        id: String,
        manifest_file: PathBuf,
        expected: String,
        found: String,
    },
    #[error("{}: manifest field `{field}`: {problem}", path.display())]
    BadManifest {
        path: PathBuf,
        field: String,
        problem: String,
    },
    #[error("manifest {}: no entry `{id}`", manifest.display())]
    UnknownEntry { id: String, manifest: PathBuf },
    #[error("{}: {message}", path.display())]
    Io { path: PathBuf, message: String },
    #[error(transparent)]
    Runtime(#[from] dm_ort::RuntimeError),
    #[error("{}: {message}", path.display())]
    Session { path: PathBuf, message: String },
    #[error("{model}: {problem}")]
    BadInput { model: String, problem: String },
}

/// A loaded ONNX model whose signature matched its manifest entry.
#[derive(Debug)]
pub struct OnnxModel {
    pub entry: ModelEntry,
    pub path: PathBuf,
    session: Session,
}

impl OnnxModel {
    /// Loads entry `id`'s file from `models_dir` with `threads` intra-op
    /// threads (ONNX Runtime's own; 1 keeps results independent of the machine).
    pub fn load(
        manifest: &Manifest,
        id: &str,
        models_dir: &Path,
        threads: usize,
    ) -> Result<Self, ModelError> {
        let entry = manifest.entry(id)?.clone();
        let path = models_dir.join(&entry.file);
        if !path.is_file() {
            return Err(ModelError::Missing {
                model: entry.model.clone(),
                id: entry.id.clone(),
                manifest_file: manifest.entry_path(id),
                expected: path,
                obtain: entry.obtain.clone(),
            });
        }
        let environment = dm_ort::default_environment()?;
        let session_error = |message: String| ModelError::Session {
            path: path.clone(),
            message,
        };
        let session = Session::builder(&environment)
            .map_err(|e| session_error(e.to_string()))?
            .with_intra_threads(threads.max(1))
            .map_err(|e| session_error(e.to_string()))?
            .commit_from_file(&path)
            .map_err(|e| session_error(format!("loading the model: {e}")))?;
        let problems = signature_problems(&entry, &session);
        if !problems.is_empty() {
            return Err(ModelError::Signature {
                path,
                model: entry.model.clone(),
                id: entry.id.clone(),
                manifest_file: manifest.entry_path(id),
                problems,
            });
        }
        Ok(Self {
            entry,
            path,
            session,
        })
    }

    /// Runs the model on named inputs; returns the named outputs as f32 arrays
    /// in the manifest's output order.
    pub fn run(
        &mut self,
        inputs: Vec<(&str, ndarray::ArrayD<f32>)>,
    ) -> Result<Vec<ndarray::ArrayD<f32>>, ModelError> {
        let path = self.path.clone();
        let session_error = |message: String| ModelError::Session {
            path: path.clone(),
            message,
        };
        let mut values = Vec::with_capacity(inputs.len());
        for (name, array) in inputs {
            let tensor = ort::value::Tensor::from_array(array)
                .map_err(|e| session_error(format!("input `{name}`: {e}")))?;
            values.push((name.to_string(), tensor.into_dyn()));
        }
        let outputs = self
            .session
            .run(values)
            .map_err(|e| session_error(format!("running the model: {e}")))?;
        self.entry
            .outputs
            .iter()
            .map(|spec| {
                let value = outputs
                    .get(spec.name.as_str())
                    .ok_or_else(|| session_error(format!("no output `{}`", spec.name)))?;
                value
                    .try_extract_array::<f32>()
                    .map(|view| view.to_owned())
                    .map_err(|e| session_error(format!("output `{}`: {e}", spec.name)))
            })
            .collect()
    }
}

fn dtype_name(ty: TensorElementType) -> &'static str {
    match ty {
        TensorElementType::Float32 => "float32",
        TensorElementType::Float16 => "float16",
        TensorElementType::Float64 => "float64",
        TensorElementType::Int64 => "int64",
        TensorElementType::Int32 => "int32",
        TensorElementType::Uint8 => "uint8",
        TensorElementType::Bool => "bool",
        _ => "other",
    }
}

/// Differences between a session's inputs/outputs and an entry: missing or
/// extra inputs, missing outputs, dtype, rank, and fixed dimensions (a
/// dynamic dimension in the file accepts any manifest value; a named one in
/// the manifest accepts any file value).
fn signature_problems(entry: &ModelEntry, session: &Session) -> Vec<String> {
    let mut problems = Vec::new();
    let check = |kind: &str,
                 spec: &TensorSpec,
                 outlets: &[ort::value::Outlet],
                 problems: &mut Vec<String>| {
        let Some(outlet) = outlets.iter().find(|outlet| outlet.name() == spec.name) else {
            problems.push(format!(
                "no {kind} `{}` (expected {})",
                spec.name,
                spec.shape_string()
            ));
            return;
        };
        let ValueType::Tensor { ty, shape, .. } = outlet.dtype() else {
            problems.push(format!("{kind} `{}` is not a tensor", spec.name));
            return;
        };
        let found_dims: Vec<String> = shape
            .iter()
            .map(|d| if *d < 0 { "?".into() } else { d.to_string() })
            .collect();
        let found = format!("{} [{}]", dtype_name(*ty), found_dims.join(", "));
        let dims_match = shape.len() == spec.shape.len()
            && shape
                .iter()
                .zip(&spec.shape)
                .all(|(found, expected)| match expected {
                    Dim::Fixed(value) => *found < 0 || found == value,
                    Dim::Named(_) => true,
                });
        if dtype_name(*ty) != spec.dtype || !dims_match {
            problems.push(format!(
                "{kind} `{}` is {found}, expected {}",
                spec.name,
                spec.shape_string()
            ));
        }
    };
    for spec in &entry.inputs {
        check("input", spec, session.inputs(), &mut problems);
    }
    for outlet in session.inputs() {
        if !entry.inputs.iter().any(|spec| spec.name == outlet.name()) {
            problems.push(format!("unexpected input `{}`", outlet.name()));
        }
    }
    for spec in &entry.outputs {
        check("output", spec, session.outputs(), &mut problems);
    }
    problems
}

/// What `dm-prep models verify` found for one entry.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum VerifyStatus {
    /// No file: the stage falls back to its classical method or asks for it.
    Absent,
    /// Signature matches; `sha256_pinned` says whether the digest was checked.
    Ok { sha256: String, sha256_pinned: bool },
    /// Present but unusable (checksum, signature or load error).
    Failed(String),
}

#[derive(Clone, Debug, PartialEq, Eq)]
pub struct VerifyReport {
    pub id: String,
    pub path: PathBuf,
    pub status: VerifyStatus,
}

/// Checks every entry's file in `models_dir`: sha256 (when pinned) and the
/// ONNX signature. Absent files are reported, not errors.
pub fn verify_dir(manifest: &Manifest, models_dir: &Path) -> Vec<VerifyReport> {
    manifest
        .entries
        .iter()
        .map(|entry| {
            let path = models_dir.join(&entry.file);
            let status = if !path.is_file() {
                VerifyStatus::Absent
            } else {
                verify_file(manifest, entry, models_dir, &path)
            };
            VerifyReport {
                id: entry.id.clone(),
                path,
                status,
            }
        })
        .collect()
}

fn verify_file(
    manifest: &Manifest,
    entry: &ModelEntry,
    models_dir: &Path,
    path: &Path,
) -> VerifyStatus {
    let sha256 = match sha256_file(path) {
        Ok(digest) => digest,
        Err(error) => return VerifyStatus::Failed(error.to_string()),
    };
    if let Some(expected) = &entry.sha256
        && *expected != sha256
    {
        return VerifyStatus::Failed(
            ModelError::Checksum {
                path: path.to_path_buf(),
                id: entry.id.clone(),
                manifest_file: manifest.entry_path(&entry.id),
                expected: expected.clone(),
                found: sha256,
            }
            .to_string(),
        );
    }
    match OnnxModel::load(manifest, &entry.id, models_dir, 1) {
        Ok(_) => VerifyStatus::Ok {
            sha256,
            sha256_pinned: entry.sha256.is_some(),
        },
        Err(error) => VerifyStatus::Failed(error.to_string()),
    }
}

/// An RGB frame resized into a model's input frame, and how to map
/// coordinates between the two.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InputGeometry {
    /// Original (width, height).
    pub original: (u32, u32),
    /// Model input (width, height).
    pub input: (u32, u32),
    /// Input pixels per original pixel along x and y.
    pub scale: (f64, f64),
    /// The content's size inside the input (smaller than `input` when padded).
    pub content: (u32, u32),
}

impl InputGeometry {
    pub fn new(original: (u32, u32), preprocess: &manifest::Preprocess) -> Self {
        let input = (preprocess.size[0], preprocess.size[1]);
        match preprocess.resize {
            manifest::Resize::Stretch => Self {
                original,
                input,
                scale: (
                    f64::from(input.0) / f64::from(original.0.max(1)),
                    f64::from(input.1) / f64::from(original.1.max(1)),
                ),
                content: input,
            },
            manifest::Resize::LongestSidePad => {
                let factor =
                    f64::from(input.0.min(input.1)) / f64::from(original.0.max(original.1).max(1));
                let content = (
                    ((f64::from(original.0) * factor).round() as u32).clamp(1, input.0),
                    ((f64::from(original.1) * factor).round() as u32).clamp(1, input.1),
                );
                Self {
                    original,
                    input,
                    scale: (factor, factor),
                    content,
                }
            }
        }
    }

    pub fn to_input(&self, xy: [f64; 2]) -> [f64; 2] {
        [xy[0] * self.scale.0, xy[1] * self.scale.1]
    }

    pub fn to_original(&self, xy: [f64; 2]) -> [f64; 2] {
        [xy[0] / self.scale.0, xy[1] / self.scale.1]
    }
}

/// A frame as the model's (3, H, W) input plane, normalised, zero-padded.
pub fn image_planes(
    image: &image::RgbImage,
    preprocess: &manifest::Preprocess,
) -> (ndarray::Array3<f32>, InputGeometry) {
    let geometry = InputGeometry::new(image.dimensions(), preprocess);
    let resized = image::imageops::resize(
        image,
        geometry.content.0,
        geometry.content.1,
        image::imageops::FilterType::Triangle,
    );
    let (w, h) = (geometry.input.0 as usize, geometry.input.1 as usize);
    let mut planes = ndarray::Array3::<f32>::zeros((3, h, w));
    for (x, y, pixel) in resized.enumerate_pixels() {
        for c in 0..3 {
            planes[[c, y as usize, x as usize]] = preprocess.normalise(pixel.0[c], c);
        }
    }
    (planes, geometry)
}

/// Bilinear sample of a (H, W) map at a continuous position (pixel centres
/// at integer + 0.5), clamped at the border.
pub(crate) fn sample_bilinear(map: ndarray::ArrayView2<'_, f32>, x: f64, y: f64) -> f32 {
    let (h, w) = map.dim();
    if h == 0 || w == 0 {
        return f32::NAN;
    }
    let fx = (x - 0.5).clamp(0.0, (w - 1) as f64);
    let fy = (y - 0.5).clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (tx, ty) = ((fx - x0 as f64) as f32, (fy - y0 as f64) as f32);
    let top = map[[y0, x0]] * (1.0 - tx) + map[[y0, x1]] * tx;
    let bottom = map[[y1, x0]] * (1.0 - tx) + map[[y1, x1]] * tx;
    top * (1.0 - ty) + bottom * ty
}

/// The monocular depth network: Depth Anything 3, else MoGe-2, with one
/// intra-op thread so the depth does not depend on the core count.
pub fn load_depth_network(
    manifest: &Manifest,
    models_dir: &Path,
) -> Result<depth::DepthEstimator, ModelError> {
    let threads = 1;
    depth::DepthEstimator::load(manifest, depth::DEPTH_ANYTHING_ID, models_dir, threads).or_else(
        |first| match depth::DepthEstimator::load(manifest, depth::MOGE_ID, models_dir, threads) {
            Ok(model) => Ok(model),
            // Both absent: report the preferred one.
            Err(ModelError::Missing { .. }) => Err(first),
            Err(other) => Err(other),
        },
    )
}
