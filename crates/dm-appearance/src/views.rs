//! The cameras of a render: a bundle camera (`train:I`), a novel view in
//! the widest gap between the bundle's cameras, or an orbit.
//!
//! Novel and orbit cameras circle the up axis through the centre of the
//! first-frame particles, at the bundle cameras' mean distance and height
//! (orbit: camera 0's), look at that centre, and keep camera 0's
//! intrinsics, so renders compare with the training images.

use std::str::FromStr;

use dm_view::Camera;
use nalgebra::{Point3, Vector3};

use crate::AppearanceError;

/// Which camera(s) to render from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ViewChoice {
    /// Bundle camera `I`.
    Train(usize),
    /// One unseen viewpoint (the middle of the widest azimuth gap).
    Novel,
    /// A full circle over the rendered frames.
    Orbit,
}

impl FromStr for ViewChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "novel" => Ok(Self::Novel),
            "orbit" => Ok(Self::Orbit),
            _ => match s.strip_prefix("train:").map(str::parse::<usize>) {
                Some(Ok(i)) => Ok(Self::Train(i)),
                _ => Err(format!(
                    "`{s}` is not a view: use train:I (a bundle camera index), novel or orbit"
                )),
            },
        }
    }
}

/// Camera position relative to a centre in cylinder coordinates about `up`.
struct Placement {
    azimuth: f64,
    radius: f64,
    height: f64,
}

/// Orthonormal basis `(e0, e1)` of the plane perpendicular to `up`.
fn plane_basis(up: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let seed = if up.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e0 = (seed - up * seed.dot(up)).normalize();
    (e0, up.cross(&e0))
}

fn placement(camera: &Camera, centre: &Point3<f64>, up: &Vector3<f64>) -> Placement {
    let (e0, e1) = plane_basis(up);
    let offset = camera.center() - centre;
    let height = offset.dot(up);
    let horizontal = offset - up * height;
    Placement {
        azimuth: horizontal.dot(&e1).atan2(horizontal.dot(&e0)),
        radius: horizontal.norm(),
        height,
    }
}

/// A camera at `p` around `centre`, looking at it, with `intrinsics`'s
/// image size and focal lengths.
fn placed_camera(
    p: &Placement,
    centre: &Point3<f64>,
    up: &Vector3<f64>,
    intrinsics: &Camera,
) -> Camera {
    let (e0, e1) = plane_basis(up);
    let eye = centre + (e0 * p.azimuth.cos() + e1 * p.azimuth.sin()) * p.radius + up * p.height;
    let mut camera = Camera::look_at(eye, *centre, *up, intrinsics.width, intrinsics.height, 50.0);
    camera.fx = intrinsics.fx;
    camera.fy = intrinsics.fy;
    camera.cx = intrinsics.cx;
    camera.cy = intrinsics.cy;
    camera
}

/// Centre of the first-frame particles.
pub fn particle_centre(particles: &[[f64; 3]]) -> Point3<f64> {
    let n = particles.len().max(1) as f64;
    let mut c = Vector3::zeros();
    for p in particles {
        c += Vector3::from(*p);
    }
    Point3::from(c / n)
}

/// The camera of each rendered frame (`frames` of them) for `choice`.
pub fn cameras_for(
    choice: ViewChoice,
    bundle_cameras: &[Camera],
    centre: &Point3<f64>,
    up: [f64; 3],
    frames: usize,
) -> Result<Vec<Camera>, AppearanceError> {
    let Some(first) = bundle_cameras.first() else {
        return Err(AppearanceError::InvalidOption {
            option: "--view".into(),
            problem: "no cameras recorded for this scene".into(),
        });
    };
    let up = Vector3::from(up)
        .try_normalize(1e-12)
        .unwrap_or(Vector3::z());
    match choice {
        ViewChoice::Train(i) => match bundle_cameras.get(i) {
            Some(c) => Ok(vec![c.clone(); frames]),
            None => Err(AppearanceError::InvalidOption {
                option: "--view".into(),
                problem: format!(
                    "train:{i} does not exist; the scene has {} cameras (0..{})",
                    bundle_cameras.len(),
                    bundle_cameras.len() - 1
                ),
            }),
        },
        ViewChoice::Novel => {
            let places: Vec<Placement> = bundle_cameras
                .iter()
                .map(|c| placement(c, centre, &up))
                .collect();
            let n = places.len() as f64;
            let mut azimuths: Vec<f64> = places.iter().map(|p| p.azimuth).collect();
            azimuths.sort_by(f64::total_cmp);
            // Widest gap between consecutive azimuths, wrapping around.
            let tau = std::f64::consts::TAU;
            let mut best = (f64::NEG_INFINITY, 0.0);
            for k in 0..azimuths.len() {
                let from = azimuths[k];
                let to = if k + 1 < azimuths.len() {
                    azimuths[k + 1]
                } else {
                    azimuths[0] + tau
                };
                if to - from > best.0 {
                    best = (to - from, from + 0.5 * (to - from));
                }
            }
            let place = Placement {
                azimuth: best.1,
                radius: places.iter().map(|p| p.radius).sum::<f64>() / n,
                height: places.iter().map(|p| p.height).sum::<f64>() / n,
            };
            Ok(vec![placed_camera(&place, centre, &up, first); frames])
        }
        ViewChoice::Orbit => {
            let start = placement(first, centre, &up);
            Ok((0..frames)
                .map(|k| {
                    let place = Placement {
                        azimuth: start.azimuth
                            + std::f64::consts::TAU * k as f64 / frames.max(1) as f64,
                        ..start
                    };
                    placed_camera(&place, centre, &up, first)
                })
                .collect())
        }
    }
}

/// A recorded camera as a renderer camera; errors name `cameras[index]`.
pub fn camera_from_spec(
    spec: &dm_bundle::CameraSpec,
    index: usize,
) -> Result<Camera, AppearanceError> {
    dm_model::preview::camera_from_spec(spec).map_err(|problem| AppearanceError::InvalidOption {
        option: format!("cameras[{index}]"),
        problem,
    })
}
