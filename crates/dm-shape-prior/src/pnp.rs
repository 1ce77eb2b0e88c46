//! Pose from keypoints: ORB features of the first-frame crop matched to
//! renders of the mesh from candidate views (each render pixel knows its
//! mesh point), then OpenCV's `solvePnPRansac`.

use image::{GrayImage, RgbImage};
use nalgebra::{Isometry3, Rotation3, Translation3, UnitQuaternion, Vector3};
use opencv::core::{DMatch, KeyPoint, Mat, Point2f, Point3f, Vector};
use opencv::prelude::*;

use crate::PriorError;
use crate::mesh::Mesh;
use crate::raster::{Intrinsics, Render, render};

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PnpOptions {
    /// Candidate viewpoints, spread evenly on a sphere around the mesh.
    pub candidate_views: usize,
    /// Side of the square candidate renders (pixels).
    pub candidate_size: u32,
    /// Lowe's ratio test: best / second-best Hamming distance below this.
    pub ratio: f32,
    pub ransac_iterations: i32,
    pub reprojection_error_px: f32,
    /// Fewer RANSAC inliers than this is no pose.
    pub min_inliers: usize,
    /// Pixels around the mask's bounding box kept in the crop.
    pub crop_margin_px: u32,
    /// ORB's cap on features per image.
    pub features: i32,
}

impl Default for PnpOptions {
    fn default() -> Self {
        Self {
            candidate_views: 40,
            candidate_size: 400,
            ratio: 0.8,
            ransac_iterations: 2000,
            reprojection_error_px: 2.0,
            min_inliers: 12,
            crop_margin_px: 16,
            features: 1500,
        }
    }
}

/// The pose PnP found and how well it is supported.
#[derive(Clone, Debug, PartialEq)]
pub struct PnpPose {
    /// Mesh frame → camera frame.
    pub mesh_to_camera: Isometry3<f64>,
    /// Which candidate view gave it (index into the Fibonacci sphere).
    pub view: usize,
    pub matches: usize,
    pub inliers: usize,
}

fn cv(error: opencv::Error) -> PriorError {
    PriorError::OpenCv(error.to_string())
}

/// ORB keypoints and descriptors of a grey image (mask: where to look).
fn orb_features(
    gray: &GrayImage,
    mask: Option<&GrayImage>,
    options: &PnpOptions,
) -> Result<(Vector<KeyPoint>, Mat), PriorError> {
    let image = Mat::new_rows_cols_with_data::<u8>(
        gray.height() as i32,
        gray.width() as i32,
        gray.as_raw(),
    )
    .map_err(cv)?;
    let mask_mat = match mask {
        Some(mask) => Mat::new_rows_cols_with_data::<u8>(
            mask.height() as i32,
            mask.width() as i32,
            mask.as_raw(),
        )
        .map_err(cv)?
        .try_clone()
        .map_err(cv)?,
        None => Mat::default(),
    };
    let mut orb = opencv::features2d::ORB::create(
        options.features,
        1.2,
        8,
        15,
        0,
        2,
        opencv::features2d::ORB_ScoreType::HARRIS_SCORE,
        31,
        10,
    )
    .map_err(cv)?;
    let mut keypoints = Vector::<KeyPoint>::new();
    let mut descriptors = Mat::default();
    orb.detect_and_compute(&image, &mask_mat, &mut keypoints, &mut descriptors, false)
        .map_err(cv)?;
    Ok((keypoints, descriptors))
}

/// Evenly spread unit directions (Fibonacci sphere).
fn sphere_directions(count: usize) -> Vec<Vector3<f64>> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..count)
        .map(|k| {
            let z = 1.0 - 2.0 * (k as f64 + 0.5) / count as f64;
            let ring = (1.0 - z * z).sqrt();
            let angle = golden * k as f64;
            Vector3::new(ring * angle.cos(), ring * angle.sin(), z)
        })
        .collect()
}

/// A camera at `centre + distance · direction` looking at `centre`.
fn look_at(centre: &Vector3<f64>, direction: &Vector3<f64>, distance: f64) -> Isometry3<f64> {
    let forward = -direction;
    let helper = if forward.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let right = helper.cross(&forward).normalize();
    let down = forward.cross(&right);
    let rotation = Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_rows(&[
        right.transpose(),
        down.transpose(),
        forward.transpose(),
    ]));
    let eye = centre + direction * distance;
    let translation = -(rotation * eye);
    Isometry3::from_parts(
        Translation3::from(translation),
        UnitQuaternion::from_rotation_matrix(&rotation),
    )
}

/// Candidate renders of the mesh filling about 80 % of a square image.
pub fn candidate_renders(mesh: &Mesh, options: &PnpOptions) -> Vec<Render> {
    let (centre, radius) = mesh.bounds();
    let size = options.candidate_size;
    let focal = f64::from(size);
    // The bounding sphere spans 80 % of the image: radius / distance = 0.4 · size / focal.
    let distance = radius / 0.4 * focal / f64::from(size);
    let intrinsics = Intrinsics {
        fx: focal,
        fy: focal,
        cx: f64::from(size) / 2.0,
        cy: f64::from(size) / 2.0,
        width: size,
        height: size,
    };
    sphere_directions(options.candidate_views)
        .iter()
        .map(|direction| render(mesh, &look_at(&centre, direction, distance), &intrinsics))
        .collect()
}

/// The crop of `frame` around the mask (with margin), its grey image, the
/// mask inside it, and the crop's top-left corner.
fn crop(
    frame: &RgbImage,
    mask: Option<&GrayImage>,
    margin: u32,
) -> Result<(GrayImage, Option<GrayImage>, [u32; 2]), PriorError> {
    let gray = image::imageops::grayscale(frame);
    let Some(mask) = mask else {
        return Ok((gray, None, [0, 0]));
    };
    if mask.dimensions() != frame.dimensions() {
        return Err(PriorError::Input(format!(
            "mask is {:?}, frame {:?}",
            mask.dimensions(),
            frame.dimensions()
        )));
    }
    let Some((min, max)) = dm_bundle::mask_box(mask) else {
        return Err(PriorError::Input(
            "the first-frame object mask is empty".into(),
        ));
    };
    let x0 = (min[0] as u32).saturating_sub(margin);
    let y0 = (min[1] as u32).saturating_sub(margin);
    let x1 = (max[0] as u32 + margin).min(frame.width());
    let y1 = (max[1] as u32 + margin).min(frame.height());
    let gray_crop = image::imageops::crop_imm(&gray, x0, y0, x1 - x0, y1 - y0).to_image();
    let mask_crop = image::imageops::crop_imm(mask, x0, y0, x1 - x0, y1 - y0).to_image();
    Ok((gray_crop, Some(mask_crop), [x0, y0]))
}

/// Solves the mesh's pose in `frame` (camera `intrinsics`, object `mask`).
pub fn solve_pose(
    mesh: &Mesh,
    frame: &RgbImage,
    mask: Option<&GrayImage>,
    intrinsics: &Intrinsics,
    options: &PnpOptions,
) -> Result<PnpPose, PriorError> {
    let (gray, crop_mask, offset) = crop(frame, mask, options.crop_margin_px)?;
    let (frame_keypoints, frame_descriptors) = orb_features(&gray, crop_mask.as_ref(), options)?;
    if frame_keypoints.len() < options.min_inliers {
        return Err(PriorError::Pose(format!(
            "{} ORB keypoints on the object in the first frame; need {} (too small or too plain)",
            frame_keypoints.len(),
            options.min_inliers
        )));
    }
    let matcher =
        opencv::features2d::BFMatcher::create(opencv::core::NORM_HAMMING, false).map_err(cv)?;
    let camera = Mat::from_slice_2d(&[
        [intrinsics.fx, 0.0, intrinsics.cx],
        [0.0, intrinsics.fy, intrinsics.cy],
        [0.0, 0.0, 1.0],
    ])
    .map_err(cv)?;
    let no_distortion = Mat::default();
    let mut best: Option<PnpPose> = None;
    for (view, candidate) in candidate_renders(mesh, options).iter().enumerate() {
        let gray_render = image::imageops::grayscale(&candidate.color);
        let covered = GrayImage::from_fn(gray_render.width(), gray_render.height(), |x, y| {
            image::Luma([if candidate.depth_at(x, y).is_some() {
                255
            } else {
                0
            }])
        });
        let (keypoints, descriptors) = orb_features(&gray_render, Some(&covered), options)?;
        if keypoints.len() < 2 {
            continue;
        }
        let mut knn = Vector::<Vector<DMatch>>::new();
        matcher
            .knn_train_match(
                &frame_descriptors,
                &descriptors,
                &mut knn,
                2,
                &Mat::default(),
                false,
            )
            .map_err(cv)?;
        let mut object_points = Vector::<Point3f>::new();
        let mut image_points = Vector::<Point2f>::new();
        for pair in knn.iter() {
            if pair.len() < 2 {
                continue;
            }
            let (first, second) = (pair.get(0).map_err(cv)?, pair.get(1).map_err(cv)?);
            if first.distance >= options.ratio * second.distance {
                continue;
            }
            let train = keypoints.get(first.train_idx as usize).map_err(cv)?.pt();
            let (u, v) = (train.x.round() as i64, train.y.round() as i64);
            if u < 0
                || v < 0
                || u >= i64::from(options.candidate_size)
                || v >= i64::from(options.candidate_size)
            {
                continue;
            }
            let Some(point) = candidate.surface_at(u as u32, v as u32) else {
                continue;
            };
            let query = frame_keypoints
                .get(first.query_idx as usize)
                .map_err(cv)?
                .pt();
            object_points.push(Point3f::new(point.x as f32, point.y as f32, point.z as f32));
            image_points.push(Point2f::new(
                query.x + offset[0] as f32,
                query.y + offset[1] as f32,
            ));
        }
        let matches = object_points.len();
        if matches < options.min_inliers.max(6) {
            continue;
        }
        let mut rvec = Mat::default();
        let mut tvec = Mat::default();
        let mut inliers = Vector::<i32>::new();
        let found = opencv::calib3d::solve_pnp_ransac(
            &object_points,
            &image_points,
            &camera,
            &no_distortion,
            &mut rvec,
            &mut tvec,
            false,
            options.ransac_iterations,
            options.reprojection_error_px,
            0.999,
            &mut inliers,
            opencv::calib3d::SOLVEPNP_ITERATIVE,
        )
        .map_err(cv)?;
        if !found || inliers.len() < options.min_inliers {
            continue;
        }
        if best.as_ref().is_some_and(|b| b.inliers >= inliers.len()) {
            continue;
        }
        let read = |m: &Mat, i: i32| m.at::<f64>(i).copied().map_err(cv);
        let axis_angle = Vector3::new(read(&rvec, 0)?, read(&rvec, 1)?, read(&rvec, 2)?);
        let translation = Vector3::new(read(&tvec, 0)?, read(&tvec, 1)?, read(&tvec, 2)?);
        best = Some(PnpPose {
            mesh_to_camera: Isometry3::from_parts(
                Translation3::from(translation),
                UnitQuaternion::from_scaled_axis(axis_angle),
            ),
            view,
            matches,
            inliers: inliers.len(),
        });
    }
    best.ok_or_else(|| {
        PriorError::Pose(format!(
            "no candidate view gave {} PnP-RANSAC inliers ({} views, {} first-frame keypoints)",
            options.min_inliers,
            options.candidate_views,
            frame_keypoints.len()
        ))
    })
}
