use dm_view::{Camera, ViewError, orbit_cameras};
use nalgebra::{Point3, Vector3};

fn assert_close(a: f64, b: f64, tol: f64, what: &str) {
    assert!((a - b).abs() <= tol, "{what}: {a} vs {b}");
}

#[test]
fn project_unproject_round_trip() {
    let camera = Camera::look_at(
        Point3::new(1.5, -2.0, 1.2),
        Point3::new(0.1, 0.2, 0.3),
        Vector3::z(),
        640,
        480,
        55.0,
    );
    for p in [
        Point3::new(0.0, 0.0, 0.0),
        Point3::new(0.3, 0.4, 0.5),
        Point3::new(-0.2, 0.5, 0.1),
    ] {
        let (u, v, z) = camera.project(&p).expect("point in front of camera");
        let back = camera.unproject(u, v, z);
        assert!((back - p).norm() < 1e-9, "{p} -> {back}");
    }
}

#[test]
fn project_rejects_points_behind_camera() {
    let camera = Camera::look_at(
        Point3::origin(),
        Point3::new(0.0, 1.0, 0.0),
        Vector3::z(),
        64,
        48,
        60.0,
    );
    assert!(camera.project(&Point3::new(0.0, -1.0, 0.0)).is_none());
    assert!(camera.project(&Point3::new(f64::NAN, 1.0, 0.0)).is_none());
    assert!(camera.project(&Point3::new(0.0, 1.0, 0.0)).is_some());
}

#[test]
fn look_at_places_target_at_image_centre_with_opencv_axes() {
    let eye = Point3::new(0.0, -3.0, 1.0);
    let target = Point3::new(0.0, 0.0, 0.5);
    let camera = Camera::look_at(eye, target, Vector3::z(), 320, 240, 60.0);
    let (u, v, z) = camera.project(&target).expect("target visible");
    assert_close(u, 160.0, 1e-9, "u");
    assert_close(v, 120.0, 1e-9, "v");
    assert_close(z, (target - eye).norm(), 1e-9, "z");
    assert!((camera.center() - eye).norm() < 1e-12);

    // World up projects upwards (smaller v), world +x (right when looking along +y) to
    // larger u.
    let (_, v_above, _) = camera
        .project(&(target + Vector3::z() * 0.1))
        .expect("visible");
    let (u_right, _, _) = camera
        .project(&(target + Vector3::x() * 0.1))
        .expect("visible");
    assert!(v_above < v);
    assert!(u_right > u);

    // Vertical field of view: a point at the top edge is fov/2 off axis.
    let half_fov = 30f64.to_radians();
    assert_close(camera.fy, 120.0 / half_fov.tan(), 1e-9, "fy");
}

#[test]
fn look_at_degenerate_up_does_not_panic() {
    let camera = Camera::look_at(
        Point3::new(0.0, 0.0, 2.0),
        Point3::origin(),
        Vector3::z(),
        32,
        32,
        60.0,
    );
    let (u, v, z) = camera.project(&Point3::origin()).expect("visible");
    assert_close(u, 16.0, 1e-9, "u");
    assert_close(v, 16.0, 1e-9, "v");
    assert_close(z, 2.0, 1e-9, "z");
}

#[test]
fn orbit_cameras_look_at_target_from_radius() {
    let target = Point3::new(0.2, -0.1, 0.4);
    for up in [Vector3::z(), Vector3::y(), Vector3::new(1.0, 1.0, 0.5)] {
        let cameras = orbit_cameras(target, 1.7, 25.0, 5, 10.0, up, 320, 240, 50.0);
        assert_eq!(cameras.len(), 5);
        let up_unit = up.normalize();
        for camera in &cameras {
            let (u, v, _) = camera.project(&target).expect("target visible");
            assert_close(u, 160.0, 1e-9, "u");
            assert_close(v, 120.0, 1e-9, "v");
            let offset = camera.center() - target;
            assert_close(offset.norm(), 1.7, 1e-9, "radius");
            // Elevation above the plane perpendicular to up.
            let elevation = (offset.dot(&up_unit) / offset.norm()).asin().to_degrees();
            assert_close(elevation, 25.0, 1e-9, "elevation");
        }
        // Evenly spaced: consecutive horizontal directions are 72 degrees apart.
        let horizontal: Vec<Vector3<f64>> = cameras
            .iter()
            .map(|c| {
                let o = c.center() - target;
                (o - up_unit * o.dot(&up_unit)).normalize()
            })
            .collect();
        for pair in horizontal.windows(2) {
            let angle = pair[0].dot(&pair[1]).clamp(-1.0, 1.0).acos().to_degrees();
            assert_close(angle, 72.0, 1e-9, "azimuth spacing");
        }
    }
}

#[test]
fn matrix_round_trip() {
    let camera = Camera::look_at(
        Point3::new(1.0, 2.0, 3.0),
        Point3::origin(),
        Vector3::z(),
        640,
        480,
        45.0,
    );
    let m = camera.to_matrix_4x4();
    let rebuilt = Camera::from_matrix_4x4(640, 480, camera.fx, camera.fy, camera.cx, camera.cy, m)
        .expect("valid matrix");
    let p = Point3::new(0.3, -0.2, 0.1);
    let (a, b) = (
        camera.project(&p).expect("visible"),
        rebuilt.project(&p).expect("visible"),
    );
    assert_close(a.0, b.0, 1e-9, "u");
    assert_close(a.1, b.1, 1e-9, "v");
    assert_close(a.2, b.2, 1e-12, "z");
}

#[test]
fn from_matrix_rejects_invalid_input() {
    let camera = Camera::look_at(
        Point3::new(1.0, 2.0, 3.0),
        Point3::origin(),
        Vector3::z(),
        64,
        48,
        45.0,
    );
    let good = camera.to_matrix_4x4();
    let build = |m| Camera::from_matrix_4x4(64, 48, 50.0, 50.0, 32.0, 24.0, m);

    let mut scaled = good;
    for row in scaled.iter_mut().take(3) {
        for value in row.iter_mut().take(3) {
            *value *= 1.1;
        }
    }
    assert!(matches!(
        build(scaled),
        Err(ViewError::NonOrthonormalRotation { .. })
    ));

    let mut reflected = good;
    for value in reflected[0].iter_mut().take(3) {
        *value = -*value;
    }
    assert!(matches!(
        build(reflected),
        Err(ViewError::NotProperRotation { .. })
    ));

    let mut bad_row = good;
    bad_row[3][0] = 0.5;
    assert!(matches!(
        build(bad_row),
        Err(ViewError::InvalidHomogeneousRow(_))
    ));

    let mut nan = good;
    nan[1][3] = f64::NAN;
    assert_eq!(build(nan), Err(ViewError::NonFiniteMatrix));

    assert!(matches!(
        Camera::from_matrix_4x4(64, 48, -1.0, 50.0, 32.0, 24.0, good),
        Err(ViewError::InvalidIntrinsics(_))
    ));
    assert!(build(good).is_ok());
}
