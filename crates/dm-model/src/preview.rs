//! Preview strips: the observed camera image above the model's prediction
//! rendered from the same camera, at a few frames.

use dm_bundle::Bundle;
use dm_view::{Camera, Frame, RenderOptions, Splat, render, side_by_side};
use image::RgbImage;

/// A recorded camera as a renderer camera (the one conversion; callers add
/// where the spec came from to the error).
pub fn camera_from_spec(spec: &dm_bundle::CameraSpec) -> Result<Camera, String> {
    Camera::from_matrix_4x4(
        spec.width,
        spec.height,
        spec.fx,
        spec.fy,
        spec.cx,
        spec.cy,
        spec.world_to_camera,
    )
    .map_err(|e| e.to_string())
}

/// A renderer camera as a recorded camera (the inverse of
/// [`camera_from_spec`]), OpenCV axes.
pub fn spec_from_camera(name: String, camera: &Camera) -> dm_bundle::CameraSpec {
    dm_bundle::CameraSpec {
        name,
        width: camera.width,
        height: camera.height,
        fx: camera.fx,
        fy: camera.fy,
        cx: camera.cx,
        cy: camera.cy,
        world_to_camera: camera.to_matrix_4x4(),
        axes: dm_bundle::CAMERA_AXES_OPENCV.to_string(),
    }
}

/// The bundle camera `index` as a renderer camera.
pub fn bundle_camera(bundle: &Bundle, index: usize) -> Result<Camera, dm_bundle::BundleError> {
    camera_from_spec(&bundle.meta.cameras[index]).map_err(|problem| {
        dm_bundle::BundleError::new(
            bundle.root.join(dm_bundle::BUNDLE_JSON),
            format!("cameras[{index}].world_to_camera"),
            problem,
        )
    })
}

/// Label of object splats in [`particle_frame`]'s label image.
pub const OBJECT_LABEL: u8 = 1;
/// Label of hand splats in [`particle_frame`]'s label image.
pub const HAND_LABEL: u8 = 2;

/// Renders particles (with their colours) and hand anchors (skin-coloured
/// balls) from `camera` over a floor.
pub fn render_particles(
    camera: &Camera,
    positions: &[[f32; 3]],
    colors: &[[f32; 3]],
    radius: f32,
    anchors: &[[f32; 3]],
    up: [f64; 3],
    floor_height: f64,
) -> RgbImage {
    particle_frame(camera, positions, colors, radius, anchors, up, floor_height).to_rgb8()
}

/// [`render_particles`] with depth and labels ([`OBJECT_LABEL`],
/// [`HAND_LABEL`]): what a bundle writer needs.
pub fn particle_frame(
    camera: &Camera,
    positions: &[[f32; 3]],
    colors: &[[f32; 3]],
    radius: f32,
    anchors: &[[f32; 3]],
    up: [f64; 3],
    floor_height: f64,
) -> Frame {
    let mut splats: Vec<Splat> = positions
        .iter()
        .zip(colors)
        .map(|(&position, &color)| Splat {
            position,
            radius,
            color,
            label: OBJECT_LABEL,
        })
        .collect();
    splats.extend(anchors.iter().map(|&position| Splat {
        position,
        radius: 0.009,
        color: [0.86, 0.66, 0.55],
        label: HAND_LABEL,
    }));
    let options = RenderOptions::studio(up, floor_height);
    render(camera, &splats, &options)
}

/// Two rows (observed, predicted) of camera `camera_index` at `frames`.
pub fn comparison_strip(
    bundle: &Bundle,
    camera_index: usize,
    rollout: &[Vec<[f32; 3]>],
    colors: &[[f32; 3]],
    radius: f32,
    frames: &[usize],
) -> Result<RgbImage, dm_bundle::BundleError> {
    let camera = bundle_camera(bundle, camera_index)?;
    let up = bundle.meta.up_axis.unit_vector();
    let mut observed = Vec::new();
    let mut predicted = Vec::new();
    for &t in frames {
        observed.push(bundle.load_rgb(camera_index, t)?);
        let anchors: Vec<[f32; 3]> = bundle
            .tracks
            .hand_points
            .index_axis(ndarray::Axis(0), t)
            .outer_iter()
            .map(|r| [r[0], r[1], r[2]])
            .collect();
        predicted.push(render_particles(
            &camera,
            &rollout[t],
            colors,
            radius,
            &anchors,
            up,
            bundle.meta.floor_height_m,
        ));
    }
    let top = side_by_side(&observed, &[]);
    let bottom = side_by_side(&predicted, &[]);
    let mut out = RgbImage::from_pixel(
        top.width(),
        top.height() + bottom.height() + 4,
        image::Rgb([255, 255, 255]),
    );
    image::imageops::replace(&mut out, &top, 0, 0);
    image::imageops::replace(&mut out, &bottom, 0, i64::from(top.height()) + 4);
    Ok(out)
}
