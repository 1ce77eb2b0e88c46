//! What the page needs to draw a model: its three cameras (main view and
//! two novel views, one orbit around the object), the sprites (one per
//! Gaussian splat, or per particle when the model has no splats) with
//! their colour, size and opacity, and the per-sprite fields for the
//! expert-map and Young's-modulus colourings.

use dm_mpm::PhysicsConfig;
use dm_mpm::neighbors::PointIndex;
use dm_splat::Gaussians;
use dm_view::{Camera, orbit_cameras};
use nalgebra::{Point3, Vector3};
use serde::Serialize;

use crate::PlayError;
use crate::session::{Body, bounds};

/// Page default resolution of the main view (the novel views are half).
pub const MAIN_VIEW_SIZE: [u32; 2] = [640, 480];
/// Vertical field of view of every view, degrees.
pub const FOV_DEG: f64 = 40.0;
/// Azimuth of the main view and of the two novel views (degrees, around
/// the up axis through the object's centre).
pub const VIEW_AZIMUTHS_DEG: [f64; 3] = [-90.0, 30.0, 150.0];
/// Elevation of every view above the object's centre, degrees.
pub const VIEW_ELEVATION_DEG: f64 = 25.0;

/// Static geometry of the playground's views.
#[derive(Clone, Debug)]
pub struct SceneView {
    pub up: [f64; 3],
    pub centre: [f64; 3],
    /// Largest extent of the first-frame particles, metres.
    pub extent: f64,
    /// Median nearest-neighbour distance of the first-frame particles.
    pub particle_spacing: f64,
    /// Where hands may go: the simulation domain inside its walls.
    pub hand_box: ([f64; 3], [f64; 3]),
    pub floor_height: f64,
    /// Main, novel 1, novel 2 (the main view at [`MAIN_VIEW_SIZE`]).
    pub cameras: Vec<Camera>,
}

impl SceneView {
    pub fn new(particles: &[[f64; 3]], physics: &PhysicsConfig) -> Result<Self, PlayError> {
        if particles.is_empty() {
            return Err(PlayError::InvalidModel(
                "model.json has no particles".into(),
            ));
        }
        let (lo, hi) = bounds(particles);
        let centre = [0, 1, 2].map(|a| 0.5 * (lo[a] + hi[a]));
        let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max).max(1e-3);
        let up = physics.floor.as_ref().map_or([0.0, 0.0, 1.0], |f| f.up);
        let index = PointIndex::new(particles);
        let mut nn: Vec<f64> = particles
            .iter()
            .step_by((particles.len() / 1000).max(1))
            .filter_map(|p| index.nearest(p, 2).get(1).map(|n| n.1))
            .collect();
        nn.sort_by(f64::total_cmp);
        let particle_spacing = nn.get(nn.len() / 2).copied().unwrap_or(0.005).max(1e-4);
        let margin = (physics.wall_cells as f64 + 1.0) * physics.dx();
        let hand_box = (
            physics.domain_origin.map(|o| o + margin),
            physics
                .domain_origin
                .map(|o| o + physics.domain_size - margin),
        );
        // The object spans about 40 % of the view: room for the hands to
        // pull it an object size away without leaving the frame.
        let radius = 0.5 * extent / (0.5 * FOV_DEG.to_radians()).tan() * 2.4;
        let target = Point3::from(centre);
        let up_v = Vector3::from(up);
        let cameras = VIEW_AZIMUTHS_DEG
            .iter()
            .enumerate()
            .flat_map(|(k, &azimuth)| {
                let scale = if k == 0 { 1 } else { 2 };
                orbit_cameras(
                    target,
                    radius,
                    VIEW_ELEVATION_DEG,
                    1,
                    azimuth,
                    up_v,
                    MAIN_VIEW_SIZE[0] / scale,
                    MAIN_VIEW_SIZE[1] / scale,
                    FOV_DEG,
                )
            })
            .collect();
        Ok(Self {
            up,
            centre,
            extent,
            particle_spacing,
            hand_box,
            floor_height: physics.floor.as_ref().map_or(0.0, |f| f.height),
            cameras,
        })
    }

    /// The main camera's right direction in world coordinates (hands
    /// start left and right of the object along it).
    pub fn main_right(&self) -> [f64; 3] {
        let r = self.cameras[0]
            .camera_to_world()
            .transform_vector(&Vector3::x());
        [r.x, r.y, r.z]
    }
}

/// Draws sprites as the page does (a depth-tested disc per sprite, its
/// radius and degree-0 colour, no blending) over the studio floor, on the
/// CPU: the headless counterpart of the page's WebGL draw, for
/// `dm-bench play` and snapshots. `positions` is flat xyz, one per sprite.
pub fn draw_sprites(
    camera: &Camera,
    positions: &[f32],
    sprites: &Sprites,
    view: &SceneView,
) -> dm_view::Frame {
    let splats: Vec<dm_view::Splat> = positions
        .chunks_exact(3)
        .zip(sprites.colors.chunks_exact(3))
        .zip(&sprites.radii)
        .map(|((p, c), &radius)| dm_view::Splat {
            position: [p[0], p[1], p[2]],
            radius,
            color: [c[0], c[1], c[2]],
            label: 1,
        })
        .collect();
    let options = dm_view::RenderOptions::studio(view.up, view.floor_height);
    dm_view::render(camera, &splats, &options)
}

/// A camera as the page uses it (OpenCV axes: x right, y down, z forward).
#[derive(Clone, Debug, Serialize)]
pub struct PageCamera {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// Row-major 4×4 world → camera.
    pub world_to_camera: [[f64; 4]; 4],
}

impl From<&Camera> for PageCamera {
    fn from(c: &Camera) -> Self {
        Self {
            width: c.width,
            height: c.height,
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            world_to_camera: c.to_matrix_4x4(),
        }
    }
}

/// What the page draws per sprite, fixed for a session.
#[derive(Clone, Debug, Serialize)]
pub struct Sprites {
    /// `"gaussian_splats"` or `"particles"`.
    pub kind: String,
    pub count: usize,
    /// Flat RGB in [0, 1].
    pub colors: Vec<f32>,
    /// World radius of each sprite (metres): 2σ of the splat's mean scale,
    /// or the particle splat radius.
    pub radii: Vec<f32>,
    pub opacities: Vec<f32>,
    /// The first-frame (simulated) particle each sprite sits nearest to (its expert
    /// and Young's-modulus colours are that particle's).
    pub particle: Vec<u32>,
}

impl Sprites {
    /// One sprite per particle, coloured by the model's particle colours.
    pub fn particles(body: &Body) -> Self {
        let n = body.particles.len();
        Self {
            kind: "particles".into(),
            count: n,
            colors: body.colors.iter().flatten().copied().collect(),
            radii: vec![body.splat_radius; n],
            opacities: vec![1.0; n],
            particle: (0..n as u32).collect(),
        }
    }

    /// One sprite per Gaussian (isotropic: the mean of its three scales).
    pub fn splats(body: &Body, gaussians: &Gaussians<f32>) -> Self {
        let index = PointIndex::new(&body.particles);
        let particle = gaussians
            .means
            .iter()
            .map(|m| {
                let q = [m.x as f64, m.y as f64, m.z as f64];
                index.nearest(&q, 1).first().map_or(0, |n| n.0 as u32)
            })
            .collect();
        Self {
            kind: "gaussian_splats".into(),
            count: gaussians.len(),
            colors: gaussians
                .colors
                .iter()
                .flat_map(|c| [c.x, c.y, c.z].map(|v| v.clamp(0.0, 1.0)))
                .collect(),
            radii: gaussians
                .log_scales
                .iter()
                .map(|s| 2.0 * ((s.x + s.y + s.z) / 3.0).exp())
                .collect(),
            opacities: (0..gaussians.len()).map(|i| gaussians.opacity(i)).collect(),
            particle,
        }
    }
}
