use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::ViewError;

/// Points with camera-space depth at or below this (metres) are treated as behind
/// the camera.
pub const NEAR_PLANE: f64 = 1e-4;

/// Tolerance for accepting a rotation block as orthonormal in `from_matrix_4x4`;
/// loose enough for matrices round-tripped through f32 text files.
const ORTHONORMAL_TOLERANCE: f64 = 1e-5;

/// Pinhole camera with OpenCV axes (x right, y down, z forward).
///
/// `world_to_camera` maps world points into camera space; the image coordinates of a
/// camera-space point `(x, y, z)` are `(fx * x / z + cx, fy * y / z + cy)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub world_to_camera: Isometry3<f64>,
}

impl Camera {
    /// Camera at `eye` looking at `target`, with `up` projecting to image "up"
    /// (i.e. the camera's -y axis). Square pixels, principal point at the image centre,
    /// `vertical_fov_deg` is clamped to (0.001, 179.9) degrees.
    ///
    /// Degenerate inputs (eye == target, `up` parallel to the viewing direction or
    /// zero) never panic: they fall back to an arbitrary but deterministic orientation.
    pub fn look_at(
        eye: Point3<f64>,
        target: Point3<f64>,
        up: Vector3<f64>,
        width: u32,
        height: u32,
        vertical_fov_deg: f64,
    ) -> Camera {
        let up_unit = normalized_or(up, Vector3::z());
        let forward = normalized_or(target - eye, fallback_perpendicular(&up_unit));
        let right = match forward.cross(&up_unit).try_normalize(1e-12) {
            Some(right) => right,
            // Looking straight along `up`: any perpendicular is as good as another.
            None => fallback_perpendicular(&forward),
        };
        let down = forward.cross(&right);
        let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_rows(&[
            right.transpose(),
            down.transpose(),
            forward.transpose(),
        ]));
        let translation = -(rotation * eye.coords);
        let world_to_camera = Isometry3::from_parts(
            Translation3::from(translation),
            UnitQuaternion::from_rotation_matrix(&rotation),
        );

        let fov_rad = vertical_fov_deg.clamp(1e-3, 179.9).to_radians();
        let focal = 0.5 * f64::from(height) / (0.5 * fov_rad).tan();
        Camera {
            width,
            height,
            fx: focal,
            fy: focal,
            cx: 0.5 * f64::from(width),
            cy: 0.5 * f64::from(height),
            world_to_camera,
        }
    }

    /// Camera from intrinsics and a row-major 4x4 world-to-camera rigid transform.
    /// Rejects non-finite values, a bad homogeneous row, non-positive focal lengths,
    /// zero image size and rotation blocks that are not proper orthonormal rotations.
    pub fn from_matrix_4x4(
        width: u32,
        height: u32,
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        m: [[f64; 4]; 4],
    ) -> Result<Camera, ViewError> {
        if width == 0 || height == 0 {
            return Err(ViewError::InvalidIntrinsics(format!(
                "image size must be non-zero, got {width}x{height}"
            )));
        }
        if !(fx.is_finite() && fy.is_finite() && fx > 0.0 && fy > 0.0) {
            return Err(ViewError::InvalidIntrinsics(format!(
                "focal lengths must be finite and positive, got fx={fx}, fy={fy}"
            )));
        }
        if !(cx.is_finite() && cy.is_finite()) {
            return Err(ViewError::InvalidIntrinsics(format!(
                "principal point must be finite, got cx={cx}, cy={cy}"
            )));
        }
        if m.iter().flatten().any(|value| !value.is_finite()) {
            return Err(ViewError::NonFiniteMatrix);
        }
        let last_row = m[3];
        let expected_last_row = [0.0, 0.0, 0.0, 1.0];
        if last_row
            .iter()
            .zip(expected_last_row)
            .any(|(value, expected)| (value - expected).abs() > 1e-9)
        {
            return Err(ViewError::InvalidHomogeneousRow(last_row));
        }

        let rotation_block = Matrix3::from_fn(|row, col| m[row][col]);
        let max_error = (rotation_block.transpose() * rotation_block - Matrix3::identity())
            .abs()
            .max();
        if max_error > ORTHONORMAL_TOLERANCE {
            return Err(ViewError::NonOrthonormalRotation { max_error });
        }
        let determinant = rotation_block.determinant();
        if determinant <= 0.0 {
            return Err(ViewError::NotProperRotation { determinant });
        }

        let rotation =
            UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rotation_block));
        let translation = Vector3::new(m[0][3], m[1][3], m[2][3]);
        Ok(Camera {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            world_to_camera: Isometry3::from_parts(Translation3::from(translation), rotation),
        })
    }

    /// Row-major homogeneous world-to-camera matrix (`m[row][col]`).
    pub fn to_matrix_4x4(&self) -> [[f64; 4]; 4] {
        let h = self.world_to_camera.to_homogeneous();
        std::array::from_fn(|row| std::array::from_fn(|col| h[(row, col)]))
    }

    /// Intrinsic matrix `K` (row-major).
    pub fn intrinsics_3x3(&self) -> [[f64; 3]; 3] {
        [
            [self.fx, 0.0, self.cx],
            [0.0, self.fy, self.cy],
            [0.0, 0.0, 1.0],
        ]
    }

    /// Inverse of `world_to_camera`.
    pub fn camera_to_world(&self) -> Isometry3<f64> {
        self.world_to_camera.inverse()
    }

    /// Camera centre (optical centre) in world coordinates.
    pub fn center(&self) -> Point3<f64> {
        self.world_to_camera
            .inverse_transform_point(&Point3::origin())
    }

    /// Viewing direction (camera +z) in world coordinates.
    pub fn forward_world(&self) -> Vector3<f64> {
        self.world_to_camera.inverse_transform_vector(&Vector3::z())
    }

    /// World point to `(u, v, z)`: continuous image coordinates and depth along the
    /// optical axis. `None` if the point is not finite or not in front of the near
    /// plane. Points outside the image bounds are still returned.
    pub fn project(&self, p_world: &Point3<f64>) -> Option<(f64, f64, f64)> {
        let p = self.world_to_camera.transform_point(p_world);
        if !p.coords.iter().all(|c| c.is_finite()) || p.z <= NEAR_PLANE {
            return None;
        }
        let inv_z = 1.0 / p.z;
        Some((
            self.fx * p.x * inv_z + self.cx,
            self.fy * p.y * inv_z + self.cy,
            p.z,
        ))
    }

    /// World point at image coordinates `(u, v)` and optical-axis depth `depth`.
    pub fn unproject(&self, u: f64, v: f64, depth: f64) -> Point3<f64> {
        let p_camera = Point3::new(
            (u - self.cx) / self.fx * depth,
            (v - self.cy) / self.fy * depth,
            depth,
        );
        self.world_to_camera.inverse_transform_point(&p_camera)
    }

    /// Unit world-space direction of the viewing ray through image point `(u, v)`.
    pub fn ray_direction_world(&self, u: f64, v: f64) -> Vector3<f64> {
        let d_camera = Vector3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0);
        self.world_to_camera
            .inverse_transform_vector(&d_camera)
            .normalize()
    }

    /// Whether continuous image coordinates fall inside the image.
    pub fn contains_pixel(&self, u: f64, v: f64) -> bool {
        u >= 0.0 && v >= 0.0 && u < f64::from(self.width) && v < f64::from(self.height)
    }
}

/// `count` cameras evenly spaced in azimuth on a circle around `target`, all at
/// distance `radius` from it and looking at it, raised by `elevation_deg` above the
/// plane perpendicular to `up` (any direction, not only +z).
///
/// Azimuth 0 points along the world axis least aligned with `up` (projected into the
/// orbit plane; +x for `up` = +z) and increases counter-clockwise seen from above.
pub fn orbit_cameras(
    target: Point3<f64>,
    radius: f64,
    elevation_deg: f64,
    count: usize,
    start_azimuth_deg: f64,
    up: Vector3<f64>,
    width: u32,
    height: u32,
    fov_deg: f64,
) -> Vec<Camera> {
    let up_unit = normalized_or(up, Vector3::z());
    let azimuth_zero = fallback_perpendicular(&up_unit);
    let azimuth_ninety = up_unit.cross(&azimuth_zero);
    let elevation = elevation_deg.to_radians();
    (0..count)
        .map(|index| {
            let azimuth = (start_azimuth_deg + 360.0 * index as f64 / count as f64).to_radians();
            let horizontal = azimuth_zero * azimuth.cos() + azimuth_ninety * azimuth.sin();
            let offset = (horizontal * elevation.cos() + up_unit * elevation.sin()) * radius;
            Camera::look_at(target + offset, target, up_unit, width, height, fov_deg)
        })
        .collect()
}

fn normalized_or(v: Vector3<f64>, fallback: Vector3<f64>) -> Vector3<f64> {
    if v.iter().all(|c| c.is_finite()) {
        v.try_normalize(1e-12).unwrap_or(fallback)
    } else {
        fallback
    }
}

/// Deterministic unit vector perpendicular to `axis` (unit): the world axis least
/// aligned with it, with the `axis` component removed.
pub(crate) fn fallback_perpendicular(axis: &Vector3<f64>) -> Vector3<f64> {
    let candidates = [Vector3::x(), Vector3::y(), Vector3::z()];
    let mut best = candidates[0];
    for candidate in &candidates[1..] {
        if candidate.dot(axis).abs() < best.dot(axis).abs() - 1e-12 {
            best = *candidate;
        }
    }
    (best - axis * best.dot(axis))
        .try_normalize(1e-12)
        .unwrap_or(Vector3::x())
}
