//! The fuzz targets: each parser of outside input, fed from memory or
//! through a file in a scratch directory (as the tools read them).

use crate::FuzzError;
use std::fs;
use std::path::{Path, PathBuf};

/// A parser of outside input.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Target {
    /// PhysTwin's numpy pickles (dm-prep's unpickler, default limits).
    Pickle,
    /// 3DGS PLY files (dm-splat: the splats and the point goals).
    Ply,
    /// OBJ meshes of the shape prior (dm-prep prior).
    Obj,
    /// glTF binary meshes of the shape prior.
    Glb,
    /// A model manifest entry (models_manifest/*.json).
    Manifest,
    /// A bundle's bundle.json, opened with the rest of a valid bundle.
    BundleJson,
    /// A bundle's .npy files (tracks and particles), one at a time.
    BundleNpy,
    /// A model directory's model.json.
    ModelJson,
    /// A fit's checkpoint.json (read by `dm-fit --resume`).
    Checkpoint,
    /// The playground's WebSocket commands.
    PlayCommand,
}

impl Target {
    pub const ALL: [Target; 10] = [
        Target::Pickle,
        Target::Ply,
        Target::Obj,
        Target::Glb,
        Target::Manifest,
        Target::BundleJson,
        Target::BundleNpy,
        Target::ModelJson,
        Target::Checkpoint,
        Target::PlayCommand,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Target::Pickle => "pickle",
            Target::Ply => "ply",
            Target::Obj => "obj",
            Target::Glb => "glb",
            Target::Manifest => "manifest",
            Target::BundleJson => "bundle-json",
            Target::BundleNpy => "bundle-npy",
            Target::ModelJson => "model-json",
            Target::Checkpoint => "checkpoint",
            Target::PlayCommand => "play-command",
        }
    }

    pub fn from_name(name: &str) -> Option<Target> {
        Target::ALL.into_iter().find(|t| t.name() == name)
    }

    /// Whether token-level text mutations apply.
    pub fn is_text(self) -> bool {
        matches!(
            self,
            Target::Obj
                | Target::Manifest
                | Target::BundleJson
                | Target::ModelJson
                | Target::Checkpoint
                | Target::PlayCommand
        )
    }

    /// Mixed into the seed so targets draw different mutations.
    pub(crate) fn salt(self) -> u64 {
        (self as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15)
    }

    /// The seed inputs: the files of `corpus/NAME/` (for the bundle
    /// targets, the seed bundle's bundle.json or .npy files).
    pub fn seeds(self, corpus: &Path) -> Result<Vec<Vec<u8>>, FuzzError> {
        let files = match self {
            Target::BundleJson => vec![corpus.join("bundle/bundle.json")],
            Target::BundleNpy => bundle_npy_files(&corpus.join("bundle"))?,
            _ => sorted_files(&corpus.join(self.name()))?,
        };
        let seeds = files
            .iter()
            .map(|path| {
                fs::read(path).map_err(|e| FuzzError::Corpus {
                    path: path.clone(),
                    message: e.to_string(),
                })
            })
            .collect::<Result<Vec<_>, _>>()?;
        if seeds.is_empty() {
            return Err(FuzzError::Corpus {
                path: corpus.join(self.name()),
                message: "no seed inputs".into(),
            });
        }
        Ok(seeds)
    }

    /// What feeds one input to the parser, set up in `scratch`.
    pub(crate) fn harness(self, scratch: &Path, corpus: &Path) -> Result<Harness, FuzzError> {
        let bundle = scratch.join("bundle");
        if matches!(self, Target::BundleJson | Target::BundleNpy) {
            copy_dir(&corpus.join("bundle"), &bundle)?;
        }
        let npy_files = if self == Target::BundleNpy {
            bundle_npy_files(&bundle)?
        } else {
            Vec::new()
        };
        let originals = npy_files
            .iter()
            .map(fs::read)
            .collect::<Result<Vec<_>, _>>()?;
        fs::create_dir_all(scratch.join("models"))?;
        Ok(Harness {
            target: self,
            scratch: scratch.to_path_buf(),
            bundle,
            npy_files,
            originals,
            fed: 0,
        })
    }
}

/// Feeds inputs to one target's parser.
#[derive(Debug)]
pub(crate) struct Harness {
    target: Target,
    scratch: PathBuf,
    bundle: PathBuf,
    npy_files: Vec<PathBuf>,
    originals: Vec<Vec<u8>>,
    fed: usize,
}

impl Harness {
    /// Parses `input`; true when the parser accepted it. Panics are the
    /// caller's to catch.
    pub(crate) fn feed(&mut self, input: &[u8]) -> bool {
        self.fed += 1;
        let file = |name: &str| -> PathBuf {
            let path = self.scratch.join(name);
            fs::write(&path, input).unwrap_or_else(|e| panic!("scratch write failed: {e}"));
            path
        };
        match self.target {
            Target::Pickle => {
                dm_numpy::pickle::from_slice_with_limits(input, &dm_numpy::Limits::default())
                    .is_ok()
            }
            Target::Ply => {
                let path = file("input.ply");
                let splats = dm_splat::ply::read_ply::<f32>(&path).is_ok();
                let points = dm_splat::ply::read_ply_points(&path).is_ok();
                splats || points
            }
            Target::Obj => dm_shape_prior::mesh::Mesh::load(&file("input.obj")).is_ok(),
            Target::Glb => dm_shape_prior::mesh::Mesh::load(&file("input.glb")).is_ok(),
            Target::Manifest => {
                let path = self.scratch.join("models/entry.json");
                fs::write(&path, input).unwrap_or_else(|e| panic!("scratch write failed: {e}"));
                dm_prep_models::manifest::Manifest::load_dir(&self.scratch.join("models")).is_ok()
            }
            Target::BundleJson => {
                fs::write(self.bundle.join("bundle.json"), input)
                    .unwrap_or_else(|e| panic!("scratch write failed: {e}"));
                dm_bundle::Bundle::open(&self.bundle).is_ok()
            }
            Target::BundleNpy => {
                let k = self.fed % self.npy_files.len();
                let path = &self.npy_files[k];
                fs::write(path, input).unwrap_or_else(|e| panic!("scratch write failed: {e}"));
                let opened = dm_bundle::Bundle::open(&self.bundle).is_ok();
                fs::write(path, &self.originals[k])
                    .unwrap_or_else(|e| panic!("scratch write failed: {e}"));
                opened
            }
            Target::ModelJson => dm_model::WorldModel::load(&file("model.json")).is_ok(),
            Target::Checkpoint => dm_fit::run::Checkpoint::load(&file("checkpoint.json")).is_ok(),
            Target::PlayCommand => {
                serde_json::from_slice::<dm_play::server::Command>(input).is_ok()
            }
        }
    }
}

fn sorted_files(dir: &Path) -> Result<Vec<PathBuf>, FuzzError> {
    let mut files: Vec<PathBuf> = fs::read_dir(dir)
        .map_err(|e| FuzzError::Corpus {
            path: dir.to_path_buf(),
            message: e.to_string(),
        })?
        .filter_map(|entry| entry.ok().map(|entry| entry.path()))
        .filter(|path| path.is_file())
        .collect();
    files.sort();
    Ok(files)
}

fn bundle_npy_files(bundle: &Path) -> Result<Vec<PathBuf>, FuzzError> {
    let mut files = Vec::new();
    for dir in ["tracks", "particles"] {
        files.extend(
            sorted_files(&bundle.join(dir))?
                .into_iter()
                .filter(|p| p.extension().is_some_and(|e| e == "npy")),
        );
    }
    Ok(files)
}

fn copy_dir(from: &Path, to: &Path) -> Result<(), FuzzError> {
    fs::create_dir_all(to)?;
    for entry in fs::read_dir(from).map_err(|e| FuzzError::Corpus {
        path: from.to_path_buf(),
        message: e.to_string(),
    })? {
        let entry = entry?;
        let target = to.join(entry.file_name());
        if entry.file_type()?.is_dir() {
            copy_dir(&entry.path(), &target)?;
        } else {
            fs::copy(entry.path(), target)?;
        }
    }
    Ok(())
}
