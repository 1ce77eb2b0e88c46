//! The ONNX Runtime library of the setup venv, found and loaded once per process.
//!
//! `make lpips` installs the pinned PyPI onnxruntime (1.31.1) into `.venv` and
//! records the path of its `libonnxruntime.so` in `.cache/lpips/ort_dylib_path`
//! (scripts/build_lpips.py). Every crate that runs ONNX models (dm-eval's
//! LPIPS, dm-prep's model adapters) loads that library through this crate, so
//! the lookup rules live in one place:
//! * `$ORT_DYLIB_PATH`, when set, names the library directly;
//! * else the record file `ort_dylib_path` in the cache directory
//!   (`$DM_LPIPS_DIR`, else `.cache/lpips` of the workspace this was built in).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

pub use ort;

/// Environment variable naming the library directly.
pub const DYLIB_ENV: &str = "ORT_DYLIB_PATH";
/// Environment variable naming the cache directory that holds the record.
pub const CACHE_DIR_ENV: &str = "DM_LPIPS_DIR";
/// The record file: one line, the library's path.
pub const DYLIB_RECORD_FILE: &str = "ort_dylib_path";
/// The command that installs the runtime and writes the record.
pub const MAKE_TARGET: &str = "make lpips";

/// Why the runtime library could not be found or loaded.
#[derive(Debug, thiserror::Error)]
pub enum RuntimeError {
    #[error("{}: missing ONNX Runtime record; run `{MAKE_TARGET}` (or set {DYLIB_ENV})", path.display())]
    MissingRecord { path: PathBuf },
    #[error("{}: empty; expected the path of libonnxruntime.so (rerun `{MAKE_TARGET}`)", path.display())]
    EmptyRecord { path: PathBuf },
    #[error("{}: cannot load the ONNX Runtime library: {message} (rebuild with `{MAKE_TARGET}` or set {DYLIB_ENV})", path.display())]
    Load { path: PathBuf, message: String },
}

/// `$DM_LPIPS_DIR`, else the workspace's `.cache/lpips`.
pub fn default_cache_dir() -> PathBuf {
    match std::env::var_os(CACHE_DIR_ENV) {
        Some(dir) if !dir.is_empty() => PathBuf::from(dir),
        // crates/dm-ort → the workspace root.
        _ => Path::new(env!("CARGO_MANIFEST_DIR"))
            .ancestors()
            .nth(2)
            .unwrap_or(Path::new("."))
            .join(".cache/lpips"),
    }
}

/// The library path: `$ORT_DYLIB_PATH`, else the record in `cache_dir`;
/// checked to be a file.
pub fn dylib_path(cache_dir: &Path) -> Result<PathBuf, RuntimeError> {
    let dylib = match std::env::var_os(DYLIB_ENV) {
        Some(path) if !path.is_empty() => PathBuf::from(path),
        _ => {
            let record = cache_dir.join(DYLIB_RECORD_FILE);
            let text =
                std::fs::read_to_string(&record).map_err(|_| RuntimeError::MissingRecord {
                    path: record.clone(),
                })?;
            if text.trim().is_empty() {
                return Err(RuntimeError::EmptyRecord { path: record });
            }
            PathBuf::from(text.trim())
        }
    };
    if !dylib.is_file() {
        return Err(RuntimeError::Load {
            path: dylib,
            message: "no such file".into(),
        });
    }
    Ok(dylib)
}

/// ONNX Runtime allows one environment per process, and one library: the
/// first successful load wins for the process.
static ENVIRONMENT: OnceLock<Result<ort::environment::Environment, String>> = OnceLock::new();

/// The process's ONNX Runtime environment, loading `dylib` on first use.
pub fn environment(dylib: &Path) -> Result<ort::environment::Environment, RuntimeError> {
    let result = ENVIRONMENT.get_or_init(|| {
        ort::init_from(dylib)
            .map_err(|e| e.to_string())?
            .with_name("deformmaster")
            .build()
            .map_err(|e| e.to_string())
    });
    result.clone().map_err(|message| RuntimeError::Load {
        path: dylib.to_path_buf(),
        message,
    })
}

/// The environment of the default library (`dylib_path(default_cache_dir())`).
pub fn default_environment() -> Result<ort::environment::Environment, RuntimeError> {
    environment(&dylib_path(&default_cache_dir())?)
}
