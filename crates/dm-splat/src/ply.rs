//! Gaussians in the standard 3DGS PLY layout (binary little-endian), so
//! other splat viewers open them.
//!
//! Written properties, all `float`, in this order: `x y z nx ny nz f_dc_0
//! f_dc_1 f_dc_2 opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3`.
//! As in 3DGS: `opacity` is the logit, `scale_*` are log standard
//! deviations, `rot_*` is the quaternion `(w, x, y, z)`, normals are zero
//! and the colour is the degree-0 spherical-harmonic coefficient
//! `f_dc = (rgb − 0.5) / C0`. Reading accepts any `float` vertex properties
//! in any order (e.g. a 3DGS file with `f_rest_*`); the higher-order
//! coefficients are ignored (degree-0 colour only).

use std::io::{BufRead, BufReader, BufWriter, Read, Seek, Write};
use std::path::Path;

use dm_mpm::real::Real;
use nalgebra::Vector3;

use crate::{Gaussians, SplatError};

/// Degree-0 real spherical-harmonic constant `1 / (2 √π)`.
pub const SH_C0: f64 = 0.282_094_791_773_878_14;

const PROPERTIES: [&str; 17] = [
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
    "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
];

/// Writes `gaussians` to `path` (through a temporary file renamed into
/// place, so a reader never sees a partial file).
pub fn write_ply<T: Real>(path: &Path, gaussians: &Gaussians<T>) -> Result<(), SplatError> {
    gaussians.validate()?;
    let io_err = |source| SplatError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut tmp_name = path.as_os_str().to_owned();
    tmp_name.push(".tmp");
    let tmp = std::path::PathBuf::from(tmp_name);
    {
        let file = std::fs::File::create(&tmp).map_err(io_err)?;
        let mut w = BufWriter::new(file);
        let mut header = format!(
            "ply\nformat binary_little_endian 1.0\nelement vertex {}\n",
            gaussians.len()
        );
        for name in PROPERTIES {
            header.push_str(&format!("property float {name}\n"));
        }
        header.push_str("end_header\n");
        w.write_all(header.as_bytes()).map_err(io_err)?;
        for i in 0..gaussians.len() {
            let m = &gaussians.means[i];
            let s = &gaussians.log_scales[i];
            let q = &gaussians.rotations[i];
            let c = &gaussians.colors[i];
            let dc = |v: T| (v.to_f64() - 0.5) / SH_C0;
            let row: [f64; 17] = [
                m.x.to_f64(),
                m.y.to_f64(),
                m.z.to_f64(),
                0.0,
                0.0,
                0.0,
                dc(c.x),
                dc(c.y),
                dc(c.z),
                gaussians.opacity_logits[i].to_f64(),
                s.x.to_f64(),
                s.y.to_f64(),
                s.z.to_f64(),
                q[0].to_f64(),
                q[1].to_f64(),
                q[2].to_f64(),
                q[3].to_f64(),
            ];
            for v in row {
                w.write_all(&(v as f32).to_le_bytes()).map_err(io_err)?;
            }
        }
        w.flush().map_err(io_err)?;
    }
    std::fs::rename(&tmp, path).map_err(io_err)
}

/// The vertex element of a binary little-endian PLY file with float
/// properties: their names and the raw rows.
struct VertexTable {
    properties: Vec<String>,
    data: Vec<u8>,
}

impl VertexTable {
    /// Column of property `name`.
    fn column(&self, name: &str) -> Option<usize> {
        self.properties.iter().position(|p| p == name)
    }

    fn rows(&self) -> std::slice::ChunksExact<'_, u8> {
        self.data.chunks_exact((self.properties.len() * 4).max(1))
    }
}

fn read_f32(row: &[u8], col: usize) -> f32 {
    f32::from_le_bytes([
        row[4 * col],
        row[4 * col + 1],
        row[4 * col + 2],
        row[4 * col + 3],
    ])
}

fn read_vertex_table(path: &Path) -> Result<VertexTable, SplatError> {
    let ply_err = |message: String| SplatError::Ply {
        path: path.to_path_buf(),
        message,
    };
    let io_err = |source| SplatError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::open(path).map_err(io_err)?;
    let mut reader = BufReader::new(file);
    let mut line = String::new();
    let mut next_line = |reader: &mut BufReader<std::fs::File>| -> Result<String, SplatError> {
        line.clear();
        let n = reader.read_line(&mut line).map_err(io_err)?;
        if n == 0 {
            return Err(ply_err("header ends before end_header".into()));
        }
        Ok(line.trim_end().to_string())
    };
    if next_line(&mut reader)? != "ply" {
        return Err(ply_err("not a PLY file (first line is not 'ply')".into()));
    }
    let mut count: Option<usize> = None;
    let mut properties: Vec<String> = Vec::new();
    let mut in_vertex = false;
    loop {
        let l = next_line(&mut reader)?;
        let words: Vec<&str> = l.split_whitespace().collect();
        match words.as_slice() {
            ["end_header"] => break,
            ["format", "binary_little_endian", _] => {}
            ["format", other, _] => {
                return Err(ply_err(format!(
                    "format {other} not supported (binary_little_endian only)"
                )));
            }
            ["comment", ..] | ["obj_info", ..] => {}
            ["element", "vertex", n] => {
                count = Some(
                    n.parse()
                        .map_err(|_| ply_err(format!("bad vertex count {n}")))?,
                );
                in_vertex = true;
            }
            ["element", name, _] => {
                if count.is_some() {
                    // Elements after the vertices are never read.
                    in_vertex = false;
                } else {
                    return Err(ply_err(format!(
                        "element {name} before vertex not supported"
                    )));
                }
            }
            ["property", kind, name] if in_vertex => {
                if *kind != "float" && *kind != "float32" {
                    return Err(ply_err(format!(
                        "vertex property {name} is {kind}; only float is supported"
                    )));
                }
                properties.push((*name).to_string());
            }
            ["property", ..] => {}
            _ => return Err(ply_err(format!("unexpected header line '{l}'"))),
        }
    }
    let count = count.ok_or_else(|| ply_err("no vertex element".into()))?;
    let stride = properties.len() * 4;
    let needed = count
        .checked_mul(stride)
        .ok_or_else(|| ply_err("vertex count too large".into()))?;
    // Check against the file size before allocating: a corrupt header must
    // not ask for terabytes.
    let header_len = reader.stream_position().map_err(io_err)?;
    let file_len = reader.get_ref().metadata().map_err(io_err)?.len();
    if file_len.saturating_sub(header_len) < needed as u64 {
        return Err(ply_err(format!(
            "vertex data shorter than {count} vertices ({} bytes after the header, {needed} needed)",
            file_len.saturating_sub(header_len)
        )));
    }
    let mut data = vec![0u8; needed];
    reader
        .read_exact(&mut data)
        .map_err(|e| ply_err(format!("vertex data shorter than {count} vertices: {e}")))?;
    Ok(VertexTable { properties, data })
}

/// The vertex positions (x, y, z) of a PLY point cloud (binary
/// little-endian, float vertex properties), metres.
pub fn read_ply_points(path: &Path) -> Result<Vec<[f64; 3]>, SplatError> {
    let table = read_vertex_table(path)?;
    let columns = ["x", "y", "z"].map(|n| table.column(n));
    let [Some(x), Some(y), Some(z)] = columns else {
        return Err(SplatError::Ply {
            path: path.to_path_buf(),
            message: "missing vertex property x, y or z".into(),
        });
    };
    Ok(table
        .rows()
        .map(|row| [x, y, z].map(|c| f64::from(read_f32(row, c))))
        .collect())
}

/// Reads Gaussians from a 3DGS PLY file (binary little-endian, float
/// vertex properties including at least the seventeen written by
/// [`write_ply`] minus the normals).
pub fn read_ply<T: Real>(path: &Path) -> Result<Gaussians<T>, SplatError> {
    let table = read_vertex_table(path)?;
    let column = |name: &str| {
        table.column(name).ok_or_else(|| SplatError::Ply {
            path: path.to_path_buf(),
            message: format!("missing vertex property {name}"),
        })
    };
    let required: Vec<usize> = PROPERTIES
        .iter()
        .filter(|n| !n.starts_with('n'))
        .map(|n| column(n))
        .collect::<Result<_, _>>()?;
    let mut gaussians = Gaussians::default();
    for row in table.rows() {
        let value = |k: usize| T::lit(f64::from(read_f32(row, required[k])));
        // `required` follows PROPERTIES without the three normals.
        let rgb = |k: usize| T::lit(value(k).to_f64() * SH_C0 + 0.5);
        gaussians.push(
            Vector3::new(value(0), value(1), value(2)),
            Vector3::new(value(7), value(8), value(9)),
            [value(10), value(11), value(12), value(13)],
            value(6),
            Vector3::new(rgb(3), rgb(4), rgb(5)),
        );
    }
    gaussians.validate()?;
    Ok(gaussians)
}
