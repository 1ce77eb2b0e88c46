//! `fit`: dm-fit's stages called in-process, its options given as dm-fit's
//! own flags (the Python layer turns keywords into them); the model
//! directory is written as dm-fit writes it, checkpointed after each step.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};

use dm_bundle::Bundle;
use dm_fit::material_fit::FitError;
use dm_fit::run::{FitOptions, FitOutcome, run_fit_until};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::bundle::to_json_object;
use crate::{
    BundleError, DeformMasterError, SimulationError, Watcher, bundle_error, guarded, parse_flags,
};

/// dm-fit's options as its command line takes them.
#[derive(clap::Parser)]
#[command(name = "dm-fit")]
struct FitFlags {
    #[command(flatten)]
    options: FitOptions,
}

fn fit_error(error: FitError) -> PyErr {
    let message = error.to_string();
    match error {
        FitError::Bundle(_) => BundleError::new_err(message),
        FitError::Model(e) => crate::model_error(e),
        FitError::Simulation(_) => SimulationError::new_err(message),
        FitError::InvalidOption { .. } => PyValueError::new_err(message),
        _ => DeformMasterError::new_err(message),
    }
}

/// Fits (or, with `resume`, continues) a world model of the bundle at
/// `bundle` into the model directory `out` as `dm-fit` does, from its
/// command-line `args`; returns fit_report.json as a dict, or None where
/// `stop_after` steps paused it. `progress(message)` gets dm-fit's
/// progress lines; an exception it raises, or Ctrl-C, pauses the fit after
/// the step it is in (checkpointed) and is raised.
#[pyfunction]
#[pyo3(signature = (bundle, out, args, resume = false, stop_after = None, progress = None))]
fn fit_from_args<'py>(
    py: Python<'py>,
    bundle: PathBuf,
    out: PathBuf,
    args: Vec<String>,
    resume: bool,
    stop_after: Option<usize>,
    progress: Option<Py<PyAny>>,
) -> PyResult<Option<Bound<'py, PyAny>>> {
    guarded("fit", || {
        let flags: FitFlags = parse_flags("dm-fit", &args)?;
        let scene = py.detach(|| Bundle::open(&bundle)).map_err(bundle_error)?;
        let cancel = AtomicBool::new(false);
        let mut watcher = Watcher::new(py, progress)?;
        let outcome = py.detach(|| {
            run_fit_until(
                &scene,
                &flags.options,
                &out,
                resume,
                stop_after,
                Some(&cancel),
                &mut |message| {
                    if !watcher.keep_going(|py, callback| callback.call1(py, (message,)).map(drop))
                    {
                        cancel.store(true, Ordering::Relaxed);
                    }
                },
            )
        });
        watcher.finish()?;
        match outcome.map_err(fit_error)? {
            FitOutcome::Finished(report) => Ok(Some(to_json_object(py, &*report)?)),
            FitOutcome::Paused { .. } => Ok(None),
        }
    })
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(fit_from_args, m)?)?;
    Ok(())
}
