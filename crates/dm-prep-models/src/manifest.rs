//! `models_manifest/`: what each ONNX model must look like (docs/prep.md).
//!
//! One JSON file per model: task, expected file name, sha256 (null when no
//! reference export has been pinned), input/output names with dtypes and
//! shapes (an integer is a fixed dimension, a string a named dynamic one),
//! preprocessing, and where a user obtains it. The workspace's manifest is
//! compiled in ([`Manifest::builtin`]); [`Manifest::load_dir`] reads another.

use std::fs;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::ModelError;

/// The manifest files compiled into the binary, by file name.
const BUILTIN: [(&str, &str); 5] = [
    (
        "sam2_image_encoder.json",
        include_str!("../../../models_manifest/sam2_image_encoder.json"),
    ),
    (
        "sam2_prompt_decoder.json",
        include_str!("../../../models_manifest/sam2_prompt_decoder.json"),
    ),
    (
        "cotracker3.json",
        include_str!("../../../models_manifest/cotracker3.json"),
    ),
    (
        "depth_anything3.json",
        include_str!("../../../models_manifest/depth_anything3.json"),
    ),
    (
        "moge2.json",
        include_str!("../../../models_manifest/moge2.json"),
    ),
];

/// Where model files are looked for when no directory is given.
pub const MODELS_DIR_ENV: &str = "DM_MODELS_DIR";
pub const DEFAULT_MODELS_DIR: &str = "models";

/// The models directory: `$DM_MODELS_DIR`, else `./models`.
pub fn default_models_dir() -> PathBuf {
    match std::env::var_os(MODELS_DIR_ENV) {
        Some(dir) if !dir.is_empty() => PathBuf::from(dir),
        _ => PathBuf::from(DEFAULT_MODELS_DIR),
    }
}

/// One dimension of a tensor in the manifest.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Dim {
    Fixed(i64),
    Named(String),
}

impl std::fmt::Display for Dim {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Dim::Fixed(value) => write!(f, "{value}"),
            Dim::Named(name) => f.write_str(name),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TensorSpec {
    pub name: String,
    /// `float32`, `int64`, `bool`, ...
    pub dtype: String,
    pub shape: Vec<Dim>,
}

impl TensorSpec {
    pub fn shape_string(&self) -> String {
        let dims: Vec<String> = self.shape.iter().map(Dim::to_string).collect();
        format!("{} {} [{}]", self.name, self.dtype, dims.join(", "))
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Resize {
    /// Scale the longest side to the input size, pad bottom/right with zeros (SAM).
    LongestSidePad,
    /// Scale both axes to the input size.
    Stretch,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Layout {
    /// (1, 3, H, W)
    #[serde(rename = "NCHW")]
    Nchw,
    /// (1, T, 3, H, W)
    #[serde(rename = "NTCHW")]
    Ntchw,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Preprocess {
    /// Network input (width, height).
    pub size: [u32; 2],
    pub resize: Resize,
    pub layout: Layout,
    /// 8-bit values are multiplied by this before mean/std.
    pub value_scale: f32,
    pub mean: [f32; 3],
    pub std: [f32; 3],
}

impl Preprocess {
    /// `(value · value_scale − mean[c]) / std[c]` of an 8-bit channel value.
    pub fn normalise(&self, value: u8, channel: usize) -> f32 {
        (f32::from(value) * self.value_scale - self.mean[channel]) / self.std[channel]
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelEntry {
    pub id: String,
    pub task: String,
    pub model: String,
    pub file: String,
    /// Lower-case hex; `None` when no reference export has been pinned.
    pub sha256: Option<String>,
    pub inputs: Vec<TensorSpec>,
    pub outputs: Vec<TensorSpec>,
    pub preprocess: Preprocess,
    pub obtain: String,
}

/// All entries, in file-name order.
#[derive(Clone, Debug, PartialEq)]
pub struct Manifest {
    pub entries: Vec<ModelEntry>,
    /// Where the entries came from, for messages (`models_manifest/` when built in).
    pub source: PathBuf,
}

impl Manifest {
    /// The workspace's `models_manifest/`, compiled in.
    pub fn builtin() -> Result<Self, ModelError> {
        let source = PathBuf::from("models_manifest");
        let entries = BUILTIN
            .iter()
            .map(|(file, text)| parse_entry(&source.join(file), text))
            .collect::<Result<_, _>>()?;
        Ok(Self { entries, source })
    }

    /// Every `*.json` of a directory.
    pub fn load_dir(dir: &Path) -> Result<Self, ModelError> {
        let io = |error: std::io::Error| ModelError::Io {
            path: dir.to_path_buf(),
            message: error.to_string(),
        };
        let mut files: Vec<PathBuf> = fs::read_dir(dir)
            .map_err(io)?
            .filter_map(|entry| entry.ok().map(|entry| entry.path()))
            .filter(|path| path.extension().is_some_and(|ext| ext == "json"))
            .collect();
        files.sort();
        let entries = files
            .iter()
            .map(|path| {
                let text = fs::read_to_string(path).map_err(|error| ModelError::Io {
                    path: path.clone(),
                    message: error.to_string(),
                })?;
                parse_entry(path, &text)
            })
            .collect::<Result<_, _>>()?;
        Ok(Self {
            entries,
            source: dir.to_path_buf(),
        })
    }

    pub fn entry(&self, id: &str) -> Result<&ModelEntry, ModelError> {
        self.entries
            .iter()
            .find(|entry| entry.id == id)
            .ok_or_else(|| ModelError::UnknownEntry {
                id: id.to_string(),
                manifest: self.source.clone(),
            })
    }

    /// The manifest file of an entry, for messages.
    pub fn entry_path(&self, id: &str) -> PathBuf {
        self.source.join(format!("{id}.json"))
    }
}

fn parse_entry(path: &Path, text: &str) -> Result<ModelEntry, ModelError> {
    let deserializer = &mut serde_json::Deserializer::from_str(text);
    let entry: ModelEntry = serde_path_to_error::deserialize(deserializer).map_err(|error| {
        ModelError::BadManifest {
            path: path.to_path_buf(),
            field: error.path().to_string(),
            problem: error.inner().to_string(),
        }
    })?;
    if let Some(digest) = &entry.sha256
        && (digest.len() != 64
            || !digest
                .bytes()
                .all(|b| b.is_ascii_hexdigit() && !b.is_ascii_uppercase()))
    {
        return Err(ModelError::BadManifest {
            path: path.to_path_buf(),
            field: "sha256".into(),
            problem: format!("`{digest}` is not 64 lower-case hex digits"),
        });
    }
    Ok(entry)
}

/// SHA-256 of a file, lower-case hex.
pub fn sha256_file(path: &Path) -> Result<String, ModelError> {
    let mut file = fs::File::open(path).map_err(|error| ModelError::Io {
        path: path.to_path_buf(),
        message: error.to_string(),
    })?;
    let mut hasher = Sha256::new();
    std::io::copy(&mut file, &mut hasher).map_err(|error| ModelError::Io {
        path: path.to_path_buf(),
        message: error.to_string(),
    })?;
    Ok(hasher
        .finalize()
        .iter()
        .map(|byte| format!("{byte:02x}"))
        .collect())
}
