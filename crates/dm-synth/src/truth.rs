//! The ground-truth simulation: higher fidelity than the model, spatially
//! varying material, scripted hands, and the hidden effect.

use crate::actions::{HandScript, plan};
use crate::effects::{EffectName, EffectSpec};
use crate::field::SmoothField;
use crate::shapes::{ParticleCloud, Preset};
use crate::{Progress, SynthConfig, SynthError, splitmix};
use dm_mpm::domain::cube_domain_containing;
use dm_mpm::{ActuatorConfig, ActuatorMode, ForceField, ParticleMaterial, PhysicsConfig, World};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

pub const FPS: f64 = 30.0;
/// Frames simulated before recording so the object rests under gravity.
pub(crate) const SETTLE_FRAMES: usize = 8;
/// Truth fidelity relative to the model defaults (grid 32, dt 8e-4): the
/// grid's cells over the domain of the object and the hands alone.
const TRUTH_GRID: usize = 48;
/// Room (m) kept along the floor between the object's rest shape and the
/// truth's slip walls, which are the simulation's edge, not part of the
/// world. With the object's own bounds as the domain's, a rope's end lay
/// one cell from the wall and was held there for the whole clip (seed
/// 1026: its end stayed at x = 0.26 m while the push and a tilted gravity
/// drove it outwards), a constraint no model with a wider domain can
/// reproduce (docs/RESULTS.md).
pub(crate) const WALL_ROOM_M: f64 = 0.1;
const TRUTH_SUBSTEPS_PER_FRAME: usize = 84;
/// The truth's Courant number: finer than the model's
/// ([`dm_mpm::config::DEFAULT_CFL`]), like its grid and substep.
const TRUTH_CFL: f64 = 0.3;

/// Expert mix (Neo-Hookean, fixed corotated, StVK) of a `--homogeneous` truth.
pub const HOMOGENEOUS_EXPERT_WEIGHTS: [f64; 3] = [0.3, 0.6, 0.1];

/// The truth's hands. Real fingers grip firmly: stiffer and tighter than
/// the model's default actuators.
pub const TRUTH_GRIP: ActuatorConfig = ActuatorConfig {
    mode: ActuatorMode::Distributed,
    kp: 2.0e4,
    kd: 300.0,
    grasp_radius: 0.014,
};

/// Everything the sensor model needs.
#[derive(Clone, Debug)]
pub struct GroundTruth {
    pub preset: Preset,
    pub hands: Vec<HandScript>,
    pub cloud: ParticleCloud,
    /// Positions of every truth particle per recorded frame.
    pub frames: Vec<Vec<[f32; 3]>>,
    /// Anchor positions per recorded frame (all hands, concatenated).
    pub anchors: Vec<Vec<[f64; 3]>>,
    /// What the hand tracker records per frame: `anchors`, or for
    /// `actuator_lag` the anchors `lag` seconds earlier.
    pub recorded_anchors: Vec<Vec<[f64; 3]>>,
    /// Effect parameters drawn from the seed (truth file `effect.params`).
    pub effect_extra: BTreeMap<String, serde_json::Value>,
    pub youngs_pa: Vec<f64>,
    pub poisson: Vec<f64>,
    pub inclusion: Option<([f64; 3], f64)>,
    pub physics: PhysicsConfig,
}

/// `{"E_pa", "nu"}`: medians over the object.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TruthMaterial {
    #[serde(rename = "E_pa")]
    pub e_pa: f64,
    pub nu: f64,
}

/// `{"name", "params"}` of the hidden effect.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TruthEffect {
    pub name: String,
    pub params: BTreeMap<String, serde_json::Value>,
}

/// Version of the truth simulation, recorded in every truth file so that
/// a cached scene made by another version is made again (a configuration
/// alone no longer names one scene). 1: the domain bounded by the object
/// and the hands (a rope's ends one cell from the slip walls); 2: room
/// along the floor ([`WALL_ROOM_M`]).
pub const TRUTH_VERSION: u32 = 2;

/// The truth file, kept outside the bundle (contract keys: `preset`,
/// `seed`, `material`, `effect`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TruthFile {
    /// [`TRUTH_VERSION`] of the simulation that made it (absent: 1).
    #[serde(default = "first_truth_version")]
    pub truth_version: u32,
    pub preset: String,
    pub seed: u64,
    pub material: TruthMaterial,
    pub effect: Option<TruthEffect>,
    pub action: String,
    pub hands: Vec<HandScript>,
    pub truth_particles: usize,
    pub physics: PhysicsConfig,
    pub config: SynthConfig,
    /// What the foreign engine reported (absent when dm-mpm made the truth).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub engine: Option<crate::foreign::EngineRecord>,
    /// How far the hidden effect moves the object: the mean distance (m)
    /// of its surface particles from the same scene without the effect
    /// (for `actuator_lag`, of the recorded hand anchors from the true
    /// ones). Reported for foreign scenes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub effect_displacement_m: Option<f64>,
}

impl TruthFile {
    /// Reads a truth file and checks its scene settings as dm-synth checks
    /// them before simulating, so no world is built from settings it would
    /// refuse (a clip without frames); errors name the file and the field.
    pub fn load(path: &std::path::Path) -> Result<Self, dm_bundle::BundleError> {
        let truth: Self = dm_bundle::read_json(path)?;
        truth
            .config
            .validate()
            .map_err(|e| dm_bundle::BundleError::new(path, "config", e.to_string()))?;
        Ok(truth)
    }
}

/// The version of a record written before versions were recorded (serde's
/// default for `truth_version` fields).
pub fn first_truth_version() -> u32 {
    1
}

impl TruthFile {
    /// Whether this version of the truth simulation made it.
    pub fn is_current(&self) -> bool {
        self.truth_version == TRUTH_VERSION
    }
}

fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

impl GroundTruth {
    pub fn truth_file(&self, config: &SynthConfig) -> TruthFile {
        TruthFile {
            truth_version: TRUTH_VERSION,
            preset: self.preset.name().into(),
            seed: config.seed,
            material: TruthMaterial {
                e_pa: median(&self.youngs_pa),
                nu: median(&self.poisson),
            },
            effect: config.effect.map(|e| TruthEffect {
                name: e.name.name().into(),
                params: e.params(self.inclusion, &self.effect_extra),
            }),
            action: config.resolved_action().name().into(),
            hands: self.hands.clone(),
            truth_particles: self.cloud.len(),
            physics: self.physics.clone(),
            config: config.clone(),
            engine: None,
            effect_displacement_m: None,
        }
    }
}

/// Per-particle truth material.
struct TruthMaterialFields {
    youngs: Vec<f64>,
    poisson: Vec<f64>,
    expert_weights: Vec<[f64; 3]>,
    /// Centre and radius of the stiff inclusion, if that effect is hidden.
    inclusion: Option<([f64; 3], f64)>,
}

/// Spatially varying (or homogeneous) truth material and the stiff
/// inclusion, if that effect is hidden.
fn truth_material(config: &SynthConfig, cloud: &ParticleCloud) -> TruthMaterialFields {
    let (e0, nu0) = config.preset.nominal_material();
    let n = cloud.len();
    let seed = splitmix(config.seed ^ 0x3a7e_41a1);
    let (mut youngs, poisson, weights) = if config.homogeneous {
        (
            vec![e0; n],
            vec![nu0; n],
            vec![HOMOGENEOUS_EXPERT_WEIGHTS; n],
        )
    } else {
        let e_field = SmoothField::new(seed, 0.08);
        let nu_field = SmoothField::new(seed ^ 1, 0.1);
        let mix_field = SmoothField::new(seed ^ 2, 0.1);
        let youngs: Vec<f64> = cloud
            .positions
            .iter()
            .map(|&p| e0 * (0.3 * e_field.at(p)).exp())
            .collect();
        let poisson = cloud
            .positions
            .iter()
            .map(|&p| (nu0 + 0.03 * nu_field.at(p)).clamp(0.05, 0.45))
            .collect();
        let weights = cloud
            .positions
            .iter()
            .map(|&p| {
                let m = mix_field.at(p);
                let l = [0.4 + 0.5 * m, 1.0 - 0.3 * m, -0.3 + 0.4 * m];
                let e = l.map(f64::exp);
                let s = e[0] + e[1] + e[2];
                e.map(|x| x / s)
            })
            .collect();
        (youngs, poisson, weights)
    };
    // Rescale so the median is exactly the nominal value the truth file reports.
    if !config.homogeneous {
        let m = median(&youngs);
        youngs.iter_mut().for_each(|e| *e *= e0 / m);
    }
    let mut inclusion = None;
    if let Some(EffectSpec {
        name: EffectName::StiffInclusion,
        magnitude,
    }) = config.effect
    {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 3);
        let centre = cloud.positions[rng.random_range(0..n)];
        let (lo, hi) = config.preset.bounds();
        let size = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
        let radius = 0.25 * size;
        for (e, p) in youngs.iter_mut().zip(&cloud.positions) {
            let d2: f64 = (0..3).map(|a| (p[a] - centre[a]).powi(2)).sum();
            if d2 < radius * radius {
                *e *= magnitude;
            }
        }
        inclusion = Some((centre, radius));
    }
    TruthMaterialFields {
        youngs,
        poisson,
        expert_weights: weights,
        inclusion,
    }
}

/// An angle in [0, 2π) drawn from `seed`.
fn seeded_angle(seed: u64) -> f64 {
    let mut rng = ChaCha8Rng::seed_from_u64(splitmix(seed));
    rng.random_range(0.0..std::f64::consts::TAU)
}

/// The axis along which `density_variation` grades the density (the
/// preset's longest extent) and which end is heavy (from the seed).
fn density_axis(preset: Preset, seed: u64) -> (usize, bool) {
    let (lo, hi) = preset.bounds();
    let axis = (0..3)
        .max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b])))
        .unwrap_or(0);
    (axis, splitmix(seed ^ 0xde05).is_multiple_of(2))
}

/// The truth particles of `config`'s scene, whichever engine moves them.
pub(crate) fn truth_cloud(config: &SynthConfig) -> ParticleCloud {
    ParticleCloud::fill(
        config.preset,
        config.truth_particles,
        splitmix(config.seed ^ 0xc10d),
    )
}

/// Gravity tilted by `tilt_deg` towards an azimuth drawn from `seed`; the
/// azimuth and the vector go into the truth file's effect parameters.
pub(crate) fn tilted_gravity(
    seed: u64,
    tilt_deg: f64,
    effect_extra: &mut BTreeMap<String, serde_json::Value>,
) -> [f64; 3] {
    let azimuth = seeded_angle(seed ^ 0x7117);
    let tilt = tilt_deg.to_radians();
    let g = 9.8;
    let gravity = [
        g * tilt.sin() * azimuth.cos(),
        g * tilt.sin() * azimuth.sin(),
        -g * tilt.cos(),
    ];
    effect_extra.insert(
        "azimuth_deg".into(),
        serde_json::json!(azimuth.to_degrees()),
    );
    effect_extra.insert("gravity".into(), serde_json::json!(gravity));
    gravity
}

/// The grid body force of an effect outside the diagnosis library, its
/// direction, point or axis drawn from the seed; what a diagnosis should
/// recover goes into the truth file's effect parameters (for `wind` its
/// world-frame unit `direction` and `magnitude_m_s2`).
pub(crate) fn body_force(
    config: &SynthConfig,
    name: EffectName,
    magnitude: f64,
    effect_extra: &mut BTreeMap<String, serde_json::Value>,
) -> ForceField {
    let azimuth = seeded_angle(config.seed ^ 0xf0ce);
    let horizontal = [azimuth.cos(), azimuth.sin(), 0.0];
    let mut field = ForceField::default();
    match name {
        EffectName::Wind => {
            field.uniform = horizontal.map(|c| c * magnitude);
            effect_extra.insert("direction".into(), serde_json::json!(horizontal));
        }
        EffectName::Attractor => {
            let (lo, hi) = config.preset.bounds();
            let centre: [f64; 3] = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]));
            field.attractor_stiffness = magnitude;
            field.attractor_point =
                std::array::from_fn(|a| centre[a] + ATTRACTOR_OFFSET_M * horizontal[a]);
            effect_extra.insert("point_m".into(), serde_json::json!(field.attractor_point));
        }
        EffectName::AnisotropicDrag => {
            let axis = (splitmix(config.seed ^ 0xa5d7) % 3) as usize;
            field.axis_drag[axis] = magnitude;
            let direction: [f64; 3] = std::array::from_fn(|a| if a == axis { 1.0 } else { 0.0 });
            effect_extra.insert("axis".into(), serde_json::json!(axis));
            effect_extra.insert("direction".into(), serde_json::json!(direction));
        }
        _ => {}
    }
    field
}

/// How far beside the object's centre an `attractor` pulls (horizontally).
const ATTRACTOR_OFFSET_M: f64 = 0.1;

/// Density factors `1 + a s` of `density_variation` at `positions`, `s`
/// running from 0 to 1 along the preset's longest axis towards the heavy
/// end; the axis and end go into the truth file's effect parameters.
pub(crate) fn density_factors(
    config: &SynthConfig,
    magnitude: f64,
    positions: &[[f64; 3]],
    effect_extra: &mut BTreeMap<String, serde_json::Value>,
) -> Vec<f64> {
    let (axis, heavy_at_max) = density_axis(config.preset, config.seed);
    let coords: Vec<f64> = positions.iter().map(|p| p[axis]).collect();
    let lo = coords.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = coords.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    effect_extra.insert("axis".into(), serde_json::json!(axis));
    effect_extra.insert("heavy_at_max".into(), serde_json::json!(heavy_at_max));
    coords
        .iter()
        .map(|c| {
            let s = (c - lo) / (hi - lo).max(1e-9);
            1.0 + magnitude * if heavy_at_max { s } else { 1.0 - s }
        })
        .collect()
}

/// Every hand's anchors per recorded frame, `lag_s` seconds late.
pub(crate) fn hand_anchor_frames(
    hands: &[HandScript],
    frames: usize,
    lag_s: f64,
) -> Vec<Vec<[f64; 3]>> {
    (0..frames)
        .map(|t| {
            hands
                .iter()
                .flat_map(|h| h.anchors_at(t as f64 / FPS - lag_s))
                .collect()
        })
        .collect()
}

/// How late the recorded hand track runs (`actuator_lag`'s magnitude).
pub(crate) fn hand_track_lag_s(config: &SynthConfig) -> f64 {
    match config.effect {
        Some(EffectSpec {
            name: EffectName::ActuatorLag,
            magnitude,
        }) => magnitude,
        _ => 0.0,
    }
}

/// The truth simulation's physics before the effect: a cubic domain holding
/// the object, every hand anchor over the clip and `room_m` around the
/// object along the floor ([`WALL_ROOM_M`]), its grid as fine as
/// [`TRUTH_GRID`] cells over the domain without the room.
pub(crate) fn truth_physics<'a>(
    preset: Preset,
    anchors: impl Iterator<Item = &'a [f64; 3]>,
    room_m: f64,
) -> PhysicsConfig {
    let (mut lo, mut hi) = preset.bounds();
    lo[2] = lo[2].min(-0.02);
    for p in anchors {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a] - 0.05);
            hi[a] = hi[a].max(p[a] + 0.05);
        }
    }
    let up = [0.0, 0.0, 1.0];
    let extent = |lo: [f64; 3], hi: [f64; 3]| (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
    let extent_without_room = extent(lo, hi);
    let (object_lo, object_hi) = preset.bounds();
    for a in 0..2 {
        lo[a] = lo[a].min(object_lo[a] - room_m);
        hi[a] = hi[a].max(object_hi[a] + room_m);
    }
    let grid = (TRUTH_GRID as f64 * extent(lo, hi) / extent_without_room - 1e-9).ceil() as usize;
    let mut physics = match preset {
        Preset::Toy => PhysicsConfig::volumetric([0.0; 3], 1.0, up),
        _ => PhysicsConfig::thin_object([0.0; 3], 1.0, up),
    };
    physics.grid_res = grid;
    physics.dt = 1.0 / FPS / TRUTH_SUBSTEPS_PER_FRAME as f64;
    physics.substeps_per_frame = TRUTH_SUBSTEPS_PER_FRAME;
    physics.cfl = Some(TRUTH_CFL);
    let (origin, size) =
        cube_domain_containing(lo, hi, grid, physics.wall_cells, physics.position_clip);
    physics.domain_origin = origin;
    physics.domain_size = size;
    if let Some(floor) = physics.floor.as_mut() {
        floor.margin = 0.0;
    }
    physics
}

/// The truth world before its settling frames, and what the truth file records of it.
struct TruthSetup {
    world: World<f32>,
    physics: PhysicsConfig,
    effect_extra: BTreeMap<String, serde_json::Value>,
    cloud: ParticleCloud,
    material: TruthMaterialFields,
}

/// The truth world of `config` (material, hidden effect, grip) in a domain
/// around the object, the hands' `anchor_frames` and `extra_points`.
fn truth_setup(
    config: &SynthConfig,
    anchor_frames: &[Vec<[f64; 3]>],
    extra_points: &[[f64; 3]],
) -> Result<TruthSetup, SynthError> {
    let cloud = truth_cloud(config);
    let material = truth_material(config, &cloud);
    let mut physics = truth_physics(
        config.preset,
        anchor_frames.iter().flatten().chain(extra_points),
        WALL_ROOM_M,
    );
    let mut effect_extra = BTreeMap::new();
    match config.effect {
        Some(EffectSpec {
            name: EffectName::AirDrag,
            magnitude,
        }) => physics.effects.air_drag_linear = magnitude,
        Some(EffectSpec {
            name: EffectName::FloorFriction,
            magnitude,
        }) => physics.effects.floor_friction = magnitude,
        Some(EffectSpec {
            name: EffectName::Plasticity,
            magnitude,
        }) => physics.effects.plastic_yield = Some(magnitude),
        Some(EffectSpec {
            name: EffectName::AirDragQuadratic,
            magnitude,
        }) => physics.effects.air_drag_quadratic = magnitude,
        Some(EffectSpec {
            name: EffectName::ViscousDamping,
            magnitude,
        }) => physics.effects.viscosity = magnitude,
        Some(EffectSpec {
            name: EffectName::GroundTilt,
            magnitude,
        }) => physics.gravity = tilted_gravity(config.seed, magnitude, &mut effect_extra),
        Some(EffectSpec {
            name: name @ (EffectName::Wind | EffectName::Attractor | EffectName::AnisotropicDrag),
            magnitude,
        }) => physics.effects.force_field = body_force(config, name, magnitude, &mut effect_extra),
        _ => {}
    }
    let density_factors = match config.effect {
        Some(EffectSpec {
            name: EffectName::DensityVariation,
            magnitude,
        }) => Some(density_factors(
            config,
            magnitude,
            &cloud.positions,
            &mut effect_extra,
        )),
        _ => None,
    };
    let grip = TRUTH_GRIP;
    let mut world = World::new(
        physics.clone(),
        &cloud.positions,
        cloud.particle_volume(),
        ParticleMaterial::<f32>::from_fields(
            &material.youngs,
            &material.poisson,
            &material.expert_weights,
        ),
        grip,
    )?;
    if let Some(factors) = &density_factors {
        world.set_density_factors(factors)?;
    }

    Ok(TruthSetup {
        world,
        physics,
        effect_extra,
        cloud,
        material,
    })
}

/// The truth world of a dm-mpm truth file at the clip's first frame (the
/// object settled, no hand holding it), in a domain that also holds
/// `extra_points`: a world the scene's model did not fit, to carry other
/// hand motions out in (dm-plan's plant). Its hands are the caller's.
/// Also which of its particles are surface particles.
pub fn plant_world(
    truth: &TruthFile,
    extra_points: &[[f64; 3]],
) -> Result<(World<f32>, Vec<bool>), SynthError> {
    if truth.engine.is_some() {
        return Err(SynthError::InvalidOption {
            option: "engine".into(),
            problem: "the truth file comes from MuJoCo; only dm-mpm truth worlds can be rebuilt as plants".into(),
        });
    }
    let anchor_frames = clip_hand_anchors(truth);
    let TruthSetup {
        mut world, cloud, ..
    } = truth_setup(&truth.config, &anchor_frames, extra_points)?;
    let idle = vec![false; anchor_frames[0].len()];
    for _ in 0..SETTLE_FRAMES {
        world.step_frame(&anchor_frames[0], &anchor_frames[0], &idle)?;
    }
    Ok((world, cloud.on_surface))
}

/// The true hands' anchors at every frame of the clip (without the lag a
/// recorded track may have): what a plant replays to reach a frame of the
/// clip.
pub fn clip_hand_anchors(truth: &TruthFile) -> Vec<Vec<[f64; 3]>> {
    hand_anchor_frames(&truth.hands, truth.config.frames, 0.0)
}

/// Runs the truth simulation for `config`.
pub fn simulate_truth(
    config: &SynthConfig,
    progress: Progress<'_>,
) -> Result<GroundTruth, SynthError> {
    let preset = config.preset;
    let action = config.resolved_action();
    let duration = config.frames as f64 / FPS;
    let hands = plan(preset, action, config.two_hands, duration);
    let anchor_frames = hand_anchor_frames(&hands, config.frames, 0.0);
    let TruthSetup {
        mut world,
        physics,
        effect_extra,
        cloud,
        material:
            TruthMaterialFields {
                youngs,
                poisson,
                inclusion,
                ..
            },
    } = truth_setup(config, &anchor_frames, &[])?;
    let total = SETTLE_FRAMES + config.frames;
    let idle = vec![false; anchor_frames[0].len()];
    for s in 0..SETTLE_FRAMES {
        world.step_frame(&anchor_frames[0], &anchor_frames[0], &idle)?;
        progress("truth simulation", s + 1, total);
    }
    let active = vec![true; anchor_frames[0].len()];
    let as_f32 = |ps: Vec<[f64; 3]>| ps.iter().map(|p| p.map(|c| c as f32)).collect::<Vec<_>>();
    let mut frames = vec![as_f32(world.positions())];
    for t in 0..config.frames - 1 {
        world.step_frame(&anchor_frames[t], &anchor_frames[t + 1], &active)?;
        frames.push(as_f32(world.positions()));
        progress("truth simulation", SETTLE_FRAMES + t + 2, total);
    }
    let recorded_anchors = hand_anchor_frames(&hands, config.frames, hand_track_lag_s(config));
    Ok(GroundTruth {
        preset,
        hands,
        cloud,
        frames,
        anchors: anchor_frames,
        recorded_anchors,
        effect_extra,
        youngs_pa: youngs,
        poisson,
        inclusion,
        physics,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::actions::Action;

    /// dm-plan's plant is the scene's truth world: rebuilt from the truth
    /// file, it starts where the clip's first frame is, bit for bit.
    #[test]
    fn a_plant_world_starts_at_the_clips_first_frame() {
        let config = SynthConfig::tiny(Preset::Rope, 3);
        let truth = simulate_truth(&config, &mut |_, _, _| {}).expect("truth");
        let (world, surface) = plant_world(&truth.truth_file(&config), &[]).expect("plant");
        assert_eq!(surface.len(), world.particle_count());
        let start: Vec<[f32; 3]> = world
            .positions()
            .iter()
            .map(|p| p.map(|c| c as f32))
            .collect();
        assert_eq!(start, truth.frames[0]);
    }

    /// Replaying the clip's hands in the plant world reaches the clip's
    /// frames, bit for bit.
    #[test]
    fn a_plant_world_replays_the_clip() {
        let config = SynthConfig::tiny(Preset::Cloth, 5);
        let truth = simulate_truth(&config, &mut |_, _, _| {}).expect("truth");
        let (mut world, _) = plant_world(&truth.truth_file(&config), &[]).expect("plant");
        let hands = clip_hand_anchors(&truth.truth_file(&config));
        assert_eq!(hands.len(), config.frames);
        let active = vec![true; hands[0].len()];
        for t in 0..config.frames - 1 {
            world
                .step_frame(&hands[t], &hands[t + 1], &active)
                .expect("step");
        }
        let last: Vec<[f32; 3]> = world
            .positions()
            .iter()
            .map(|p| p.map(|c| c as f32))
            .collect();
        assert_eq!(&last, truth.frames.last().expect("frames"));
    }

    /// The truth's slip walls held a rope's ends one cell away for whole
    /// clips (seed 1026); every preset and action now keeps its rest shape
    /// [`WALL_ROOM_M`] inside the walls along the floor, on cells no
    /// coarser than the domain without the room gave.
    #[test]
    fn truth_walls_leave_room_around_the_object() {
        for preset in [Preset::Rope, Preset::Cloth, Preset::Toy] {
            for action in Action::ALL {
                let hands = plan(preset, action, false, 1.2);
                let anchors: Vec<[f64; 3]> = (0..36)
                    .flat_map(|t| hands.iter().flat_map(move |h| h.anchors_at(t as f64 / FPS)))
                    .collect();
                let physics = truth_physics(preset, anchors.iter(), WALL_ROOM_M);
                let without_room = truth_physics(preset, anchors.iter(), 0.0);
                let dx = physics.dx();
                let wall = physics.wall_cells as f64 * dx;
                let (lo, hi) = preset.bounds();
                for a in 0..2 {
                    let low_wall = physics.domain_origin[a] + wall;
                    let high_wall = physics.domain_origin[a] + physics.domain_size - wall;
                    let room = (lo[a] - low_wall).min(high_wall - hi[a]);
                    assert!(
                        room >= WALL_ROOM_M,
                        "{preset:?} {action:?}: {room:.3} m between the object and a wall on axis {a}"
                    );
                }
                assert_eq!(without_room.grid_res, TRUTH_GRID);
                assert!(
                    dx <= without_room.dx() * (1.0 + 1e-12),
                    "{preset:?} {action:?}: cells of {dx:.4} m, {:.4} m without the room",
                    without_room.dx()
                );
            }
        }
    }
}
