//! `plan`: dm-plan's search and execution called in-process, its options
//! given as dm-plan's own flags (keywords turned into them), its outputs
//! returned as arrays; and a plan from a live simulation's state.

use std::ops::ControlFlow;
use std::path::PathBuf;

use dm_model::WorldModel;
use dm_plan::PlanError;
use dm_plan::goal::Goal;
use dm_plan::live::{LiveStart, plan_from_state};
use dm_plan::run::{PlanOptions, RunResult, SearchOptions, plan as run_plan, write_outputs};
use numpy::IntoPyArray;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::bundle::to_json_object;
use crate::{
    BundleError, DeformMasterError, ModelError, SimulationError, Watcher, guarded, parse_flags,
};

pub(crate) fn plan_error(error: PlanError) -> PyErr {
    let message = error.to_string();
    match error {
        PlanError::Bundle(_) => BundleError::new_err(message),
        PlanError::Model(e) => crate::model_error(e),
        PlanError::Simulation(_) => SimulationError::new_err(message),
        PlanError::InvalidOption { .. } => PyValueError::new_err(message),
        PlanError::Play(_) | PlanError::Synth(_) => ModelError::new_err(message),
        PlanError::File { .. } | PlanError::Stopped { .. } => DeformMasterError::new_err(message),
    }
}

/// dm-plan's progress handed to the caller's callback, Ctrl-C checked;
/// `Break` once either raised.
fn reporting(watcher: &mut Watcher) -> impl FnMut(&str, usize, usize) -> ControlFlow<()> + '_ {
    move |stage, done, total| {
        let going =
            watcher.keep_going(|py, callback| callback.call1(py, (stage, done, total)).map(drop));
        if going {
            ControlFlow::Continue(())
        } else {
            ControlFlow::Break(())
        }
    }
}

/// dm-plan's search options as `Simulation.plan`'s keywords give them.
#[derive(clap::Parser)]
#[command(name = "Simulation.plan")]
struct SearchFlags {
    #[command(flatten)]
    search: SearchOptions,
}

/// A plan from `start` (a simulation of `model`) to `goal`, searched with
/// the options `args` (dm-plan's search flags); see `Simulation.plan`.
pub(crate) fn plan_live<'py>(
    py: Python<'py>,
    model: &WorldModel,
    start: &LiveStart<'_>,
    goal: &Goal,
    args: &[String],
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let flags: SearchFlags = parse_flags("Simulation.plan", args)?;
    let mut watcher = Watcher::new(py, progress)?;
    let result = py.detach(|| {
        plan_from_state(
            model,
            start,
            goal,
            &flags.search,
            &mut reporting(&mut watcher),
        )
    });
    watcher.finish()?;
    let plan = result.map_err(plan_error)?;
    let d = PyDict::new(py);
    d.set_item("record", to_json_object(py, &plan.record)?)?;
    d.set_item(
        "hands",
        dm_plan::output::actions_array(&plan.hands).into_pyarray(py),
    )?;
    d.set_item(
        "planned",
        dm_plan::output::frames_array(&plan.planned).into_pyarray(py),
    )?;
    let ids: Vec<i64> = plan.planned_particles.iter().map(|&i| i as i64).collect();
    d.set_item("planned_particles", ids.into_pyarray(py))?;
    d.set_item("frame_dt", plan.frame_dt)?;
    Ok(d)
}

/// The arrays and record of a run, as dm-plan writes them to files.
fn result_dict<'py>(py: Python<'py>, result: &RunResult) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("record", to_json_object(py, &result.record)?)?;
    d.set_item(
        "hands",
        dm_plan::output::actions_array(&result.hands).into_pyarray(py),
    )?;
    d.set_item(
        "planned",
        dm_plan::output::frames_array(&result.planned).into_pyarray(py),
    )?;
    d.set_item(
        "executed",
        dm_plan::output::frames_array(&result.executed).into_pyarray(py),
    )?;
    let goal = dm_plan::output::frames_array(std::slice::from_ref(&result.goal.points));
    d.set_item(
        "goal",
        goal.index_axis_move(ndarray::Axis(0), 0).into_pyarray(py),
    )?;
    d.set_item("frame_dt", result.frame_dt)?;
    Ok(d)
}

/// Plans and carries out a hand motion as `dm-plan` does, from its
/// command-line `args`; writes dm-plan's files (no video) into `out` when
/// given. `progress(stage, done, total)` is called as the run goes; an
/// exception it raises, or Ctrl-C, stops the run and is raised.
#[pyfunction]
#[pyo3(signature = (args, out = None, progress = None))]
fn plan_from_args<'py>(
    py: Python<'py>,
    args: Vec<String>,
    out: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    guarded("plan", || {
        let mut options: PlanOptions = parse_flags("dm-plan", &args)?;
        options.no_video = true;
        options.out = out.clone().unwrap_or_default();
        let mut watcher = Watcher::new(py, progress)?;
        let result = py.detach(|| run_plan(&options, &mut reporting(&mut watcher)));
        watcher.finish()?;
        let result = result.map_err(plan_error)?;
        if let Some(out) = &out {
            py.detach(|| write_outputs(out, &result))
                .map_err(plan_error)?;
        }
        result_dict(py, &result)
    })
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(plan_from_args, m)?)?;
    Ok(())
}
