//! World models loaded from a model directory (or built untrained from a
//! bundle) and simulations of them stepped frame by frame.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use dm_appearance::follow::SplatFollower;
use dm_model::device::Device;
use dm_model::metrics::{chamfer_to, frame_errors, match_tracks};
use dm_model::{ModelOptions, ResidualKind, Simulation, WorldModel};
use dm_plan::goal::Goal;
use dm_plan::live::LiveStart;
use dm_play::MaterialControl;
use dm_play::session::{DAMPING_RANGE, E_SCALE_RANGE, NU_RANGE};
use dm_splat::Gaussians;
use numpy::{
    AllowTypeChange, IntoPyArray, PyArray1, PyArray2, PyArray3, PyArrayLike1, PyArrayLike2,
    PyArrayLike3,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::arrays::{frames_from_array, frames_to_array, points_from_array, points_to_array};
use crate::bundle::PyBundle;
use crate::plan::{plan_error, plan_live};
use crate::render::{CameraArg, render_view};
use crate::{
    DeformMasterError, Interrupts, ModelError, SimulationError, guarded, keyword_flags, model_error,
};

/// A world model: fitted (`load_model`) or untrained (`Model.from_bundle`).
#[pyclass(name = "Model", module = "deformmaster", frozen)]
#[derive(Debug)]
pub struct PyModel {
    pub model: Arc<WorldModel>,
    /// The fitted splats (`gaussians.ply`), when the model directory has them.
    splats: Option<Arc<Gaussians<f32>>>,
    directory: Option<PathBuf>,
}

#[pymethods]
impl PyModel {
    /// The untrained model of a bundle's scene (dm-sim without
    /// --model-dir): `experts` "moce" or "nh", `residual` "none", "pgnd"
    /// or "mlp" (an untrained network), `grid` cells per side.
    #[staticmethod]
    #[pyo3(signature = (bundle, experts = "moce", residual = "none", grid = None))]
    fn from_bundle(
        bundle: &PyBundle,
        experts: &str,
        residual: &str,
        grid: Option<usize>,
    ) -> PyResult<Self> {
        guarded("Model.from_bundle", || {
            let experts = match experts {
                "moce" => dm_model::ExpertChoice::Moce,
                "nh" => dm_model::ExpertChoice::Nh,
                other => {
                    return Err(ModelError::new_err(format!(
                        "experts `{other}`: use \"moce\" or \"nh\""
                    )));
                }
            };
            let residual = match residual {
                "none" => ResidualKind::None,
                "pgnd" => ResidualKind::Pgnd,
                "mlp" => ResidualKind::Mlp,
                other => {
                    return Err(ModelError::new_err(format!(
                        "residual `{other}`: use \"none\", \"pgnd\" or \"mlp\""
                    )));
                }
            };
            let defaults = ModelOptions::default();
            let options = ModelOptions {
                experts,
                residual,
                grid: grid.unwrap_or(defaults.grid),
                ..defaults
            };
            let model = WorldModel::from_bundle(&bundle.inner, &options).map_err(model_error)?;
            Ok(Self {
                model: Arc::new(model),
                splats: None,
                directory: None,
            })
        })
    }

    /// The directory the model was loaded from (None when built from a bundle).
    #[getter]
    fn directory(&self) -> Option<PathBuf> {
        self.directory.clone()
    }

    #[getter]
    fn particle_count(&self) -> usize {
        self.model.particles.len()
    }

    /// The first `surface_count` particles are the surface ones.
    #[getter]
    fn surface_count(&self) -> usize {
        self.model.surface_count
    }

    /// First-frame particle positions, (N, 3) float64 metres.
    #[getter]
    fn particles<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        points_to_array(py, &self.model.particles)
    }

    /// Particle colours, (N, 3) float32 in [0, 1].
    #[getter]
    fn colors<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f32>> {
        points_to_array(py, &self.model.colors)
    }

    /// The simulation's cubic domain: its lower corner (metres) and edge length.
    #[getter]
    fn domain(&self) -> ([f64; 3], f64) {
        (
            self.model.physics.domain_origin,
            self.model.physics.domain_size,
        )
    }

    /// Simulated seconds per video frame.
    #[getter]
    fn frame_dt(&self) -> f64 {
        self.model.physics.dt * self.model.physics.substeps_per_frame as f64
    }

    /// Per-particle Young's modulus (Pa) and Poisson ratio, (N,) float64 each.
    fn material_fields<'py>(
        &self,
        py: Python<'py>,
    ) -> (Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>) {
        let m = &self.model;
        let (e, nu, _) = m.patches.particle_fields(&m.params, &m.bounds);
        (e.into_pyarray(py), nu.into_pyarray(py))
    }

    /// Median Young's modulus (Pa) and Poisson ratio.
    #[getter]
    fn material<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let (e, nu) = self.model.material_medians();
        let d = PyDict::new(py);
        d.set_item("E_median_pa", e)?;
        d.set_item("nu_median", nu)?;
        d.set_item(
            "particle_damping_per_s",
            self.model.physics.particle_damping,
        )?;
        Ok(d)
    }

    /// Whether the model carries a residual network.
    #[getter]
    fn has_residual(&self) -> bool {
        self.model.residual.is_some()
    }

    /// Whether the model directory has fitted splats (renders use them).
    #[getter]
    fn has_splats(&self) -> bool {
        self.splats.is_some()
    }

    /// A simulation at the first frame with the hands at `hands` ((H, 3)
    /// metres). With `follow_splats` the fitted splats are moved every
    /// frame (needed for splat renders; costs a few ms per frame).
    /// `device` is "cpu" or "cuda" (the MPM world and the residual
    /// network on the first NVIDIA GPU).
    #[pyo3(signature = (hands, follow_splats = false, device = "cpu"))]
    fn simulation(
        &self,
        py: Python<'_>,
        hands: PyArrayLike2<'_, f64, AllowTypeChange>,
        follow_splats: bool,
        device: &str,
    ) -> PyResult<PySimulation> {
        guarded("Model.simulation", || {
            let device = parse_device(device)?;
            let hands = points_from_array(&hands, "hands")?;
            let follower = match (&self.splats, follow_splats) {
                (Some(g), true) => Some(
                    SplatFollower::new((**g).clone(), &self.model.particles)
                        .map_err(|e| ModelError::new_err(e.to_string()))?,
                ),
                (None, true) => {
                    return Err(ModelError::new_err(
                        "follow_splats: this model has no fitted splats (gaussians.ply); dm-fit's stage 3 or dm-appearance writes them",
                    ));
                }
                _ => None,
            };
            let model = self.model.clone();
            let simulation = py
                .detach(|| model.simulation_on(device))
                .map_err(model_error)?;
            Ok(PySimulation {
                state: Mutex::new(SimulationState {
                    simulation,
                    hands,
                    grasp_next: true,
                    material: MaterialControl {
                        e_scale: 1.0,
                        nu: None,
                        damping: self.model.physics.particle_damping,
                    },
                    follower,
                }),
                model: self.model.clone(),
            })
        })
    }

    /// Open-loop rollout driven by the bundle's hand track, as dm-sim runs
    /// it: positions of every frame, (T, N, 3) float32. `device` as in
    /// `simulation`. Ctrl-C stops it between frames.
    #[pyo3(signature = (bundle, frames = None, device = "cpu"))]
    fn rollout<'py>(
        &self,
        py: Python<'py>,
        bundle: &PyBundle,
        frames: Option<usize>,
        device: &str,
    ) -> PyResult<Bound<'py, PyArray3<f32>>> {
        guarded("Model.rollout", || {
            let device = parse_device(device)?;
            let frames = frames.unwrap_or(bundle.inner.frame_count());
            let model = &self.model;
            let b = &bundle.inner;
            let mut interrupts = Interrupts::new(py)?;
            let mut stopped = None;
            let rollout = py
                .detach(|| {
                    model.rollout_while(b, frames, device, &mut |_| match interrupts.check() {
                        Ok(()) => std::ops::ControlFlow::Continue(()),
                        Err(interrupt) => {
                            stopped = Some(interrupt);
                            std::ops::ControlFlow::Break(())
                        }
                    })
                })
                .map_err(model_error)?;
            if let Some(interrupt) = stopped {
                return Err(interrupt);
            }
            frames_to_array(py, &rollout)
        })
    }

    /// The particle each of the bundle's tracked points follows (its
    /// nearest at the first frame, as the track error matches them),
    /// (M,) int64.
    fn track_particles<'py>(
        &self,
        py: Python<'py>,
        bundle: &PyBundle,
    ) -> PyResult<Bound<'py, PyArray1<i64>>> {
        let matched = match_tracks(&self.model.particles, &bundle.inner.tracks);
        let ids: Vec<i64> = matched.iter().map(|m| m.map_or(-1, |i| i as i64)).collect();
        Ok(ids.into_pyarray(py))
    }

    /// A named goal shape (rope: straighten, u-shape, move; cloth: fold,
    /// flatten, move; toy: place, squash, rotate; docs/plan.md) made from
    /// this model's first-frame particles in `bundle`'s scene: `(points
    /// (M, 3), particles (M,))`, the arguments of `Simulation.plan`.
    #[allow(clippy::type_complexity)]
    fn goal<'py>(
        &self,
        py: Python<'py>,
        name: &str,
        bundle: &PyBundle,
    ) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyArray1<i64>>)> {
        guarded("Model.goal", || {
            let meta = &bundle.inner.meta;
            let goal = Goal::named(
                name,
                meta.category,
                &self.model.particles,
                self.model.surface_count,
                meta.up_axis.unit_vector(),
                meta.floor_height_m,
            )
            .map_err(plan_error)?;
            let ids: Vec<i64> = goal.particles.iter().flatten().map(|&i| i as i64).collect();
            Ok((points_to_array(py, &goal.points), ids.into_pyarray(py)))
        })
    }

    /// Per-frame errors of a rollout ((T, N, 3), frame 0 first) against the
    /// bundle's tracks: `track_m` and `chamfer_m`, (T,) float64, NaN where
    /// no point was visible (docs/metrics.md).
    fn frame_errors<'py>(
        &self,
        py: Python<'py>,
        bundle: &PyBundle,
        rollout: PyArrayLike3<'_, f32, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let view = rollout.as_array();
        if view.shape()[1] != self.model.particles.len() || view.shape()[2] != 3 {
            return Err(PyValueError::new_err(format!(
                "`rollout` must have shape (T, {}, 3), got {:?}",
                self.model.particles.len(),
                view.shape()
            )));
        }
        let frames: Vec<Vec<[f32; 3]>> = view
            .outer_iter()
            .map(|f| f.outer_iter().map(|r| [r[0], r[1], r[2]]).collect())
            .collect();
        let errors = frame_errors(&frames, self.model.surface_count, &bundle.inner.tracks);
        let d = PyDict::new(py);
        d.set_item("track_m", errors.track.into_pyarray(py))?;
        d.set_item("chamfer_m", errors.chamfer.into_pyarray(py))?;
        Ok(d)
    }

    fn __repr__(&self) -> String {
        let (e, nu) = self.model.material_medians();
        format!(
            "Model({} particles, E {e:.3e} Pa, nu {nu:.2}, residual {}, splats {})",
            self.model.particles.len(),
            self.model.residual.is_some(),
            self.splats.is_some()
        )
    }
}

/// `"cpu"` or `"cuda"` as a device, else the error naming the argument.
fn parse_device(device: &str) -> PyResult<Device> {
    match device {
        "cpu" => Ok(Device::Cpu),
        "cuda" => Ok(Device::Cuda),
        other => Err(ModelError::new_err(format!(
            "device: expected \"cpu\" or \"cuda\", got {other:?}"
        ))),
    }
}

/// Reads `model.json` (and the splats, when present) from a dm-fit model directory.
#[pyfunction]
fn load_model(py: Python<'_>, directory: PathBuf) -> PyResult<PyModel> {
    guarded("load_model", || {
        let model = py
            .detach(|| WorldModel::load(&directory.join("model.json")))
            .map_err(crate::model_error)?;
        let splats = if dm_appearance::store::has_appearance(&directory) {
            let (gaussians, _) = py
                .detach(|| dm_appearance::store::load_appearance(&directory, &model))
                .map_err(|e| ModelError::new_err(e.to_string()))?;
            Some(Arc::new(gaussians))
        } else {
            None
        };
        Ok(PyModel {
            model: Arc::new(model),
            splats,
            directory: Some(directory),
        })
    })
}

#[derive(Debug)]
struct SimulationState {
    simulation: Simulation,
    /// Hand anchor positions now (the start of the next frame).
    hands: Vec<[f64; 3]>,
    /// Whether the next frame captures grasps (the first frame, and the
    /// first after a material change rebuilt the world).
    grasp_next: bool,
    material: MaterialControl,
    follower: Option<SplatFollower>,
}

impl SimulationState {
    fn step(&mut self, to: &[[f64; 3]], grasp: Option<&[bool]>) -> Result<(), PyErr> {
        if to.len() != self.hands.len() {
            return Err(PyValueError::new_err(format!(
                "{} hand positions given; the simulation has {} hands",
                to.len(),
                self.hands.len()
            )));
        }
        let grasp: Vec<bool> = match grasp {
            Some(g) => g.to_vec(),
            None => vec![self.grasp_next; to.len()],
        };
        self.simulation
            .step(&self.hands, to, &grasp)
            .map_err(model_error)?;
        self.hands = to.to_vec();
        self.grasp_next = false;
        if let Some(follower) = &mut self.follower {
            follower
                .advance(&self.simulation.positions_f32().map_err(model_error)?)
                .map_err(|e| SimulationError::new_err(e.to_string()))?;
        }
        Ok(())
    }
}

/// A simulation of a world model, advanced one video frame per `step`.
#[pyclass(name = "Simulation", module = "deformmaster", frozen)]
#[derive(Debug)]
pub struct PySimulation {
    state: Mutex<SimulationState>,
    model: Arc<WorldModel>,
}

impl PySimulation {
    /// The state, or an error when another thread is stepping it (waiting
    /// while holding the GIL could deadlock with that thread).
    fn lock(&self) -> PyResult<std::sync::MutexGuard<'_, SimulationState>> {
        match self.state.try_lock() {
            Ok(guard) => Ok(guard),
            Err(std::sync::TryLockError::WouldBlock) => Err(SimulationError::new_err(
                "the simulation is being stepped from another thread",
            )),
            Err(std::sync::TryLockError::Poisoned(_)) => Err(DeformMasterError::new_err(
                "the simulation was left inconsistent by an internal error; create a new one",
            )),
        }
    }
}

#[pymethods]
impl PySimulation {
    /// Advances one frame while the hands move linearly from where they
    /// are to `hands` ((H, 3) metres). `grasp` ((H,) bool) marks hands
    /// that tie the particles within the grasp radius at this frame's
    /// start; by default every hand grasps at the first frame (and after
    /// `set_material`), none later.
    #[pyo3(signature = (hands, grasp = None))]
    fn step(
        &self,
        py: Python<'_>,
        hands: PyArrayLike2<'_, f64, AllowTypeChange>,
        grasp: Option<PyArrayLike1<'_, bool, AllowTypeChange>>,
    ) -> PyResult<()> {
        guarded("Simulation.step", || {
            let to = points_from_array(&hands, "hands")?;
            let grasp: Option<Vec<bool>> = grasp.map(|g| g.as_array().to_vec());
            let mut state = self.lock()?;
            let state = &mut *state;
            py.detach(|| state.step(&to, grasp.as_deref()))
        })
    }

    /// Steps one frame per row of `hands` ((K, H, 3)) and returns the
    /// particle positions after each, (K, N, 3) float32; the GIL is
    /// released between frames, and Ctrl-C stops the call there.
    fn step_many<'py>(
        &self,
        py: Python<'py>,
        hands: PyArrayLike3<'_, f64, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyArray3<f32>>> {
        guarded("Simulation.step_many", || {
            let path = frames_from_array(&hands, "hands")?;
            let mut state = self.lock()?;
            let state = &mut *state;
            let mut interrupts = Interrupts::new(py)?;
            let frames = py.detach(|| -> PyResult<Vec<Vec<[f32; 3]>>> {
                let mut out = Vec::with_capacity(path.len());
                for to in &path {
                    // Ctrl-C stops between frames, the state at the last one.
                    interrupts.check()?;
                    state.step(to, None)?;
                    out.push(state.simulation.positions_f32().map_err(model_error)?);
                }
                Ok(out)
            })?;
            if frames.is_empty() {
                let n = self.model.particles.len();
                return Ok(numpy::PyArray3::zeros(py, [0, n, 3], false));
            }
            frames_to_array(py, &frames)
        })
    }

    /// Plans where the hands go over the next frames to bring the object
    /// to `goal` ((M, 3) metres; `particles`, (M,), the model particle that
    /// should end at each point, when known, e.g. from `Model.goal`), from
    /// this simulation's state, its hands holding what they hold (taking
    /// hold at the plan's start only where `step` would) and its material
    /// in force. `rigid_hands`, `(start, end)` ranges of the anchors in
    /// order (e.g. `Bundle.hand_ranges`), moves each range as one rigid
    /// hand (a gripper); by default every anchor moves on its own.
    /// Keywords are dm-plan's search options
    /// (`horizon=30`, `iterations=3`, `exact=True`; `device` defaults to
    /// the simulation's). The simulation is not advanced: step
    /// `plan["hands"][1:]` (all of them, or the first few and plan again).
    /// `progress(stage, done, total)` as in `plan`; Ctrl-C stops the search.
    #[pyo3(signature = (goal, particles = None, progress = None, rigid_hands = None, **options))]
    fn plan<'py>(
        &self,
        py: Python<'py>,
        goal: PyArrayLike2<'_, f64, AllowTypeChange>,
        particles: Option<PyArrayLike1<'_, i64, AllowTypeChange>>,
        progress: Option<Py<PyAny>>,
        rigid_hands: Option<Vec<[usize; 2]>>,
        options: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyDict>> {
        guarded("Simulation.plan", || {
            let points = points_from_array(&goal, "goal")?;
            let particles = particles
                .map(|ids| {
                    ids.as_array()
                        .iter()
                        .map(|&i| {
                            usize::try_from(i).map_err(|_| {
                                PyValueError::new_err(format!(
                                    "`particles` holds {i}; particle numbers are ≥ 0"
                                ))
                            })
                        })
                        .collect::<PyResult<Vec<usize>>>()
                })
                .transpose()?;
            let goal = Goal {
                name: "points".into(),
                points,
                particles,
            };
            let mut args = keyword_flags(options)?;
            let (state, grip, hands, material) = {
                let mut guard = self.lock()?;
                let guard = &mut *guard;
                let simulation = &mut guard.simulation;
                let device_given = match options {
                    Some(o) => o.get_item("device")?.is_some_and(|d| !d.is_none()),
                    None => false,
                };
                if !device_given {
                    args.extend(["--device".into(), simulation.device().to_string()]);
                }
                let all: Vec<usize> = (0..self.model.particles.len()).collect();
                let (state, mut grip) = py
                    .detach(|| -> Result<_, dm_model::ModelError> {
                        let world = simulation.world()?;
                        Ok((world.state(), world.grip(&all)?))
                    })
                    .map_err(model_error)?;
                // As `step` by default: the hands take hold only when its
                // next frame grasps.
                if !guard.grasp_next {
                    grip.grasped = vec![true; guard.hands.len()];
                }
                (state, grip, guard.hands.clone(), guard.material)
            };
            let start = LiveStart {
                state: &state,
                hands: &hands,
                grip: &grip,
                material: &material,
                rigid_hands: rigid_hands.as_deref(),
            };
            plan_live(py, &self.model, &start, &goal, &args, progress)
        })
    }

    /// Where the MPM world runs: "cpu" or "cuda".
    #[getter]
    fn device(&self) -> PyResult<String> {
        Ok(self.lock()?.simulation.device().to_string())
    }

    /// Frames stepped since the first frame.
    #[getter]
    fn frame(&self) -> PyResult<usize> {
        Ok(self.lock()?.simulation.frame())
    }

    /// Hand anchor positions now, (H, 3) float64.
    #[getter]
    fn hands<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        Ok(points_to_array(py, &self.lock()?.hands))
    }

    /// Particle positions, (N, 3) float32 metres (the simulation's precision).
    #[getter]
    fn positions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        Ok(points_to_array(
            py,
            &self
                .lock()?
                .simulation
                .positions_f32()
                .map_err(model_error)?,
        ))
    }

    /// Particle velocities, (N, 3) float64 m/s.
    #[getter]
    fn velocities<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        Ok(points_to_array(
            py,
            &self
                .lock()?
                .simulation
                .world()
                .map_err(model_error)?
                .velocities(),
        ))
    }

    /// Deformation gradients F, (N, 3, 3) float32.
    #[getter]
    fn deformation_gradients<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray3<f32>>> {
        let f = self
            .lock()?
            .simulation
            .world()
            .map_err(model_error)?
            .deformation_gradients();
        let array = ndarray::Array3::from_shape_fn((f.len(), 3, 3), |(p, r, c)| f[p][(r, c)]);
        Ok(array.into_pyarray(py))
    }

    /// Positions of the given particles ((M,) int indices, e.g.
    /// `Model.track_particles`), (M, 3) float32.
    fn points<'py>(
        &self,
        py: Python<'py>,
        particles: PyArrayLike1<'_, i64, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let positions = self
            .lock()?
            .simulation
            .positions_f32()
            .map_err(model_error)?;
        let ids = particles.as_array();
        let mut out = Vec::with_capacity(ids.len());
        for &i in ids {
            let p = usize::try_from(i)
                .ok()
                .and_then(|i| positions.get(i))
                .ok_or_else(|| {
                    PyValueError::new_err(format!(
                        "particle index {i} is outside 0..{}",
                        positions.len()
                    ))
                })?;
            out.push(*p);
        }
        Ok(points_to_array(py, &out))
    }

    /// One-directional L1 Chamfer distance (metres) from `targets`
    /// ((M, 3)) to the surface particles: the metric's Chamfer term.
    fn chamfer_to(&self, targets: PyArrayLike2<'_, f64, AllowTypeChange>) -> PyResult<f64> {
        let targets = points_from_array(&targets, "targets")?;
        let mut state = self.lock()?;
        let positions = state.simulation.world().map_err(model_error)?.positions();
        let surface = &positions[..self.model.surface_count.min(positions.len())];
        Ok(chamfer_to(surface, &targets))
    }

    /// Sets the material as the playground does, within its slider ranges:
    /// every fitted Young's modulus times `e_scale` (0.1–10), one Poisson
    /// ratio `nu` for all (0–0.45; None keeps the fitted field) and the
    /// particle damping rate (1/s, 0–50; None keeps it). The simulation continues from its
    /// state; grasps are captured again at the next step.
    #[pyo3(signature = (e_scale = 1.0, nu = None, damping = None))]
    fn set_material(
        &self,
        py: Python<'_>,
        e_scale: f64,
        nu: Option<f64>,
        damping: Option<f64>,
    ) -> PyResult<()> {
        guarded("Simulation.set_material", || {
            let in_range = |v: f64, r: [f64; 2]| v.is_finite() && (r[0]..=r[1]).contains(&v);
            if !in_range(e_scale, E_SCALE_RANGE) {
                return Err(PyValueError::new_err(format!(
                    "e_scale must be within {E_SCALE_RANGE:?}, got {e_scale}"
                )));
            }
            if let Some(nu) = nu.filter(|&nu| !in_range(nu, NU_RANGE)) {
                return Err(PyValueError::new_err(format!(
                    "nu must be within {NU_RANGE:?}, got {nu}"
                )));
            }
            if let Some(d) = damping.filter(|&d| !in_range(d, DAMPING_RANGE)) {
                return Err(PyValueError::new_err(format!(
                    "damping must be within {DAMPING_RANGE:?} 1/s, got {d}"
                )));
            }
            let mut state = self.lock()?;
            let state = &mut *state;
            let control = MaterialControl {
                e_scale,
                nu,
                damping: damping.unwrap_or(state.material.damping),
            };
            let model = &self.model;
            py.detach(|| {
                let mut physics = model.physics.clone();
                physics.particle_damping = control.damping;
                let material = model.scaled_material(control.e_scale, control.nu);
                state.simulation.rebuild(model, physics, material)
            })
            .map_err(model_error)?;
            state.material = control;
            state.grasp_next = true;
            Ok(())
        })
    }

    /// The material in force: `e_scale`, `nu` (None: fitted) and `damping`.
    #[getter]
    fn material<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let m = self.lock()?.material;
        let d = PyDict::new(py);
        d.set_item("e_scale", m.e_scale)?;
        d.set_item("nu", m.nu)?;
        d.set_item("damping", m.damping)?;
        Ok(d)
    }

    /// Substeps per frame in force (chosen for the stiffest material).
    #[getter]
    fn substeps_per_frame(&self) -> PyResult<usize> {
        Ok(self
            .lock()?
            .simulation
            .world()
            .map_err(model_error)?
            .config()
            .substeps_per_frame)
    }

    /// Renders the current frame from `camera` (a dict with width, height,
    /// fx, fy, cx, cy and world_to_camera, as `Bundle.camera` gives):
    /// `rgb` (h, w, 3) uint8, `depth` (h, w) float32 metres (NaN: nothing),
    /// `mask` (h, w) bool object pixels. With the splats when the
    /// simulation follows them, else the particles as spheres over a floor.
    #[pyo3(signature = (camera, background = (1.0, 1.0, 1.0)))]
    fn render<'py>(
        &self,
        py: Python<'py>,
        camera: CameraArg,
        background: (f64, f64, f64),
    ) -> PyResult<Bound<'py, PyDict>> {
        guarded("Simulation.render", || {
            let camera = camera.to_camera()?;
            let mut state = self.lock()?;
            let positions = state.simulation.positions_f32().map_err(model_error)?;
            let hands: Vec<[f32; 3]> = state.hands.iter().map(|h| h.map(|c| c as f32)).collect();
            let splats = state.follower.as_ref().map(|f| f.gaussians());
            let model = &self.model;
            let view = py.detach(|| {
                render_view(
                    model,
                    splats,
                    &positions,
                    &hands,
                    &camera,
                    [background.0, background.1, background.2],
                )
            })?;
            view.into_dict(py)
        })
    }
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyModel>()?;
    m.add_class::<PySimulation>()?;
    m.add_function(wrap_pyfunction!(load_model, m)?)?;
    Ok(())
}
