//! A small CPU rasteriser: a coloured mesh seen by a pinhole camera, with a
//! z-buffer and, per pixel, the mesh-frame surface point (which turns a
//! keypoint found in a render into a 2D–3D correspondence for PnP).
//!
//! OpenCV camera convention: x right, y down, z forward; pixel (u, v) has
//! its centre at integer coordinates, as `solvePnP` assumes.

use image::{Rgb, RgbImage};
use nalgebra::{Isometry3, Vector3};

use crate::mesh::Mesh;

/// Pinhole intrinsics and image size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

impl Intrinsics {
    pub fn project(&self, p: &Vector3<f64>) -> [f64; 2] {
        [self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy]
    }

    /// The camera-frame point at pixel (u, v) and depth z.
    pub fn unproject(&self, u: f64, v: f64, z: f64) -> Vector3<f64> {
        Vector3::new((u - self.cx) / self.fx * z, (v - self.cy) / self.fy * z, z)
    }
}

/// Points nearer than this (metres) are not drawn.
const NEAR_PLANE: f64 = 1e-3;

/// A render: colour, depth (camera z, infinite where empty) and the
/// mesh-frame surface point of each pixel.
#[derive(Clone, Debug)]
pub struct Render {
    pub color: RgbImage,
    pub depth: Vec<f64>,
    pub surface: Vec<Option<Vector3<f64>>>,
}

impl Render {
    pub fn depth_at(&self, u: u32, v: u32) -> Option<f64> {
        let index = v as usize * self.color.width() as usize + u as usize;
        self.depth.get(index).copied().filter(|d| d.is_finite())
    }

    pub fn surface_at(&self, u: u32, v: u32) -> Option<Vector3<f64>> {
        let index = v as usize * self.color.width() as usize + u as usize;
        self.surface.get(index).copied().flatten()
    }
}

/// Renders `mesh` posed by `mesh_to_camera` (black background).
pub fn render(mesh: &Mesh, mesh_to_camera: &Isometry3<f64>, intrinsics: &Intrinsics) -> Render {
    let (width, height) = (intrinsics.width as usize, intrinsics.height as usize);
    let mut color = RgbImage::new(intrinsics.width, intrinsics.height);
    let mut depth = vec![f64::INFINITY; width * height];
    let mut surface = vec![None; width * height];
    let camera: Vec<Vector3<f64>> = mesh
        .positions
        .iter()
        .map(|p| mesh_to_camera.transform_vector(p) + mesh_to_camera.translation.vector)
        .collect();
    for tri in &mesh.triangles {
        let [a, b, c] = tri.map(|i| i as usize);
        if camera[a].z < NEAR_PLANE || camera[b].z < NEAR_PLANE || camera[c].z < NEAR_PLANE {
            continue;
        }
        let [pa, pb, pc] = [a, b, c].map(|i| intrinsics.project(&camera[i]));
        let area = edge(pa, pb, pc);
        if area.abs() < 1e-12 {
            continue;
        }
        let min_x = pa[0].min(pb[0]).min(pc[0]).ceil().max(0.0) as usize;
        let max_x = pa[0].max(pb[0]).max(pc[0]).floor().min(width as f64 - 1.0);
        let min_y = pa[1].min(pb[1]).min(pc[1]).ceil().max(0.0) as usize;
        let max_y = pa[1].max(pb[1]).max(pc[1]).floor().min(height as f64 - 1.0);
        if max_x < 0.0 || max_y < 0.0 {
            continue;
        }
        let inverse_z = [a, b, c].map(|i| 1.0 / camera[i].z);
        for y in min_y..=(max_y as usize) {
            for x in min_x..=(max_x as usize) {
                let p = [x as f64, y as f64];
                let w = [
                    edge(pb, pc, p) / area,
                    edge(pc, pa, p) / area,
                    edge(pa, pb, p) / area,
                ];
                if w.iter().any(|&wi| wi < 0.0) {
                    continue;
                }
                // Perspective-correct barycentrics.
                let denominator = w[0] * inverse_z[0] + w[1] * inverse_z[1] + w[2] * inverse_z[2];
                let z = 1.0 / denominator;
                let index = y * width + x;
                if z >= depth[index] {
                    continue;
                }
                let weights = [0, 1, 2].map(|k| w[k] * inverse_z[k] * z);
                depth[index] = z;
                let vertices = [a, b, c];
                surface[index] = Some((0..3).fold(Vector3::zeros(), |sum, k| {
                    sum + mesh.positions[vertices[k]] * weights[k]
                }));
                let rgb = (0..3).fold([0f32; 3], |mut sum, k| {
                    for ch in 0..3 {
                        sum[ch] += mesh.colors[vertices[k]][ch] * weights[k] as f32;
                    }
                    sum
                });
                color.put_pixel(
                    x as u32,
                    y as u32,
                    Rgb(rgb.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)),
                );
            }
        }
    }
    Render {
        color,
        depth,
        surface,
    }
}

/// Twice the signed area of (a, b, p).
fn edge(a: [f64; 2], b: [f64; 2], p: [f64; 2]) -> f64 {
    (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
}
