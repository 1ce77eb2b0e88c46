use nalgebra::{Point3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::fallback_perpendicular;
use crate::{Camera, Frame, NEAR_PLANE};

/// Height in pixel rows of the full-width screen bands ("tiles") splats are binned
/// into; each band is rendered by one rayon task straight into the frame buffers.
/// Full-width bands need no tile-to-frame copy; 8 rows still give 60 tasks at 480p
/// for load balancing.
pub const BAND_HEIGHT: u32 = 8;

/// Splats whose footprint would be smaller than this radius (pixels) are enlarged to
/// it, so every splat covers at least the pixel containing its centre instead of
/// vanishing between pixel centres (0.5 * sqrt(2) reaches that pixel's centre).
const MIN_FOOTPRINT_RADIUS_PX: f64 = 0.7072;

const NO_SPLAT: u32 = u32::MAX;

/// A particle drawn as a sphere of `radius` metres centred at `position` (world).
/// `label` 0 is reserved for background / floor in the label image; splats with label
/// 0 are drawn but only distinguishable through `Frame::splat_index`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Splat {
    pub position: [f32; 3],
    pub radius: f32,
    pub color: [f32; 3],
    pub label: u8,
}

/// Infinite checkerboard ground plane, drawn wherever a pixel ray hits it in front of
/// the camera (both sides of the plane are drawn).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FloorPlane {
    pub point: [f64; 3],
    pub normal: [f64; 3],
    /// Checker cell edge (metres); non-positive or non-finite gives a plain `color_a`
    /// floor.
    pub checker_size_m: f64,
    pub color_a: [f32; 3],
    pub color_b: [f32; 3],
}

/// Shading and scene options for [`render`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RenderOptions {
    pub background: [f32; 3],
    /// Direction from the surface *towards* the light, world space (normalised
    /// internally). A zero or non-finite vector disables the diffuse term.
    pub light_dir_world: [f64; 3],
    pub ambient: f32,
    pub diffuse: f32,
    pub floor: Option<FloorPlane>,
}

impl RenderOptions {
    /// The look shared by synthetic captures and model previews: a soft
    /// key light from above and a grey checkered floor (10 cm squares) at
    /// `floor_height` along the unit vector `up`.
    pub fn studio(up: [f64; 3], floor_height: f64) -> Self {
        RenderOptions {
            background: [0.55, 0.6, 0.65],
            light_dir_world: [0.3, -0.4, 1.0],
            ambient: 0.35,
            diffuse: 0.7,
            floor: Some(FloorPlane {
                point: up.map(|u| u * floor_height),
                normal: up,
                checker_size_m: 0.1,
                color_a: [0.62, 0.6, 0.56],
                color_b: [0.52, 0.5, 0.47],
            }),
        }
    }
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            background: [0.55, 0.6, 0.68],
            light_dir_world: [0.3, 0.2, 1.0],
            ambient: 0.35,
            diffuse: 0.65,
            floor: None,
        }
    }
}

/// A splat transformed into camera space with its pixel bounding box; f32 is plenty
/// for per-pixel work and halves memory traffic.
#[derive(Debug, Clone, Copy)]
struct ProjectedSplat {
    /// Index into the caller's `splats` slice.
    source_index: u32,
    u: f32,
    v: f32,
    z: f32,
    radius: f32,
    /// Reciprocal footprint radii in pixels, so per-pixel offsets become unit-disc
    /// coordinates with one multiply.
    inv_footprint_x: f32,
    inv_footprint_y: f32,
    color: [f32; 3],
    label: u8,
    /// Inclusive pixel bounding box, already clipped to the image.
    x_min: u32,
    x_max: u32,
    y_min: u32,
    y_max: u32,
}

/// `w · d(u, v)` for a fixed camera-space vector `w`, where
/// `d(u, v) = ((u - cx) / fx, (v - cy) / fy, 1)` is the pixel ray with unit depth; it is
/// affine in `(u, v)`, so per-pixel floor work is a few multiply-adds.
#[derive(Debug, Clone, Copy)]
struct RayDotForm {
    per_u: f64,
    per_v: f64,
    constant: f64,
}

impl RayDotForm {
    fn new(camera: &Camera, w: &Vector3<f64>) -> RayDotForm {
        let per_u = w.x / camera.fx;
        let per_v = w.y / camera.fy;
        RayDotForm {
            per_u,
            per_v,
            constant: w.z - per_u * camera.cx - per_v * camera.cy,
        }
    }

    fn eval(&self, u: f64, v: f64) -> f64 {
        self.per_u * u + self.per_v * v + self.constant
    }
}

/// Floor plane in camera space (camera at the origin) in ray-form for per-pixel work.
#[derive(Debug, Clone, Copy)]
struct CameraSpaceFloor {
    /// `normal · d(u, v)`.
    normal_dot_ray: RayDotForm,
    /// `axis · d(u, v)` for the two in-plane checker axes.
    axis_a_dot_ray: RayDotForm,
    axis_b_dot_ray: RayDotForm,
    /// `point · normal`: the ray-depth numerator.
    offset: f64,
    point_a: f64,
    point_b: f64,
    /// 0 for a plain floor.
    inv_checker_size: f64,
    /// Colours with Lambert shading of the camera-facing side already applied (the
    /// plane is flat, so shading is constant).
    shaded_a: [f32; 3],
    shaded_b: [f32; 3],
}

/// Everything a band task reads; shared immutably across tasks.
#[derive(Debug)]
struct BandContext<'a> {
    width: u32,
    height: u32,
    projected: &'a [ProjectedSplat],
    /// Compressed bins: splats of band `b` are `bin_entries[bin_starts[b]..bin_starts[b+1]]`,
    /// positions into `projected` in ascending order.
    bin_starts: &'a [usize],
    bin_entries: &'a [u32],
    light_camera: Option<Vector3<f32>>,
    ambient: f32,
    diffuse: f32,
    floor: Option<CameraSpaceFloor>,
}

/// One band's rows of the four frame buffers.
#[derive(Debug)]
struct BandBuffers<'a> {
    rgb: &'a mut [[f32; 3]],
    depth: &'a mut [f32],
    label: &'a mut [u8],
    splat_index: &'a mut [u32],
}

/// Renders `splats` as lit sphere impostors with a z-buffer (plus the optional floor).
///
/// Each splat covers the disc of radius `fx * radius / z` (`fy` vertically) around its
/// projected centre; per pixel its depth is the sphere's front surface
/// `z - r * sqrt(1 - d^2)` (d: offset in footprint radii) and the shading normal is the
/// sphere normal there, so overlapping splats read as one smooth surface. (The
/// footprint is the usual impostor approximation, not the exact perspective ellipse;
/// footprints are at least ~0.7 px so tiny splats cover the pixel holding their
/// centre.) Splats with
/// non-finite position / radius / colour, non-positive radius, or centre behind the
/// near plane are skipped.
///
/// Deterministic: every pixel is resolved by exactly one task, which visits its
/// splats in input order; equal depths go to the lower splat index. The result is
/// bitwise identical for any rayon thread count.
pub fn render(camera: &Camera, splats: &[Splat], options: &RenderOptions) -> Frame {
    let width = camera.width;
    let height = camera.height;
    if width == 0 || height == 0 {
        return Frame::with_background(width, height, options.background);
    }

    let projected: Vec<ProjectedSplat> = splats
        .par_iter()
        .enumerate()
        .filter_map(|(index, splat)| project_splat(camera, index, splat))
        .collect();

    let band_count = height.div_ceil(BAND_HEIGHT);
    let (bin_starts, bin_entries) = bin_splats(&projected, band_count);

    let light_camera = {
        let l = Vector3::from(options.light_dir_world);
        let l_camera = camera.world_to_camera.transform_vector(&l);
        l_camera
            .try_normalize(1e-12)
            .filter(|l| l.iter().all(|c| c.is_finite()))
            .map(|l| l.cast::<f32>())
    };
    let context = BandContext {
        width,
        height,
        projected: &projected,
        bin_starts: &bin_starts,
        bin_entries: &bin_entries,
        light_camera,
        ambient: options.ambient,
        diffuse: options.diffuse,
        floor: options
            .floor
            .as_ref()
            .and_then(|floor| floor_in_camera_space(camera, floor, options)),
    };

    let mut frame = Frame::with_background(width, height, options.background);
    let band_len = width as usize * BAND_HEIGHT as usize;
    frame
        .rgb
        .par_chunks_mut(band_len)
        .zip(frame.depth.par_chunks_mut(band_len))
        .zip(frame.label.par_chunks_mut(band_len))
        .zip(frame.splat_index.par_chunks_mut(band_len))
        .enumerate()
        .for_each(|(band, (((rgb, depth), label), splat_index))| {
            let buffers = BandBuffers {
                rgb,
                depth,
                label,
                splat_index,
            };
            render_band(&context, band as u32, buffers);
        });
    frame
}

fn project_splat(camera: &Camera, index: usize, splat: &Splat) -> Option<ProjectedSplat> {
    let radius = f64::from(splat.radius);
    if !(radius.is_finite() && radius > 0.0 && splat.color.iter().all(|c| c.is_finite())) {
        return None;
    }
    let source_index = u32::try_from(index).ok().filter(|&i| i != NO_SPLAT)?;
    let position = Point3::from(splat.position.map(f64::from));
    let (u, v, z) = camera.project(&position)?;
    if !(u.is_finite() && v.is_finite()) {
        return None;
    }

    let footprint_x = (camera.fx * radius / z).max(MIN_FOOTPRINT_RADIUS_PX);
    let footprint_y = (camera.fy * radius / z).max(MIN_FOOTPRINT_RADIUS_PX);
    // Pixel x is covered when |x + 0.5 - u| <= footprint_x.
    let x_range = covered_pixel_range(u, footprint_x, camera.width)?;
    let y_range = covered_pixel_range(v, footprint_y, camera.height)?;
    Some(ProjectedSplat {
        source_index,
        u: u as f32,
        v: v as f32,
        z: z as f32,
        radius: splat.radius,
        inv_footprint_x: (1.0 / footprint_x) as f32,
        inv_footprint_y: (1.0 / footprint_y) as f32,
        color: splat.color,
        label: splat.label,
        x_min: x_range.0,
        x_max: x_range.1,
        y_min: y_range.0,
        y_max: y_range.1,
    })
}

/// Inclusive range of pixel indices in `[0, size)` whose centres lie within `extent`
/// of `center`, or `None` if empty.
fn covered_pixel_range(center: f64, extent: f64, size: u32) -> Option<(u32, u32)> {
    let first = (center - extent - 0.5).ceil().max(0.0);
    let last = (center + extent - 0.5).floor().min(f64::from(size) - 1.0);
    // Clamping in f64 first keeps the casts exact even for huge footprints.
    (first <= last).then_some((first as u32, last as u32))
}

/// Counting-sort splats into bands (CSR layout); entries within each band stay in
/// ascending splat order, which the depth tie-break relies on.
fn bin_splats(projected: &[ProjectedSplat], band_count: u32) -> (Vec<usize>, Vec<u32>) {
    let bands_of = |splat: &ProjectedSplat| splat.y_min / BAND_HEIGHT..=splat.y_max / BAND_HEIGHT;

    let mut counts = vec![0usize; band_count as usize];
    for splat in projected {
        for band in bands_of(splat) {
            counts[band as usize] += 1;
        }
    }
    let mut bin_starts = Vec::with_capacity(counts.len() + 1);
    let mut running = 0usize;
    for count in &counts {
        bin_starts.push(running);
        running += count;
    }
    bin_starts.push(running);

    let mut cursor = bin_starts[..counts.len()].to_vec();
    let mut bin_entries = vec![0u32; running];
    for (position, splat) in projected.iter().enumerate() {
        for band in bands_of(splat) {
            // `projected` is shorter than u32::MAX because source indices are u32.
            bin_entries[cursor[band as usize]] = position as u32;
            cursor[band as usize] += 1;
        }
    }
    (bin_starts, bin_entries)
}

fn floor_in_camera_space(
    camera: &Camera,
    floor: &FloorPlane,
    options: &RenderOptions,
) -> Option<CameraSpaceFloor> {
    let normal_world = Vector3::from(floor.normal).try_normalize(1e-12)?;
    let point_world = Point3::from(floor.point);
    if !(normal_world.iter().all(|c| c.is_finite()) && point_world.iter().all(|c| c.is_finite())) {
        return None;
    }
    let axis_a_world = fallback_perpendicular(&normal_world);
    let axis_b_world = normal_world.cross(&axis_a_world);

    let to_camera = &camera.world_to_camera;
    let point = to_camera.transform_point(&point_world).coords;
    let mut normal = to_camera.transform_vector(&normal_world);
    let mut normal_for_light = normal_world;
    // Shade the side facing the camera; the camera sits at the camera-space origin.
    if normal.dot(&point) > 0.0 {
        normal = -normal;
        normal_for_light = -normal_for_light;
    }
    let light = Vector3::from(options.light_dir_world)
        .try_normalize(1e-12)
        .filter(|l| l.iter().all(|c| c.is_finite()));
    let n_dot_l = light.map_or(0.0, |l| normal_for_light.dot(&l).max(0.0)) as f32;
    let shade = options.ambient + options.diffuse * n_dot_l;

    let axis_a = to_camera.transform_vector(&axis_a_world);
    let axis_b = to_camera.transform_vector(&axis_b_world);
    let checker_ok = floor.checker_size_m.is_finite() && floor.checker_size_m > 0.0;
    Some(CameraSpaceFloor {
        normal_dot_ray: RayDotForm::new(camera, &normal),
        axis_a_dot_ray: RayDotForm::new(camera, &axis_a),
        axis_b_dot_ray: RayDotForm::new(camera, &axis_b),
        offset: point.dot(&normal),
        point_a: point.dot(&axis_a),
        point_b: point.dot(&axis_b),
        inv_checker_size: if checker_ok {
            1.0 / floor.checker_size_m
        } else {
            0.0
        },
        shaded_a: floor.color_a.map(|c| c * shade),
        shaded_b: floor.color_b.map(|c| c * shade),
    })
}

/// Floor depth and shaded colour at image point `(u, v)`, if its ray hits the plane
/// beyond the near plane.
fn floor_sample(floor: &CameraSpaceFloor, u: f64, v: f64) -> Option<(f32, [f32; 3])> {
    // The pixel ray has unit z, so the ray parameter is the optical-axis depth.
    let depth = floor.offset / floor.normal_dot_ray.eval(u, v);
    if !(depth > NEAR_PLANE && depth.is_finite()) {
        return None;
    }
    let cell_a = floor_to_i64(
        (depth * floor.axis_a_dot_ray.eval(u, v) - floor.point_a) * floor.inv_checker_size,
    );
    let cell_b = floor_to_i64(
        (depth * floor.axis_b_dot_ray.eval(u, v) - floor.point_b) * floor.inv_checker_size,
    );
    let color = if cell_a.wrapping_add(cell_b) & 1 == 0 {
        floor.shaded_a
    } else {
        floor.shaded_b
    };
    Some((depth as f32, color))
}

/// `x.floor()` as an integer (saturating), without the libm call `floor` compiles to
/// on baseline x86-64.
fn floor_to_i64(x: f64) -> i64 {
    let truncated = x as i64;
    if (truncated as f64) > x {
        truncated - 1
    } else {
        truncated
    }
}

/// First and last non-negative integers `i` with `low <= i + 0.5 <= high`, clipped to
/// `[min, max]`; `None` when empty. Used for exact per-row disc spans.
fn pixel_span(low: f32, high: f32, min: u32, max: u32) -> Option<(u32, u32)> {
    let first = (low - 0.5).max(min as f32);
    let last = (high - 0.5).min(max as f32);
    // Neither can be NaN: `f32::max`/`min` return the non-NaN operand.
    if first > last {
        return None;
    }
    // Both are within [min, max] here, so truncation is floor and the casts are exact.
    let first_floor = first as u32;
    let first = if (first_floor as f32) < first {
        first_floor + 1
    } else {
        first_floor
    };
    let last = last as u32;
    (first <= last).then_some((first, last))
}

/// Renders rows `[band * BAND_HEIGHT, ..)` into `out`, which arrives initialised as
/// an empty frame (background colour, infinite depth, no splat).
fn render_band(context: &BandContext<'_>, band: u32, out: BandBuffers<'_>) {
    let width = context.width;
    let y0 = band * BAND_HEIGHT;
    let y1 = (y0 + BAND_HEIGHT).min(context.height) - 1;
    let row_len = width as usize;
    let BandBuffers {
        rgb,
        depth,
        label,
        splat_index,
    } = out;

    if let Some(floor) = &context.floor {
        for y in y0..=y1 {
            let row = (y - y0) as usize * row_len;
            for x in 0..width {
                if let Some((floor_depth, color)) =
                    floor_sample(floor, f64::from(x) + 0.5, f64::from(y) + 0.5)
                {
                    depth[row + x as usize] = floor_depth;
                    rgb[row + x as usize] = color;
                }
            }
        }
    }

    // `splat_index` holds the winner as a position into `projected` until shading, so
    // the z-buffer pass needs no extra buffer; each pixel is shaded once afterwards.
    let winner = splat_index;
    let near = NEAR_PLANE as f32;
    let bin_range = context.bin_starts[band as usize]..context.bin_starts[band as usize + 1];
    for &position in &context.bin_entries[bin_range] {
        let splat = &context.projected[position as usize];
        let footprint_x = 1.0 / splat.inv_footprint_x;
        let nearest_depth = splat.z - splat.radius;
        for y in splat.y_min.max(y0)..=splat.y_max.min(y1) {
            let dy = (y as f32 + 0.5 - splat.v) * splat.inv_footprint_y;
            let row_extent = 1.0 - dy * dy;
            if row_extent < 0.0 {
                continue;
            }
            // Exact span of this row inside the disc: avoids per-pixel rejects.
            let half_width = footprint_x * row_extent.sqrt();
            let Some((x_first, x_last)) = pixel_span(
                splat.u - half_width,
                splat.u + half_width,
                splat.x_min,
                splat.x_max,
            ) else {
                continue;
            };
            let row = (y - y0) as usize * row_len;
            for x in x_first..=x_last {
                let local = row + x as usize;
                let current = depth[local];
                // Cheap reject before the sqrt: even the sphere's nearest point is
                // behind what is already there (strict, so results are unchanged).
                if nearest_depth > current {
                    continue;
                }
                let dx = (x as f32 + 0.5 - splat.u) * splat.inv_footprint_x;
                let cap = (row_extent - dx * dx).max(0.0);
                let surface_depth = splat.z - splat.radius * cap.sqrt();
                // Bins are in ascending order, so strict `<` already keeps the lowest
                // index on ties; the explicit check documents and guards that rule.
                if surface_depth > near
                    && (surface_depth < current
                        || (surface_depth == current && position < winner[local]))
                {
                    depth[local] = surface_depth;
                    winner[local] = position;
                }
            }
        }
    }

    for local in 0..winner.len() {
        let Some(splat) = context.projected.get(winner[local] as usize) else {
            continue;
        };
        let x = (local % row_len) as u32;
        let y = y0 + (local / row_len) as u32;
        let dx = (x as f32 + 0.5 - splat.u) * splat.inv_footprint_x;
        let dy = (y as f32 + 0.5 - splat.v) * splat.inv_footprint_y;
        // Sphere normal facing the camera (-z) at this pixel.
        let normal_z = -(1.0 - (dx * dx + dy * dy)).max(0.0).sqrt();
        let n_dot_l = context
            .light_camera
            .map_or(0.0, |l| (dx * l.x + dy * l.y + normal_z * l.z).max(0.0));
        let shade = context.ambient + context.diffuse * n_dot_l;
        rgb[local] = splat.color.map(|c| c * shade);
        label[local] = splat.label;
        winner[local] = splat.source_index;
    }
}
