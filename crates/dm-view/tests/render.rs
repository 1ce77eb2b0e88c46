use dm_view::{Camera, FloorPlane, RenderOptions, Splat, render};
use nalgebra::{Point3, Vector3};

/// Camera at the origin looking along world +y with z up; odd size so the principal
/// point is a pixel centre.
fn camera() -> Camera {
    Camera::look_at(
        Point3::origin(),
        Point3::new(0.0, 1.0, 0.0),
        Vector3::z(),
        65,
        49,
        60.0,
    )
}

fn splat(position: [f32; 3], radius: f32, label: u8) -> Splat {
    Splat {
        position,
        radius,
        color: [0.8, 0.4, 0.2],
        label,
    }
}

fn center_index(camera: &Camera) -> usize {
    (camera.height / 2 * camera.width + camera.width / 2) as usize
}

#[test]
fn nearer_splat_wins_regardless_of_order() {
    let camera = camera();
    let near = splat([0.0, 1.0, 0.0], 0.05, 1);
    let far = splat([0.0, 2.0, 0.0], 0.2, 2);
    let options = RenderOptions::default();
    let center = center_index(&camera);

    let frame_a = render(&camera, &[near, far], &options);
    assert_eq!(frame_a.label[center], 1);
    assert_eq!(frame_a.splat_index[center], 0);

    let frame_b = render(&camera, &[far, near], &options);
    assert_eq!(frame_b.label[center], 1);
    assert_eq!(frame_b.splat_index[center], 1);
    assert_eq!(frame_a.depth, frame_b.depth);
    assert_eq!(frame_a.rgb, frame_b.rgb);
    assert_eq!(frame_a.label, frame_b.label);

    // The far splat is bigger on screen, so it still shows around the near one.
    assert!(frame_a.label.contains(&2));
}

#[test]
fn equal_depth_tie_goes_to_lower_index() {
    let camera = camera();
    let a = splat([0.0, 1.0, 0.0], 0.05, 1);
    let b = splat([0.0, 1.0, 0.0], 0.05, 2);
    let frame = render(&camera, &[a, b], &RenderOptions::default());
    assert!(frame.label.iter().all(|&l| l != 2));
    assert!(frame.splat_index.iter().all(|&i| i == 0 || i == u32::MAX));
}

#[test]
fn depth_at_sphere_centre_is_front_surface() {
    let camera = camera();
    let frame = render(
        &camera,
        &[splat([0.0, 1.5, 0.0], 0.1, 3)],
        &RenderOptions::default(),
    );
    let depth = frame.depth[center_index(&camera)];
    assert!((depth - 1.4).abs() < 1e-5, "depth {depth}");
    // Depth grows towards the rim, as on a sphere.
    let off_centre = frame.depth[center_index(&camera) + 2];
    assert!(off_centre > depth && off_centre < 1.5, "{off_centre}");
}

#[test]
fn labels_masks_and_empty_pixels() {
    let camera = camera();
    let splats = [
        splat([-0.2, 1.0, 0.0], 0.05, 1),
        splat([0.2, 1.0, 0.0], 0.05, 7),
    ];
    let options = RenderOptions::default();
    let frame = render(&camera, &splats, &options);

    let (u1, v1, _) = camera
        .project(&Point3::new(-0.2, 1.0, 0.0))
        .expect("visible");
    let (u7, v7, _) = camera
        .project(&Point3::new(0.2, 1.0, 0.0))
        .expect("visible");
    let mask1 = frame.mask(1);
    let mask7 = frame.mask(7);
    let mask0 = frame.mask(0);
    assert_eq!(mask1.get_pixel(u1 as u32, v1 as u32).0[0], 255);
    assert_eq!(mask1.get_pixel(u7 as u32, v7 as u32).0[0], 0);
    assert_eq!(mask7.get_pixel(u7 as u32, v7 as u32).0[0], 255);
    assert_eq!(mask0.get_pixel(0, 0).0[0], 255);

    // Every pixel belongs to exactly one label mask.
    for i in 0..frame.label.len() {
        let owners = [&mask0, &mask1, &mask7]
            .iter()
            .filter(|m| m.as_raw()[i] == 255)
            .count();
        assert_eq!(owners, 1);
    }

    // Background pixels: background colour, infinite depth, no splat.
    assert_eq!(frame.rgb[0], options.background);
    assert_eq!(frame.depth[0], f32::INFINITY);
    assert_eq!(frame.splat_index[0], u32::MAX);
    assert_eq!(frame.visible_splats(3), vec![true, true, false]);

    let rgb8 = frame.to_rgb8();
    assert_eq!(rgb8.dimensions(), (camera.width, camera.height));

    // Visibility: the front surface point of splat 0 is visible, a point behind it on
    // the same viewing ray is not.
    let front = Point3::new(-0.2, 0.95, 0.0);
    assert!(frame.is_visible(&camera, &front, 0.01));
    assert!(!frame.is_visible(&camera, &Point3::new(-0.3, 1.5, 0.0), 0.01));
    assert!(frame.is_unoccluded(&camera, &Point3::new(0.0, 1.0, 0.1), 0.01));
    assert!(!frame.is_unoccluded(&camera, &Point3::new(-0.3, 1.5, 0.0), 0.01));
}

#[test]
fn lit_side_is_brighter() {
    let camera = camera();
    let options = RenderOptions {
        light_dir_world: [-1.0, 0.0, 0.0],
        ..RenderOptions::default()
    };
    let frame = render(&camera, &[splat([0.0, 1.0, 0.0], 0.2, 1)], &options);
    let center = center_index(&camera);
    // Light from world -x = image left.
    let left = frame.rgb[center - 5][0];
    let right = frame.rgb[center + 5][0];
    assert!(left > right, "{left} vs {right}");
}

#[test]
fn floor_depth_matches_ray_plane_intersection() {
    let camera = Camera::look_at(
        Point3::new(0.3, -2.0, 1.0),
        Point3::new(0.0, 0.0, 0.0),
        Vector3::z(),
        80,
        60,
        70.0,
    );
    let floor = FloorPlane {
        point: [0.0, 0.0, -0.1],
        normal: [0.0, 0.0, 1.0],
        checker_size_m: 0.1,
        color_a: [0.9, 0.9, 0.9],
        color_b: [0.2, 0.2, 0.2],
    };
    let options = RenderOptions {
        floor: Some(floor),
        ..RenderOptions::default()
    };
    let frame = render(&camera, &[], &options);
    let origin = camera.center();
    let mut hits = 0;
    for y in 0..camera.height {
        for x in 0..camera.width {
            let (u, v) = (f64::from(x) + 0.5, f64::from(y) + 0.5);
            let direction = camera.ray_direction_world(u, v);
            let t = (-0.1 - origin.z) / direction.z;
            let i = (y * camera.width + x) as usize;
            assert_eq!(frame.label[i], 0);
            if t > 0.0 {
                let hit = origin + direction * t;
                let expected_depth = camera.project(&hit).expect("in front").2;
                let depth = f64::from(frame.depth[i]);
                assert!(
                    (depth - expected_depth).abs() < 1e-5 * expected_depth,
                    "{depth} vs {expected_depth}"
                );
                assert_ne!(frame.rgb[i], options.background);
                hits += 1;
            } else {
                assert_eq!(frame.depth[i], f32::INFINITY);
                assert_eq!(frame.rgb[i], options.background);
            }
        }
    }
    assert!(hits > 100 && hits < (camera.width * camera.height) as usize);

    // Both checker colours appear.
    let colours: std::collections::BTreeSet<[u8; 3]> =
        frame.to_rgb8().pixels().map(|p| p.0).collect();
    assert!(colours.len() >= 3, "{colours:?}");
}

#[test]
fn floor_occludes_splats_below_it() {
    let camera = Camera::look_at(
        Point3::new(0.0, -2.0, 1.0),
        Point3::origin(),
        Vector3::z(),
        64,
        48,
        60.0,
    );
    let options = RenderOptions {
        floor: Some(FloorPlane {
            point: [0.0, 0.0, 0.0],
            normal: [0.0, 0.0, 1.0],
            checker_size_m: 0.2,
            color_a: [1.0; 3],
            color_b: [0.0; 3],
        }),
        ..RenderOptions::default()
    };
    let below = splat([0.0, 0.0, -0.3], 0.1, 5);
    let above = splat([0.5, 0.0, 0.2], 0.1, 6);
    let frame = render(&camera, &[below, above], &options);
    assert!(!frame.label.contains(&5));
    assert!(frame.label.contains(&6));
}

#[test]
fn invalid_splats_are_skipped() {
    let camera = camera();
    let good = splat([0.0, 1.0, 0.0], 0.05, 1);
    let splats = [
        splat([f32::NAN, 1.0, 0.0], 0.05, 2),
        splat([0.0, 1.0, 0.0], f32::NAN, 3),
        splat([0.0, 1.0, 0.0], -1.0, 4),
        splat([0.0, -1.0, 0.0], 0.05, 5),
        splat([f32::INFINITY, 1.0, 0.0], 0.05, 6),
        Splat {
            color: [f32::NAN; 3],
            ..good
        },
        good,
        // Enormous splat right in front of the camera must not overflow anything.
        splat([0.0, 0.01, 0.0], 1e6, 8),
    ];
    let frame = render(&camera, &splats, &RenderOptions::default());
    assert!(frame.label.iter().all(|&l| l == 0 || l == 1 || l == 8));
    assert!(frame.rgb.iter().flatten().all(|c| c.is_finite()));
}

#[test]
fn tiny_splats_still_cover_a_pixel() {
    let camera = camera();
    let frame = render(
        &camera,
        &[splat([0.0, 10.0, 0.0], 1e-5, 9)],
        &RenderOptions::default(),
    );
    assert_eq!(frame.label.iter().filter(|&&l| l == 9).count(), 1);
}

#[test]
fn zero_size_camera_gives_empty_frame() {
    let mut camera = camera();
    camera.width = 0;
    let frame = render(
        &camera,
        &[splat([0.0, 1.0, 0.0], 0.05, 1)],
        &RenderOptions::default(),
    );
    assert!(frame.rgb.is_empty() && frame.depth.is_empty());
}
