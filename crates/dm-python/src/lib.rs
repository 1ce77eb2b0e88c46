//! `deformmaster._native`: the Rust side of the `deformmaster` Python
//! package (docs/python.md). Scene bundles as NumPy arrays, fitted world
//! models stepped frame by frame with the GIL released, renders with the
//! fitted splats, the per-frame metrics, dm-fit's and dm-plan's runs. The
//! Python layer (`python/deformmaster/`) coerces array types, turns
//! keywords into the tools' flags and adds the Gymnasium environment; all
//! physics runs here.
//!
//! Every entry point runs inside [`guarded`]: library errors become
//! `DeformMasterError` subclasses whose message names the file and field,
//! and a panic becomes a `DeformMasterError` instead of reaching Python.

mod arrays;
mod bundle;
mod fit;
mod model;
mod plan;
mod render;

use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict};

pyo3::create_exception!(
    deformmaster,
    DeformMasterError,
    PyException,
    "Any error raised by deformmaster; the message names the file and field at fault."
);
pyo3::create_exception!(
    deformmaster,
    BundleError,
    DeformMasterError,
    "A scene bundle could not be read or written."
);
pyo3::create_exception!(
    deformmaster,
    ModelError,
    DeformMasterError,
    "A world model could not be loaded or built, or an option is out of range."
);
pyo3::create_exception!(
    deformmaster,
    SimulationError,
    DeformMasterError,
    "The simulation refused its input or diverged."
);

/// Maps the libraries' errors onto the Python exception classes.
pub(crate) fn model_error(error: dm_model::ModelError) -> PyErr {
    match error {
        dm_model::ModelError::Bundle(e) => BundleError::new_err(e.to_string()),
        dm_model::ModelError::Simulation(e) => SimulationError::new_err(e.to_string()),
        other => ModelError::new_err(other.to_string()),
    }
}

pub(crate) fn bundle_error(error: dm_bundle::BundleError) -> PyErr {
    BundleError::new_err(error.to_string())
}

/// Runs `body`, turning a panic into a `DeformMasterError` naming `what`.
pub(crate) fn guarded<T>(what: &str, body: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(body)) {
        Ok(result) => result,
        Err(payload) => {
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown cause".into());
            Err(DeformMasterError::new_err(format!(
                "internal error in {what}: {message}"
            )))
        }
    }
}

/// Ctrl-C during a long call that released the GIL: Python's signal
/// handlers run only on its main thread and only with the GIL, so the call
/// takes the GIL back to run them, at most every [`Self::EVERY`] and only
/// on the main thread (elsewhere it would only wait for the GIL).
pub(crate) struct Interrupts {
    main_thread: bool,
    last: std::time::Instant,
}

impl Interrupts {
    const EVERY: std::time::Duration = std::time::Duration::from_millis(100);

    pub(crate) fn new(py: Python<'_>) -> PyResult<Self> {
        let threading = py.import("threading")?;
        let current = threading.call_method0("current_thread")?;
        Ok(Self {
            main_thread: current.is(&threading.call_method0("main_thread")?),
            last: std::time::Instant::now(),
        })
    }

    /// Runs the signal handlers when due; a `KeyboardInterrupt` comes back
    /// as the error.
    pub(crate) fn check(&mut self) -> PyResult<()> {
        if !self.main_thread || self.last.elapsed() < Self::EVERY {
            return Ok(());
        }
        self.last = std::time::Instant::now();
        Python::attach(|py| py.check_signals())
    }
}

/// A long call's Python side while it runs without the GIL: the caller's
/// progress callback, and Ctrl-C. The first exception either raises stops
/// the call and is raised when it returns ([`Self::finish`]).
pub(crate) struct Watcher {
    callback: Option<Py<PyAny>>,
    interrupts: Interrupts,
    failure: Option<PyErr>,
}

impl Watcher {
    pub(crate) fn new(py: Python<'_>, callback: Option<Py<PyAny>>) -> PyResult<Self> {
        Ok(Self {
            callback,
            interrupts: Interrupts::new(py)?,
            failure: None,
        })
    }

    /// Runs `call` on the callback, if there is one, with Python's signal
    /// handlers; false once either has raised.
    pub(crate) fn keep_going(
        &mut self,
        call: impl FnOnce(Python<'_>, &Py<PyAny>) -> PyResult<()>,
    ) -> bool {
        if self.failure.is_some() {
            return false;
        }
        let outcome = match &self.callback {
            Some(callback) => Python::attach(|py| {
                py.check_signals()?;
                call(py, callback)
            }),
            None => self.interrupts.check(),
        };
        outcome.map_err(|e| self.failure = Some(e)).is_ok()
    }

    /// The exception that stopped the call, if one did.
    pub(crate) fn finish(self) -> PyResult<()> {
        self.failure.map_or(Ok(()), Err)
    }
}

/// Keyword options as a tool's flags: `_` for `-`, `True` a bare flag,
/// `False` and `None` left out, any other value its `str()`.
pub(crate) fn keyword_flags(options: Option<&Bound<'_, PyDict>>) -> PyResult<Vec<String>> {
    let mut args = Vec::new();
    for (key, value) in options.into_iter().flatten() {
        let flag = format!("--{}", key.extract::<String>()?.replace('_', "-"));
        if value.is_none() {
            continue;
        }
        if let Ok(on) = value.cast::<PyBool>() {
            if on.is_true() {
                args.push(flag);
            }
            continue;
        }
        args.push(flag);
        args.push(value.str()?.to_string());
    }
    Ok(args)
}

/// [`keyword_flags`] for the Python layer's `fit` and `plan`.
#[pyfunction]
fn flags(options: &Bound<'_, PyDict>) -> PyResult<Vec<String>> {
    keyword_flags(Some(options))
}

/// A tool's options parsed from its command-line flags `args` (without
/// the program's name); the error is clap's first line, naming the flag.
pub(crate) fn parse_flags<T: clap::Parser>(tool: &str, args: &[String]) -> PyResult<T> {
    let argv = std::iter::once(tool.to_owned()).chain(args.iter().cloned());
    T::try_parse_from(argv).map_err(|e| {
        let text = e.to_string();
        let first = text
            .lines()
            .next()
            .unwrap_or("")
            .trim_start_matches("error: ");
        pyo3::exceptions::PyValueError::new_err(format!("{tool} option: {first}"))
    })
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("DeformMasterError", py.get_type::<DeformMasterError>())?;
    m.add("BundleError", py.get_type::<BundleError>())?;
    m.add("ModelError", py.get_type::<ModelError>())?;
    m.add("SimulationError", py.get_type::<SimulationError>())?;
    m.add_function(wrap_pyfunction!(flags, m)?)?;
    bundle::register(m)?;
    fit::register(m)?;
    model::register(m)?;
    plan::register(m)?;
    render::register(m)?;
    Ok(())
}
