//! First-frame particles from the first-frame observation.
//!
//! * Surface: the object's lifted frame-0 pixels of every camera, thinned
//!   to one averaged point per cell of a `spacing` grid (even density
//!   whatever the camera's distance).
//! * Planar objects (cloth, paper): the surface points are projected on
//!   their best-fit plane, triangulated (Delaunay, `spade`), triangles with
//!   an edge longer than a few spacings dropped (holes and concave borders
//!   stay open), and the triangles sampled evenly at the spacing, each
//!   sample lifted back by barycentric interpolation.
//! * Volumetric and linear objects: interior particles on a `spacing`
//!   lattice, kept where every camera that sees the point sees it on the
//!   object (or behind a hand) and not in front of the measured surface —
//!   space carving with depth — and above the floor.

use std::collections::BTreeMap;

use dm_view::Camera;
use image::GrayImage;
use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use spade::{DelaunayTriangulation, Point2, Triangulation};

/// A coloured point cloud.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ColoredPoints {
    pub points: Vec<[f64; 3]>,
    pub colors: Vec<[f32; 3]>,
}

/// One averaged point per occupied cell of a `spacing` grid, in cell order.
pub fn voxel_thin(cloud: &ColoredPoints, spacing: f64) -> ColoredPoints {
    let mut cells: BTreeMap<[i64; 3], ([f64; 3], [f64; 3], f64)> = BTreeMap::new();
    for (p, c) in cloud.points.iter().zip(&cloud.colors) {
        let key = p.map(|v| (v / spacing).floor() as i64);
        let entry = cells.entry(key).or_insert(([0.0; 3], [0.0; 3], 0.0));
        for a in 0..3 {
            entry.0[a] += p[a];
            entry.1[a] += f64::from(c[a]);
        }
        entry.2 += 1.0;
    }
    let mut out = ColoredPoints::default();
    for (sum_p, sum_c, n) in cells.into_values() {
        out.points.push(sum_p.map(|v| v / n));
        out.colors.push(sum_c.map(|v| (v / n) as f32));
    }
    out
}

/// Principal axes of a cloud: centre and eigenvectors by decreasing spread
/// (columns), with the standard deviations along them.
pub fn principal_axes(points: &[[f64; 3]]) -> (Vector3<f64>, Matrix3<f64>, [f64; 3]) {
    let n = points.len().max(1) as f64;
    let centre = points
        .iter()
        .map(|p| Vector3::new(p[0], p[1], p[2]))
        .sum::<Vector3<f64>>()
        / n;
    let covariance = points
        .iter()
        .map(|p| {
            let d = Vector3::new(p[0], p[1], p[2]) - centre;
            d * d.transpose()
        })
        .sum::<Matrix3<f64>>()
        / n;
    let eigen = SymmetricEigen::new(covariance);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eigen.eigenvalues[b].total_cmp(&eigen.eigenvalues[a]));
    let axes = Matrix3::from_columns(&order.map(|i| eigen.eigenvectors.column(i).into_owned()));
    let spread = order.map(|i| eigen.eigenvalues[i].max(0.0).sqrt());
    (centre, axes, spread)
}

/// Evenly spaced samples of a thin sheet through `surface` (see the module
/// notes). Colours come from the triangle's vertices.
pub fn fill_sheet(surface: &ColoredPoints, spacing: f64) -> ColoredPoints {
    let (centre, axes, _) = principal_axes(&surface.points);
    let (e0, e1) = (axes.column(0).into_owned(), axes.column(1).into_owned());
    let mut triangulation: DelaunayTriangulation<Point2<f64>> = DelaunayTriangulation::new();
    // Vertex handle index → surface point index (duplicates are merged by spade).
    let mut owner = Vec::new();
    for (i, p) in surface.points.iter().enumerate() {
        let d = Vector3::new(p[0], p[1], p[2]) - centre;
        if let Ok(handle) = triangulation.insert(Point2::new(d.dot(&e0), d.dot(&e1))) {
            let h = handle.index();
            if h >= owner.len() {
                owner.resize(h + 1, i);
            }
            owner[h] = i;
        }
    }
    let longest_edge = 3.0 * spacing;
    let mut out = ColoredPoints::default();
    for face in triangulation.inner_faces() {
        let vertices = face.vertices();
        let ids = vertices.map(|v| owner[v.index()]);
        let p = ids.map(|i| Vector3::from(surface.points[i]));
        let c = ids.map(|i| surface.colors[i]);
        if (0..3).any(|k| (p[k] - p[(k + 1) % 3]).norm() > longest_edge) {
            continue;
        }
        // Lattice points of spacing `spacing` in the sheet's plane that fall
        // inside the triangle (2D barycentric test): every point of the
        // plane is sampled by exactly one triangle, so density is even.
        let q = vertices.map(|v| {
            let pos = v.position();
            [pos.x, pos.y]
        });
        let (min_x, max_x) = (
            q[0][0].min(q[1][0]).min(q[2][0]),
            q[0][0].max(q[1][0]).max(q[2][0]),
        );
        let (min_y, max_y) = (
            q[0][1].min(q[1][1]).min(q[2][1]),
            q[0][1].max(q[1][1]).max(q[2][1]),
        );
        let det =
            (q[1][1] - q[2][1]) * (q[0][0] - q[2][0]) + (q[2][0] - q[1][0]) * (q[0][1] - q[2][1]);
        if det.abs() < 1e-18 {
            continue;
        }
        let mut gx = (min_x / spacing).ceil() as i64;
        while (gx as f64) * spacing <= max_x {
            let mut gy = (min_y / spacing).ceil() as i64;
            while (gy as f64) * spacing <= max_y {
                let (x, y) = (gx as f64 * spacing, gy as f64 * spacing);
                let l0 = ((q[1][1] - q[2][1]) * (x - q[2][0])
                    + (q[2][0] - q[1][0]) * (y - q[2][1]))
                    / det;
                let l1 = ((q[2][1] - q[0][1]) * (x - q[2][0])
                    + (q[0][0] - q[2][0]) * (y - q[2][1]))
                    / det;
                let l2 = 1.0 - l0 - l1;
                // Half-open edges so a lattice point on a shared edge is taken once.
                if l0 >= 0.0 && l1 >= 0.0 && l2 > 0.0 {
                    let point = p[0] * l0 + p[1] * l1 + p[2] * l2;
                    out.points.push([point.x, point.y, point.z]);
                    out.colors.push(std::array::from_fn(|a| {
                        (f64::from(c[0][a]) * l0
                            + f64::from(c[1][a]) * l1
                            + f64::from(c[2][a]) * l2) as f32
                    }));
                }
                gy += 1;
            }
            gx += 1;
        }
    }
    out
}

/// One camera's frame-0 view for carving.
#[derive(Clone, Debug)]
pub struct CarveView<'a> {
    pub camera: &'a Camera,
    /// Raw depth (m, NaN = none).
    pub depth_m: &'a [f32],
    pub object: &'a GrayImage,
    pub hand: &'a GrayImage,
}

/// Interior particles of a solid: lattice points of `spacing` inside the
/// surface cloud's bounds (see the module notes). `tolerance_m` absorbs
/// depth noise. Points closer than `spacing` to a surface particle are left
/// out (the surface layer already holds them).
pub fn carve_interior(
    views: &[CarveView<'_>],
    surface: &[[f64; 3]],
    up: [f64; 3],
    floor_height_m: f64,
    spacing: f64,
    tolerance_m: f64,
) -> Vec<[f64; 3]> {
    if surface.is_empty() {
        return Vec::new();
    }
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in surface {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let index = dm_mpm::neighbors::PointIndex::new(surface);
    // Cells of `spacing` covering [lo, hi], sampled at their centres. The
    // tolerance keeps an extent that is a whole number of cells up to
    // round-off (FMA or not) from gaining a cell centred outside the box.
    let counts = [0, 1, 2].map(|a| (((hi[a] - lo[a]) / spacing - 1e-9).ceil().max(1.0)) as usize);
    let mut out = Vec::new();
    for i in 0..counts[0] {
        for j in 0..counts[1] {
            for k in 0..counts[2] {
                let p = [
                    lo[0] + (i as f64 + 0.5) * spacing,
                    lo[1] + (j as f64 + 0.5) * spacing,
                    lo[2] + (k as f64 + 0.5) * spacing,
                ];
                let height = p[0] * up[0] + p[1] * up[1] + p[2] * up[2] - floor_height_m;
                if height <= 0.0 {
                    continue;
                }
                if index.nearest(&p, 1).first().is_some_and(|n| n.1 < spacing) {
                    continue;
                }
                if views.iter().all(|view| inside_for(view, p, tolerance_m)) {
                    out.push(p);
                }
            }
        }
    }
    out
}

/// Whether a camera's observation allows `p` to be inside the object.
fn inside_for(view: &CarveView<'_>, p: [f64; 3], tolerance_m: f64) -> bool {
    let camera = view.camera;
    let Some((u, v, z)) = camera.project(&nalgebra::Point3::new(p[0], p[1], p[2])) else {
        return true;
    };
    if !camera.contains_pixel(u, v) {
        return true; // unseen: no evidence against
    }
    let (x, y) = (u as u32, v as u32);
    let on_object = view.object.get_pixel(x, y).0[0] > 0;
    let on_hand = view.hand.get_pixel(x, y).0[0] > 0;
    if !on_object && !on_hand {
        return false; // the camera sees past it to the floor
    }
    let d = view.depth_m[y as usize * camera.width as usize + x as usize];
    // In front of the measured surface: the camera would have seen it.
    !(d.is_finite() && z < f64::from(d) - tolerance_m) || on_hand
}

/// Colour of each point: that of its nearest surface particle.
pub fn nearest_colors(points: &[[f64; 3]], surface: &ColoredPoints) -> Vec<[f32; 3]> {
    let index = dm_mpm::neighbors::PointIndex::new(&surface.points);
    points
        .iter()
        .map(|p| {
            index
                .nearest(p, 1)
                .first()
                .map_or([0.5; 3], |&(i, _)| surface.colors[i])
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn nearest_gap_stats(points: &[[f64; 3]]) -> (f64, f64) {
        let index = dm_mpm::neighbors::PointIndex::new(points);
        let gaps: Vec<f64> = points.iter().map(|p| index.nearest(p, 2)[1].1).collect();
        let min = gaps.iter().copied().fold(f64::INFINITY, f64::min);
        let max = gaps.iter().copied().fold(0.0, f64::max);
        (min, max)
    }

    #[test]
    fn sheet_fill_covers_a_square_evenly() {
        // A tilted 0.2 m square seen as scattered points.
        let mut cloud = ColoredPoints::default();
        let mut state = 12345u64;
        let mut random = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..3000 {
            let (a, b) = (0.2 * random(), 0.2 * random());
            cloud.points.push([a, b * 0.8, 0.1 + b * 0.6]);
            cloud.colors.push([0.5, 0.2, 0.1]);
        }
        let spacing = 0.01;
        let sheet = fill_sheet(&cloud, spacing);
        // Area 0.04 m² at one sample per spacing²: ~400 samples (the border
        // strip lost to the Delaunay hull of random points is small).
        assert!(
            (340..=420).contains(&sheet.points.len()),
            "{}",
            sheet.points.len()
        );
        let (min, max) = nearest_gap_stats(&sheet.points);
        assert!(
            min > 0.99 * spacing && max < 1.01 * spacing,
            "gaps {min}..{max}"
        );
        for p in &sheet.points {
            // On the plane y·0.6 − (z − 0.1)·0.8 = 0.
            assert!((p[1] * 0.6 - (p[2] - 0.1) * 0.8).abs() < 1e-9);
        }
        assert!(sheet.colors.iter().all(|c| (c[0] - 0.5).abs() < 1e-6));
    }

    #[test]
    fn carving_fills_a_box_seen_from_above() {
        // A 0.1 m cube on the floor under a camera looking straight down.
        let camera = Camera::look_at(
            nalgebra::Point3::new(0.0, 0.0, 0.8),
            nalgebra::Point3::origin(),
            Vector3::y(),
            200,
            200,
            40.0,
        );
        let (w, h) = (200usize, 200usize);
        let mut depth = vec![0.8f32; w * h];
        let mut object = GrayImage::new(w as u32, h as u32);
        let hand = GrayImage::new(w as u32, h as u32);
        let mut surface = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let ray = camera.unproject(x as f64 + 0.5, y as f64 + 0.5, 0.7);
                if ray.x.abs() < 0.05 && ray.y.abs() < 0.05 {
                    depth[y * w + x] = 0.7;
                    object.put_pixel(x as u32, y as u32, image::Luma([255]));
                    surface.push([ray.x, ray.y, ray.z]);
                }
            }
        }
        // The bottom corners bound the lattice (a real cloud has the sides).
        surface.push([-0.05, -0.05, 0.0]);
        surface.push([0.05, 0.05, 0.0]);
        let views = [CarveView {
            camera: &camera,
            depth_m: &depth,
            object: &object,
            hand: &hand,
        }];
        let spacing = 0.01;
        let interior = carve_interior(&views, &surface, [0.0, 0.0, 1.0], 0.0, spacing, 0.002);
        // 10 × 10 × 10 lattice, minus the top layer (within a spacing of the
        // observed top) — and every kept point inside the cube.
        assert!((850..=1000).contains(&interior.len()), "{}", interior.len());
        for p in &interior {
            assert!(
                p[0].abs() < 0.05 && p[1].abs() < 0.05 && p[2] > 0.0 && p[2] < 0.1,
                "{p:?}"
            );
        }
        let (min, max) = nearest_gap_stats(&interior);
        assert!((min - spacing).abs() < 1e-9 && (max - spacing).abs() < 1e-9);
    }
}
