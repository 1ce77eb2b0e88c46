//! `deformmaster._native`: the Rust side of the `deformmaster` Python
//! package (docs/python.md). Scene bundles as NumPy arrays, fitted world
//! models stepped frame by frame with the GIL released, renders with the
//! fitted splats, the per-frame metrics, dm-plan's planner. The Python layer
//! (`python/deformmaster/`) coerces array types and adds the Gymnasium
//! environment; all physics runs here.
//!
//! Every entry point runs inside [`guarded`]: library errors become
//! `DeformMasterError` subclasses whose message names the file and field,
//! and a panic becomes a `DeformMasterError` instead of reaching Python.

mod arrays;
mod bundle;
mod model;
mod plan;
mod render;

use pyo3::exceptions::PyException;
use pyo3::prelude::*;

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

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("DeformMasterError", py.get_type::<DeformMasterError>())?;
    m.add("BundleError", py.get_type::<BundleError>())?;
    m.add("ModelError", py.get_type::<ModelError>())?;
    m.add("SimulationError", py.get_type::<SimulationError>())?;
    bundle::register(m)?;
    model::register(m)?;
    plan::register(m)?;
    render::register(m)?;
    Ok(())
}
