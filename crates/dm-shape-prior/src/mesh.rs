//! Triangle meshes for the shape prior: OBJ (tobj) and glTF/GLB (gltf).

use std::path::{Path, PathBuf};

use nalgebra::{Matrix4, Point3, Vector3};

use crate::PriorError;

/// A triangle mesh with per-vertex colours (linear 0–1 RGB). Vertices may be
/// duplicated along colour seams; [`Mesh::welded`] merges them for ARAP.
#[derive(Clone, Debug, PartialEq)]
pub struct Mesh {
    pub positions: Vec<Vector3<f64>>,
    pub colors: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

/// Colour of meshes that carry none.
const DEFAULT_COLOR: [f32; 3] = [0.7, 0.7, 0.7];
/// Welding lattice (metres): positions rounding to the same multiple are one vertex.
const WELD_GRID: f64 = 1e-6;

impl Mesh {
    /// Loads `.obj`, `.gltf` or `.glb` by extension.
    pub fn load(path: &Path) -> Result<Self, PriorError> {
        let extension = path
            .extension()
            .and_then(|ext| ext.to_str())
            .map(str::to_ascii_lowercase)
            .unwrap_or_default();
        let mesh = match extension.as_str() {
            "obj" => load_obj(path)?,
            // The gltf crate's validation indexes arrays with indices
            // from the file and can panic on a malformed one: that is
            // this file's error, not a crash.
            "gltf" | "glb" => {
                std::panic::catch_unwind(|| load_gltf(path)).unwrap_or_else(|_| {
                    Err(PriorError::Mesh {
                        path: path.to_path_buf(),
                        problem: "malformed glTF: an index in the file points past its arrays"
                            .into(),
                    })
                })?
            }
            _ => {
                return Err(PriorError::Mesh {
                    path: path.to_path_buf(),
                    problem: "unknown mesh format; expected .obj, .gltf or .glb".into(),
                });
            }
        };
        mesh.validate(path)?;
        Ok(mesh)
    }

    fn validate(&self, path: &Path) -> Result<(), PriorError> {
        let problem = if self.triangles.is_empty() {
            Some("no triangles".to_string())
        } else if self.colors.len() != self.positions.len() {
            Some(format!(
                "{} colours for {} vertices",
                self.colors.len(),
                self.positions.len()
            ))
        } else if let Some(t) = self
            .triangles
            .iter()
            .position(|tri| tri.iter().any(|&i| i as usize >= self.positions.len()))
        {
            Some(format!(
                "triangle {t} indexes past the {} vertices",
                self.positions.len()
            ))
        } else if self
            .positions
            .iter()
            .any(|p| !p.iter().all(|c| c.is_finite()))
        {
            Some("non-finite vertex position".into())
        } else {
            None
        };
        match problem {
            Some(problem) => Err(PriorError::Mesh {
                path: path.to_path_buf(),
                problem,
            }),
            None => Ok(()),
        }
    }

    /// Centre of the bounding box and the bounding-sphere radius about it.
    pub fn bounds(&self) -> (Vector3<f64>, f64) {
        let mut min = Vector3::repeat(f64::INFINITY);
        let mut max = Vector3::repeat(f64::NEG_INFINITY);
        for p in &self.positions {
            min = min.inf(p);
            max = max.sup(p);
        }
        let centre = (min + max) / 2.0;
        let radius = self
            .positions
            .iter()
            .map(|p| (p - centre).norm())
            .fold(0.0, f64::max);
        (centre, radius)
    }

    /// Vertices merged by position (colour seams removed): positions,
    /// triangles over them, and each original vertex's welded index.
    /// Positions are compared on a [`WELD_GRID`] lattice: a seam's copies can
    /// differ in the last bits after f32 storage.
    pub fn welded(&self) -> (Vec<Vector3<f64>>, Vec<[u32; 3]>, Vec<u32>) {
        let mut index_of: std::collections::HashMap<[i64; 3], u32> =
            std::collections::HashMap::new();
        let mut unique: Vec<Vector3<f64>> = Vec::new();
        let map: Vec<u32> = self
            .positions
            .iter()
            .map(|p| {
                let key = [p.x, p.y, p.z].map(|c| (c / WELD_GRID).round() as i64);
                *index_of.entry(key).or_insert_with(|| {
                    unique.push(*p);
                    (unique.len() - 1) as u32
                })
            })
            .collect();
        let triangles = self
            .triangles
            .iter()
            .map(|tri| tri.map(|i| map[i as usize]))
            .filter(|tri| tri[0] != tri[1] && tri[1] != tri[2] && tri[0] != tri[2])
            .collect();
        (unique, triangles, map)
    }
}

fn load_obj(path: &Path) -> Result<Mesh, PriorError> {
    let (models, materials) =
        tobj::load_obj(path, &tobj::GPU_LOAD_OPTIONS).map_err(|error| PriorError::Mesh {
            path: path.to_path_buf(),
            problem: error.to_string(),
        })?;
    let materials = materials.unwrap_or_default();
    let mut mesh = Mesh {
        positions: Vec::new(),
        colors: Vec::new(),
        triangles: Vec::new(),
    };
    for model in &models {
        let source = &model.mesh;
        let base = mesh.positions.len() as u32;
        let count = source.positions.len() / 3;
        let material_color = source
            .material_id
            .and_then(|id| materials.get(id))
            .and_then(|material| material.diffuse)
            .unwrap_or(DEFAULT_COLOR);
        for v in 0..count {
            mesh.positions.push(Vector3::new(
                f64::from(source.positions[3 * v]),
                f64::from(source.positions[3 * v + 1]),
                f64::from(source.positions[3 * v + 2]),
            ));
            mesh.colors
                .push(if source.vertex_color.len() == source.positions.len() {
                    [
                        source.vertex_color[3 * v],
                        source.vertex_color[3 * v + 1],
                        source.vertex_color[3 * v + 2],
                    ]
                } else {
                    material_color
                });
        }
        for tri in source.indices.chunks_exact(3) {
            mesh.triangles
                .push([base + tri[0], base + tri[1], base + tri[2]]);
        }
    }
    Ok(mesh)
}

fn load_gltf(path: &Path) -> Result<Mesh, PriorError> {
    let error = |problem: String| PriorError::Mesh {
        path: path.to_path_buf(),
        problem,
    };
    let bytes = std::fs::read(path).map_err(|e| error(e.to_string()))?;
    let document = gltf::Gltf::from_slice(&bytes).map_err(|e| error(e.to_string()))?;
    let mut buffers: Vec<Vec<u8>> = Vec::new();
    for buffer in document.buffers() {
        let data = match buffer.source() {
            gltf::buffer::Source::Bin => document
                .blob
                .clone()
                .ok_or_else(|| error("buffer refers to a missing GLB binary chunk".into()))?,
            gltf::buffer::Source::Uri(uri) => {
                if uri.starts_with("data:") {
                    return Err(error(format!(
                        "buffer {}: data URIs are not supported; use GLB",
                        buffer.index()
                    )));
                }
                let file: PathBuf = path.parent().unwrap_or(Path::new(".")).join(uri);
                std::fs::read(&file).map_err(|e| {
                    error(format!(
                        "buffer {}: {}: {e}",
                        buffer.index(),
                        file.display()
                    ))
                })?
            }
        };
        if data.len() < buffer.length() {
            return Err(error(format!(
                "buffer {} holds {} bytes, declares {}",
                buffer.index(),
                data.len(),
                buffer.length()
            )));
        }
        buffers.push(data);
    }
    let mut mesh = Mesh {
        positions: Vec::new(),
        colors: Vec::new(),
        triangles: Vec::new(),
    };
    let scene = document
        .default_scene()
        .or_else(|| document.scenes().next())
        .ok_or_else(|| error("no scene".into()))?;
    let mut stack: Vec<(gltf::Node, Matrix4<f64>)> =
        scene.nodes().map(|n| (n, Matrix4::identity())).collect();
    while let Some((node, parent)) = stack.pop() {
        let local = Matrix4::from_iterator(
            node.transform()
                .matrix()
                .iter()
                .flatten()
                .map(|&v| f64::from(v)),
        );
        let world = parent * local;
        if let Some(gltf_mesh) = node.mesh() {
            for primitive in gltf_mesh.primitives() {
                if primitive.mode() != gltf::mesh::Mode::Triangles {
                    continue;
                }
                let reader =
                    primitive.reader(|buffer| buffers.get(buffer.index()).map(Vec::as_slice));
                let positions: Vec<[f32; 3]> = reader
                    .read_positions()
                    .ok_or_else(|| {
                        error(format!(
                            "mesh {}: primitive without POSITION",
                            gltf_mesh.index()
                        ))
                    })?
                    .collect();
                let base = mesh.positions.len() as u32;
                let factor = primitive
                    .material()
                    .pbr_metallic_roughness()
                    .base_color_factor();
                let colors: Vec<[f32; 3]> = match reader.read_colors(0) {
                    Some(colors) => colors.into_rgb_f32().collect(),
                    None => vec![[factor[0], factor[1], factor[2]]; positions.len()],
                };
                if colors.len() != positions.len() {
                    return Err(error(format!(
                        "mesh {}: COLOR_0 and POSITION differ in length",
                        gltf_mesh.index()
                    )));
                }
                for (p, c) in positions.iter().zip(colors) {
                    let point = world.transform_point(&Point3::new(
                        f64::from(p[0]),
                        f64::from(p[1]),
                        f64::from(p[2]),
                    ));
                    mesh.positions.push(point.coords);
                    mesh.colors.push(c);
                }
                let indices: Vec<u32> = match reader.read_indices() {
                    Some(indices) => indices.into_u32().collect(),
                    None => (0..positions.len() as u32).collect(),
                };
                for tri in indices.chunks_exact(3) {
                    mesh.triangles
                        .push([base + tri[0], base + tri[1], base + tri[2]]);
                }
            }
        }
        stack.extend(node.children().map(|child| (child, world)));
    }
    Ok(mesh)
}
