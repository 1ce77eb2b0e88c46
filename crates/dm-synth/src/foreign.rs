//! Foreign-physics truth: the same preset, hands, effect and sensor as the
//! MPM truth, simulated instead by MuJoCo's flex (finite elements on a
//! mesh, soft constraints for grips and contact), so that the world model
//! meets a discretisation, contact and grasp model it was not built from.
//!
//! The object is a flex mesh (a 1-D segment chain for the rope, a 2-D
//! shell for the cloth, a 3-D tetrahedral solid for the toy); each hand is
//! a mocap body that holds the vertices near its grasp point by equality
//! constraints. Every truth particle rides on the element holding it at
//! rest, so the sensor model renders and tracks the foreign motion exactly
//! as it does the MPM truth's. The simulation runs in Python
//! (`mujoco/mujoco_scene.py`, embedded here), started with the interpreter
//! named by `DM_MUJOCO_PYTHON` (default `python3`).

use crate::actions::{HandScript, plan};
use crate::effects::{EffectName, EffectSpec};
use crate::shapes::{ParticleCloud, Preset};
use crate::truth::{
    FPS, GroundTruth, SETTLE_FRAMES, WALL_ROOM_M, density_factors, hand_anchor_frames,
    hand_track_lag_s, tilted_gravity, truth_cloud, truth_physics,
};
use crate::{Progress, SynthConfig, SynthError};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};

/// The physics engine that makes a scene's truth.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Engine {
    /// dm-mpm's MLS-MPM at higher fidelity than the model.
    #[default]
    Mpm,
    /// MuJoCo's flex finite elements (needs Python with `mujoco`).
    Mujoco,
}

impl Engine {
    pub fn name(self) -> &'static str {
        match self {
            Engine::Mpm => "mpm",
            Engine::Mujoco => "mujoco",
        }
    }

    /// Whether this engine can hide `effect` in a scene.
    pub fn expresses(self, effect: EffectName) -> bool {
        match self {
            Engine::Mpm => true,
            Engine::Mujoco => !matches!(
                effect,
                EffectName::AirDragQuadratic
                    | EffectName::Plasticity
                    | EffectName::StiffInclusion
                    | EffectName::Wind
                    | EffectName::Attractor
                    | EffectName::AnisotropicDrag
            ),
        }
    }

    /// The library effects this engine can hide.
    pub fn effects(self) -> Vec<EffectName> {
        EffectName::ALL
            .into_iter()
            .filter(|&e| self.expresses(e))
            .collect()
    }
}

/// The simulator script, written beside each request.
const SCRIPT: &str = include_str!("../mujoco/mujoco_scene.py");
/// Environment variable naming the Python interpreter that has `mujoco`.
pub const PYTHON_ENV: &str = "DM_MUJOCO_PYTHON";
/// Substeps per recorded frame (1.67 ms): the grips' and contacts' soft
/// constraints (time constant 4 ms) need at least two steps per constant.
const SUBSTEPS_PER_FRAME: usize = 20;
/// Stiffness-proportional (Rayleigh) damping of the elastic elements, s:
/// a little internal loss, as any real material has.
const BASE_DAMPING_S: f64 = 0.002;
/// Vertices within this distance of a hand's grasp point are held: the
/// anchor ring (12 mm) plus the model's grasp radius (14 mm).
pub(crate) const HOLD_RADIUS_M: f64 = 0.026;
/// Density of the object, kg/m³ (the world model's).
const DENSITY: f64 = 1000.0;

/// The flex mesh of a preset's rest shape.
#[derive(Clone, Debug, PartialEq)]
pub struct FlexMesh {
    /// 1 (segments), 2 (triangles) or 3 (tetrahedra).
    pub dim: usize,
    pub vertices: Vec<[f64; 3]>,
    /// `dim + 1` vertex indices per element.
    pub elements: Vec<Vec<usize>>,
    /// Collision radius of vertices and elements, m.
    pub radius: f64,
    /// Shell thickness (cloth), m; 0 otherwise.
    pub thickness: f64,
}

impl FlexMesh {
    /// The mesh for `preset`: the rope's centreline in 12 mm segments, the
    /// cloth's mid-plane as a 21 × 21 triangulated grid, the toy as 6
    /// tetrahedra per 22 mm voxel of its shape.
    pub fn for_preset(preset: Preset) -> Self {
        match preset {
            Preset::Rope => {
                let (half_len, radius) = (0.24, 0.016);
                let n = 41;
                let vertices = (0..n)
                    .map(|i| {
                        [
                            -half_len + 2.0 * half_len * i as f64 / (n - 1) as f64,
                            0.0,
                            radius,
                        ]
                    })
                    .collect();
                let elements = (0..n - 1).map(|i| vec![i, i + 1]).collect();
                Self {
                    dim: 1,
                    vertices,
                    elements,
                    radius,
                    thickness: 0.0,
                }
            }
            Preset::Cloth => {
                let (half, thickness) = (0.15, 0.012);
                let n = 21;
                let at = |i: usize| -half + 2.0 * half * i as f64 / (n - 1) as f64;
                let mut vertices = Vec::new();
                for i in 0..n {
                    for j in 0..n {
                        vertices.push([at(i), at(j), thickness / 2.0]);
                    }
                }
                let mut elements = Vec::new();
                for i in 0..n - 1 {
                    for j in 0..n - 1 {
                        let (a, b, c, d) = (
                            i * n + j,
                            (i + 1) * n + j,
                            (i + 1) * n + j + 1,
                            i * n + j + 1,
                        );
                        // Counter-clockwise seen from +z: normals point up.
                        elements.push(vec![a, b, c]);
                        elements.push(vec![a, c, d]);
                    }
                }
                Self {
                    dim: 2,
                    vertices,
                    elements,
                    radius: thickness / 2.0,
                    thickness,
                }
            }
            Preset::Toy => voxel_tetrahedra(preset, 0.022),
        }
    }
}

/// Tetrahedra filling `preset`'s shape: every voxel of side `h` whose
/// centre lies within `h / 3` outside the surface, split into the six
/// tetrahedra around its main diagonal (neighbouring voxels share faces).
fn voxel_tetrahedra(preset: Preset, h: f64) -> FlexMesh {
    let (lo, hi) = preset.bounds();
    let counts = [0, 1, 2].map(|a| ((hi[a] - lo[a]) / h).ceil() as usize);
    let origin = [0, 1, 2].map(|a| 0.5 * (lo[a] + hi[a]) - 0.5 * counts[a] as f64 * h);
    let mut index = BTreeMap::new();
    let mut vertices: Vec<[f64; 3]> = Vec::new();
    let mut elements = Vec::new();
    let radius = 0.003;
    let mut vertex = |c: [usize; 3], vertices: &mut Vec<[f64; 3]>| -> usize {
        *index.entry(c).or_insert_with(|| {
            let mut p = [0, 1, 2].map(|a| origin[a] + c[a] as f64 * h);
            // Nothing starts below the floor's contact layer.
            p[2] = p[2].max(radius);
            vertices.push(p);
            vertices.len() - 1
        })
    };
    const AXIS_ORDERS: [[usize; 3]; 6] = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    for i in 0..counts[0] {
        for j in 0..counts[1] {
            for k in 0..counts[2] {
                let centre = [i, j, k].map(|n| n as f64 + 0.5);
                let centre = [0, 1, 2].map(|a| origin[a] + centre[a] * h);
                if preset.sdf(centre) > h / 3.0 {
                    continue;
                }
                for order in AXIS_ORDERS {
                    let mut corner = [i, j, k];
                    let mut tet = vec![vertex(corner, &mut vertices)];
                    for axis in order {
                        corner[axis] += 1;
                        tet.push(vertex(corner, &mut vertices));
                    }
                    if signed_volume(&vertices, &tet) < 0.0 {
                        tet.swap(1, 2);
                    }
                    elements.push(tet);
                }
            }
        }
    }
    FlexMesh {
        dim: 3,
        vertices,
        elements,
        radius,
        thickness: 0.0,
    }
}

fn signed_volume(vertices: &[[f64; 3]], tet: &[usize]) -> f64 {
    let d = |k: usize| [0, 1, 2].map(|a| vertices[tet[k]][a] - vertices[tet[0]][a]);
    let (a, b, c) = (d(1), d(2), d(3));
    a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
        + a[2] * (b[0] * c[1] - b[1] * c[0])
}

/// One hand as the simulator sees it.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct HandRequest {
    name: String,
    grasp: [f64; 3],
    held_vertices: Vec<usize>,
    /// `[x, y, z, twist_rad]` of the grasp point per recorded frame.
    poses: Vec<[f64; 4]>,
}

/// Everything `mujoco_scene.py` reads (`request.json`).
#[derive(Clone, Debug, Serialize, Deserialize)]
struct Request {
    dim: usize,
    vertices: Vec<[f64; 3]>,
    elements: Vec<Vec<usize>>,
    radius: f64,
    thickness: f64,
    mass_kg: f64,
    vertex_mass_factors: Option<Vec<f64>>,
    young_pa: f64,
    poisson: f64,
    damping_s: f64,
    gravity: [f64; 3],
    floor_height: f64,
    floor_friction: f64,
    air_drag_per_s: f64,
    fps: f64,
    settle_frames: usize,
    frames: usize,
    substeps_per_frame: usize,
    hands: Vec<HandRequest>,
    cloud_rest: Vec<[f64; 3]>,
}

/// What the engine reports (`result.json`), kept in the truth file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EngineRecord {
    pub engine: String,
    pub version: String,
    pub timestep_s: f64,
    pub steps: usize,
    pub seconds: f64,
    pub mass_kg: f64,
    /// MuJoCo's warnings over the run (its log stays in the temporary
    /// directory).
    #[serde(default)]
    pub warnings: u64,
    /// Set by dm-synth: the flex's dimension, vertex and element counts,
    /// and its elastic damping.
    #[serde(default)]
    pub flex_dim: usize,
    #[serde(default)]
    pub flex_vertices: usize,
    #[serde(default)]
    pub flex_elements: usize,
    #[serde(default)]
    pub damping_s: f64,
}

/// Every truth particle's position per recorded frame.
type ParticleFrames = Vec<Vec<[f32; 3]>>;

/// The foreign truth and what the engine reported.
#[derive(Debug)]
pub struct ForeignTruth {
    pub truth: GroundTruth,
    pub engine: EngineRecord,
    /// Mean distance (m) of the object's surface particles from their
    /// places in the same scene without the hidden effect, over the clip;
    /// for `actuator_lag`, of the recorded hand anchors from the true ones.
    pub effect_displacement_m: Option<f64>,
}

/// Checks that the engine can express `config`'s effect.
pub fn check_effect(config: &SynthConfig) -> Result<(), SynthError> {
    match config.effect.map(|e| e.name) {
        Some(name) if !Engine::Mujoco.expresses(name) => {
            let supported: Vec<&str> = Engine::Mujoco.effects().iter().map(|e| e.name()).collect();
            Err(SynthError::InvalidOption {
                option: "--effect".into(),
                problem: format!(
                    "`{}` cannot be hidden in a MuJoCo scene (supported: {})",
                    name.name(),
                    supported.join(", ")
                ),
            })
        }
        _ => Ok(()),
    }
}

/// Simulates `config`'s scene with MuJoCo (and, when an effect is hidden,
/// its null twin, to report how far the effect moves the object).
pub fn simulate_foreign(
    config: &SynthConfig,
    progress: Progress<'_>,
) -> Result<ForeignTruth, SynthError> {
    let Scene {
        hands,
        cloud,
        mesh,
        request,
        effect_extra,
    } = Scene::of(config)?;
    let preset = config.preset;
    let (frames, mut engine) = run_engine(&request, "foreign simulation", progress)?;
    engine.flex_dim = mesh.dim;
    engine.flex_vertices = mesh.vertices.len();
    engine.flex_elements = mesh.elements.len();
    engine.damping_s = request.damping_s;

    let anchors = hand_anchor_frames(&hands, config.frames, 0.0);
    let recorded_anchors = hand_anchor_frames(&hands, config.frames, hand_track_lag_s(config));
    let effect_displacement_m = match config.effect.map(|e| e.name) {
        None => None,
        Some(EffectName::ActuatorLag) => Some(mean_distance(
            anchors.iter().flatten(),
            recorded_anchors.iter().flatten(),
        )),
        Some(_) => {
            let null = scene_request(config, &hands, &cloud, &mesh, None, &mut BTreeMap::new());
            let (null_frames, _) = run_engine(&null, "null twin", progress)?;
            let surface = |f: &Vec<[f32; 3]>| -> Vec<[f64; 3]> {
                f.iter()
                    .zip(&cloud.on_surface)
                    .filter(|(_, s)| **s)
                    .map(|(p, _)| p.map(f64::from))
                    .collect()
            };
            let a: Vec<[f64; 3]> = frames.iter().flat_map(surface).collect();
            let b: Vec<[f64; 3]> = null_frames.iter().flat_map(surface).collect();
            Some(mean_distance(a.iter(), b.iter()))
        }
    };

    let (e0, nu0) = preset.nominal_material();
    let mut physics = truth_physics(preset, anchors.iter().flatten(), WALL_ROOM_M);
    physics.gravity = request.gravity;
    physics.effects.air_drag_linear = request.air_drag_per_s;
    physics.effects.floor_friction = request.floor_friction;
    let n = cloud.len();
    Ok(ForeignTruth {
        truth: GroundTruth {
            preset,
            hands,
            cloud,
            frames,
            anchors,
            recorded_anchors,
            effect_extra,
            youngs_pa: vec![e0; n],
            poisson: vec![nu0; n],
            inclusion: None,
            physics,
        },
        engine,
        effect_displacement_m,
    })
}

fn mean_distance<'a>(
    a: impl Iterator<Item = &'a [f64; 3]>,
    b: impl Iterator<Item = &'a [f64; 3]>,
) -> f64 {
    let (sum, count) = a.zip(b).fold((0.0, 0usize), |(s, c), (p, q)| {
        let d2: f64 = (0..3).map(|k| (p[k] - q[k]).powi(2)).sum();
        (s + d2.sqrt(), c + 1)
    });
    sum / count.max(1) as f64
}

/// The simulator's request for `config`'s scene with `effect` hidden.
fn scene_request(
    config: &SynthConfig,
    hands: &[HandScript],
    cloud: &ParticleCloud,
    mesh: &FlexMesh,
    effect: Option<EffectSpec>,
    effect_extra: &mut BTreeMap<String, serde_json::Value>,
) -> Request {
    let (young, poisson) = config.preset.nominal_material();
    let mut request = Request {
        dim: mesh.dim,
        vertices: mesh.vertices.clone(),
        elements: mesh.elements.clone(),
        radius: mesh.radius,
        thickness: mesh.thickness,
        mass_kg: DENSITY * cloud.particle_volume() * cloud.len() as f64,
        vertex_mass_factors: None,
        young_pa: young,
        poisson,
        damping_s: BASE_DAMPING_S,
        gravity: [0.0, 0.0, -9.8],
        floor_height: 0.0,
        floor_friction: 0.0,
        air_drag_per_s: 0.0,
        fps: FPS,
        settle_frames: SETTLE_FRAMES,
        frames: config.frames,
        substeps_per_frame: SUBSTEPS_PER_FRAME,
        hands: hands
            .iter()
            .map(|h| HandRequest {
                name: h.name.clone(),
                grasp: h.grasp,
                held_vertices: held_vertices(&mesh.vertices, h.grasp),
                poses: (0..config.frames)
                    .map(|t| {
                        let (p, angle) = h.pose_at(t as f64 / FPS);
                        [p[0], p[1], p[2], angle]
                    })
                    .collect(),
            })
            .collect(),
        cloud_rest: cloud.positions.clone(),
    };
    if let Some(EffectSpec { name, magnitude }) = effect {
        match name {
            EffectName::AirDrag => request.air_drag_per_s = magnitude,
            EffectName::FloorFriction => request.floor_friction = magnitude,
            // η ≈ β E for stiffness-proportional damping β.
            EffectName::ViscousDamping => request.damping_s += magnitude / young,
            EffectName::GroundTilt => {
                request.gravity = tilted_gravity(config.seed, magnitude, effect_extra)
            }
            EffectName::DensityVariation => {
                request.vertex_mass_factors = Some(density_factors(
                    config,
                    magnitude,
                    &mesh.vertices,
                    effect_extra,
                ))
            }
            // The hands move the same; only their record lags.
            EffectName::ActuatorLag => {}
            // Refused by `check_effect` before any request is made.
            EffectName::AirDragQuadratic
            | EffectName::Plasticity
            | EffectName::StiffInclusion
            | EffectName::Wind
            | EffectName::Attractor
            | EffectName::AnisotropicDrag => {}
        }
    }
    request
}

/// Vertices within [`HOLD_RADIUS_M`] of `grasp`, or the nearest one.
fn held_vertices(vertices: &[[f64; 3]], grasp: [f64; 3]) -> Vec<usize> {
    let dist = |p: &[f64; 3]| {
        (0..3)
            .map(|a| (p[a] - grasp[a]).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    let held: Vec<usize> = (0..vertices.len())
        .filter(|&i| dist(&vertices[i]) < HOLD_RADIUS_M)
        .collect();
    if held.is_empty() {
        (0..vertices.len())
            .min_by(|&a, &b| dist(&vertices[a]).total_cmp(&dist(&vertices[b])))
            .into_iter()
            .collect()
    } else {
        held
    }
}

pub(crate) fn engine_error(problem: impl Into<String>) -> SynthError {
    SynthError::Engine(problem.into())
}

/// The Python of [`PYTHON_ENV`] (default `python3`), to run in `dir`
/// (MuJoCo writes its log to the working directory).
pub(crate) fn python_in(dir: &Path) -> (String, Command) {
    let mut python = std::env::var(PYTHON_ENV).unwrap_or_else(|_| "python3".into());
    // Absolute, not canonical: a venv's interpreter is a symlink that must stay one.
    if python.contains('/')
        && let Ok(absolute) = std::path::absolute(&python)
    {
        python = absolute.to_string_lossy().into_owned();
    }
    let mut command = Command::new(&python);
    command.current_dir(dir);
    (python, command)
}

pub(crate) fn cannot_start(python: &str, e: std::io::Error) -> SynthError {
    engine_error(format!(
        "cannot start `{python}` ({e}); set {PYTHON_ENV} to a Python with mujoco (make foreign-setup)"
    ))
}

/// Writes the simulator script and `config`'s request into `dir`; returns
/// the script's path and the scene's truth particles.
pub(crate) fn write_request(
    config: &SynthConfig,
    dir: &Path,
) -> Result<(std::path::PathBuf, ParticleCloud), SynthError> {
    let scene = Scene::of(config)?;
    write_files(&scene.request, dir)?;
    Ok((dir.join("mujoco_scene.py"), scene.cloud))
}

/// A scene's parts as the simulator gets them.
struct Scene {
    hands: Vec<HandScript>,
    cloud: ParticleCloud,
    mesh: FlexMesh,
    request: Request,
    /// What the hidden effect drew (its direction, its field).
    effect_extra: BTreeMap<String, serde_json::Value>,
}

impl Scene {
    fn of(config: &SynthConfig) -> Result<Self, SynthError> {
        check_effect(config)?;
        let action = config.resolved_action();
        let duration = config.frames as f64 / FPS;
        let hands = plan(config.preset, action, config.two_hands, duration);
        let cloud = truth_cloud(config);
        let mesh = FlexMesh::for_preset(config.preset);
        let mut effect_extra = BTreeMap::new();
        let request = scene_request(
            config,
            &hands,
            &cloud,
            &mesh,
            config.effect,
            &mut effect_extra,
        );
        Ok(Self {
            hands,
            cloud,
            mesh,
            request,
            effect_extra,
        })
    }
}

fn write_files(request: &Request, dir: &Path) -> Result<(), SynthError> {
    let io = |path: &Path, e: std::io::Error| SynthError::Io {
        path: path.to_owned(),
        source: e,
    };
    let script = dir.join("mujoco_scene.py");
    std::fs::write(&script, SCRIPT).map_err(|e| io(&script, e))?;
    let request_path = dir.join("request.json");
    let text = serde_json::to_string(request)
        .map_err(|e| engine_error(format!("encoding the request: {e}")))?;
    std::fs::write(&request_path, text).map_err(|e| io(&request_path, e))
}

/// Runs the simulator on `request` in a fresh temporary directory and
/// reads back every truth particle's position per frame.
fn run_engine(
    request: &Request,
    stage: &str,
    progress: Progress<'_>,
) -> Result<(ParticleFrames, EngineRecord), SynthError> {
    let dir = tempfile::Builder::new()
        .prefix("dm-synth-mujoco-")
        .tempdir()
        .map_err(|e| engine_error(format!("creating a temporary directory: {e}")))?;
    write_files(request, dir.path())?;
    let script = dir.path().join("mujoco_scene.py");
    let (python, mut command) = python_in(dir.path());
    let mut child = command
        .arg(&script)
        .arg(dir.path())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| cannot_start(&python, e))?;
    let mut messages = Vec::new();
    if let Some(stderr) = child.stderr.take() {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let counted = line
                .strip_prefix("frame ")
                .and_then(|rest| rest.split_once('/'))
                .and_then(|(done, total)| Some((done.parse().ok()?, total.parse().ok()?)));
            match counted {
                Some((done, total)) => progress(stage, done, total),
                None => messages.push(line),
            }
        }
    }
    let status = child
        .wait()
        .map_err(|e| engine_error(format!("waiting for `{python}`: {e}")))?;
    if !status.success() {
        return Err(engine_error(format!(
            "`{python}` {} failed ({status}): {}",
            script.display(),
            messages.join(" | ")
        )));
    }
    let frames_path = dir.path().join("cloud_frames.npy");
    let array: ndarray::Array3<f32> = dm_bundle::read_npy_checked(&frames_path)?;
    let shape = array.shape().to_vec();
    if shape != [request.frames, request.cloud_rest.len(), 3] {
        return Err(engine_error(format!(
            "{}: shape {shape:?}, expected [{}, {}, 3]",
            frames_path.display(),
            request.frames,
            request.cloud_rest.len()
        )));
    }
    if array.iter().any(|v| !v.is_finite()) {
        return Err(engine_error(format!(
            "{}: non-finite positions",
            frames_path.display()
        )));
    }
    let frames = array
        .outer_iter()
        .map(|f| f.outer_iter().map(|p| [p[0], p[1], p[2]]).collect())
        .collect();
    let result_path = dir.path().join("result.json");
    let engine: EngineRecord = dm_bundle::read_json(&result_path)?;
    Ok((frames, engine))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every tetrahedron of the toy's mesh is positively oriented and the
    /// mesh covers the shape: each truth particle lies within a voxel's
    /// reach of a vertex.
    #[test]
    fn toy_tetrahedra_are_oriented_and_cover_the_shape() {
        let mesh = FlexMesh::for_preset(Preset::Toy);
        assert!(
            mesh.elements.len() > 500,
            "{} tetrahedra",
            mesh.elements.len()
        );
        for tet in &mesh.elements {
            assert!(signed_volume(&mesh.vertices, tet) > 0.0);
        }
        let cloud = ParticleCloud::fill(Preset::Toy, 2000, 1);
        for p in &cloud.positions {
            let nearest = mesh
                .vertices
                .iter()
                .map(|v| (0..3).map(|a| (v[a] - p[a]).powi(2)).sum::<f64>().sqrt())
                .fold(f64::INFINITY, f64::min);
            assert!(
                nearest < 0.022,
                "particle {p:?} is {nearest} m from the mesh"
            );
        }
    }

    /// Each hand holds a handful of vertices around its grasp point, for
    /// every preset and action.
    #[test]
    fn hands_hold_vertices_near_their_grasp() {
        for preset in [Preset::Rope, Preset::Cloth, Preset::Toy] {
            let mesh = FlexMesh::for_preset(preset);
            for action in crate::Action::ALL {
                for hand in plan(preset, action, false, 1.2) {
                    let held = held_vertices(&mesh.vertices, hand.grasp);
                    assert!(
                        (1..=16).contains(&held.len()),
                        "{preset:?} {action:?} {}: {} vertices held",
                        hand.name,
                        held.len()
                    );
                }
            }
        }
    }
}
