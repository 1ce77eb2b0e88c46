//! Fitting a posed mesh to observed first-frame points: rigid ICP, then
//! as-rigid-as-possible deformation (Sorkine & Alexa 2007).
//!
//! Data term: each observed point is tied to its closest point on the
//! current surface, written as barycentric weights of a triangle's vertices,
//! so points anywhere on a face pull without the bias of nearest-vertex
//! matching. Observations cover only the visible side; matching from the
//! observations to the mesh (not the reverse) keeps the hidden side free.
//!
//! ARAP energy with uniform edge weights over the welded mesh:
//! `Σ_i Σ_{j∈N(i)} |(p'_i − p'_j) − R_i (p_i − p_j)|² + λ Σ_k |Σ_v b_kv p'_v − q_k|²`,
//! alternating the local step (each `R_i` by Procrustes) and the global step
//! (one symmetric positive definite solve for all `p'`, dense Cholesky:
//! prior meshes are a few thousand vertices at most, [`MAX_ARAP_VERTICES`]).

use nalgebra::{DMatrix, Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3};

use crate::PriorError;
use dm_splat::lbs::procrustes_rotation;

/// The dense global solve is O(V³); above this the mesh should be decimated.
pub const MAX_ARAP_VERTICES: usize = 4000;
/// Tikhonov pull towards the current positions, keeping the system definite
/// where a connected component has no observations.
const ANCHOR_WEIGHT: f64 = 1e-6;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitOptions {
    /// Rigid ICP iterations before the deformation.
    pub rigid_iterations: usize,
    /// ARAP outer iterations (correspondences recomputed each time).
    pub arap_iterations: usize,
    /// Local/global alternations per outer iteration.
    pub arap_inner_iterations: usize,
    /// λ: weight of one observation relative to one edge.
    pub data_weight: f64,
    /// Observations farther than this from the surface are ignored (metres).
    pub max_distance_m: f64,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            rigid_iterations: 30,
            arap_iterations: 5,
            arap_inner_iterations: 3,
            data_weight: 0.1,
            max_distance_m: 0.02,
        }
    }
}

#[derive(Clone, Debug)]
pub struct FitResult {
    /// Welded vertices after rigid alignment and deformation (camera frame).
    pub vertices: Vec<Vector3<f64>>,
    /// The rigid pose after ICP (rest mesh → camera).
    pub rigid_pose: Isometry3<f64>,
    /// The rigid part of the deformed mesh (Kabsch of rest → deformed).
    pub deformed_pose: Isometry3<f64>,
    /// Median distance of the used observations to the surface, before
    /// (after PnP) and after the fit.
    pub median_distance_before_m: f64,
    pub median_distance_after_m: f64,
}

/// Aligns the welded rest mesh (`rest`, `triangles`), starting at `initial`
/// (rest → camera), to `observations` (camera frame).
pub fn fit_to_points(
    rest: &[Vector3<f64>],
    triangles: &[[u32; 3]],
    initial: &Isometry3<f64>,
    observations: &[Vector3<f64>],
    options: &FitOptions,
) -> Result<FitResult, PriorError> {
    if rest.len() > MAX_ARAP_VERTICES {
        return Err(PriorError::Fit(format!(
            "{} vertices after welding; ARAP's dense solve takes at most {MAX_ARAP_VERTICES} (decimate the mesh)",
            rest.len()
        )));
    }
    if observations.len() < 3 {
        return Err(PriorError::Fit(format!(
            "{} observed points; need at least 3",
            observations.len()
        )));
    }
    let mut pose = *initial;
    let posed = |pose: &Isometry3<f64>| {
        rest.iter()
            .map(|p| pose * nalgebra::Point3::from(*p))
            .map(|p| p.coords)
            .collect::<Vec<_>>()
    };
    let mut current = posed(&pose);
    let before = median(
        closest_points(&current, triangles, observations, options.max_distance_m)
            .iter()
            .map(|c| c.distance)
            .collect(),
    );

    // Rigid ICP: Kabsch between observations and their closest surface points.
    for _ in 0..options.rigid_iterations {
        let matches = closest_points(&current, triangles, observations, options.max_distance_m);
        if matches.len() < 3 {
            return Err(PriorError::Fit(format!(
                "only {} observed points within {} m of the posed mesh; the PnP pose is off",
                matches.len(),
                options.max_distance_m
            )));
        }
        let surface: Vec<Vector3<f64>> = matches.iter().map(|m| m.point).collect();
        let targets: Vec<Vector3<f64>> = matches
            .iter()
            .map(|m| observations[m.observation])
            .collect();
        let step = kabsch(&surface, &targets);
        pose = step * pose;
        current = posed(&pose);
    }
    let rigid_pose = pose;

    // ARAP deformation from the rigidly aligned mesh.
    let rest_edges = edges(rest.len(), triangles);
    let mut deformed = current.clone();
    for _ in 0..options.arap_iterations {
        let matches = closest_points(&deformed, triangles, observations, options.max_distance_m);
        let reference = deformed.clone();
        for _ in 0..options.arap_inner_iterations {
            deformed = arap_step(
                &current,
                &reference,
                &deformed,
                &rest_edges,
                triangles,
                observations,
                &matches,
                options.data_weight,
            )?;
        }
    }
    let after = median(
        closest_points(&deformed, triangles, observations, options.max_distance_m)
            .iter()
            .map(|c| c.distance)
            .collect(),
    );
    let deformed_pose = kabsch(rest, &deformed);
    Ok(FitResult {
        vertices: deformed,
        rigid_pose,
        deformed_pose,
        median_distance_before_m: before,
        median_distance_after_m: after,
    })
}

/// One local/global ARAP alternation. `shape` holds the rest edge vectors
/// (rigidly posed), `anchor` the positions the Tikhonov term pulls towards.
fn arap_step(
    shape: &[Vector3<f64>],
    anchor: &[Vector3<f64>],
    current: &[Vector3<f64>],
    neighbours: &[Vec<usize>],
    triangles: &[[u32; 3]],
    observations: &[Vector3<f64>],
    matches: &[SurfaceMatch],
    data_weight: f64,
) -> Result<Vec<Vector3<f64>>, PriorError> {
    let count = shape.len();
    let rotations: Vec<Matrix3<f64>> = (0..count)
        .map(|i| {
            let cross = neighbours[i].iter().fold(Matrix3::zeros(), |sum, &j| {
                sum + (current[i] - current[j]) * (shape[i] - shape[j]).transpose()
            });
            procrustes_rotation(&cross)
        })
        .collect();
    let mut system = DMatrix::<f64>::zeros(count, count);
    let mut rhs = DMatrix::<f64>::zeros(count, 3);
    for i in 0..count {
        system[(i, i)] += ANCHOR_WEIGHT;
        let anchor_term = anchor[i] * ANCHOR_WEIGHT;
        let mut row = anchor_term;
        for &j in &neighbours[i] {
            system[(i, i)] += 1.0;
            system[(i, j)] -= 1.0;
            row += (rotations[i] + rotations[j]) * (shape[i] - shape[j]) * 0.5;
        }
        for k in 0..3 {
            rhs[(i, k)] += row[k];
        }
    }
    for matched in matches {
        let vertices = triangles[matched.triangle].map(|v| v as usize);
        let target = observations[matched.observation];
        for a in 0..3 {
            for b in 0..3 {
                system[(vertices[a], vertices[b])] +=
                    data_weight * matched.weights[a] * matched.weights[b];
            }
            for k in 0..3 {
                rhs[(vertices[a], k)] += data_weight * matched.weights[a] * target[k];
            }
        }
    }
    let solution = system
        .cholesky()
        .ok_or_else(|| PriorError::Fit("ARAP system is not positive definite".into()))?
        .solve(&rhs);
    Ok((0..count)
        .map(|i| Vector3::new(solution[(i, 0)], solution[(i, 1)], solution[(i, 2)]))
        .collect())
}

/// Each vertex's neighbours over the triangle edges.
fn edges(count: usize, triangles: &[[u32; 3]]) -> Vec<Vec<usize>> {
    let mut neighbours = vec![Vec::new(); count];
    for tri in triangles {
        for (a, b) in [(tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])] {
            let (a, b) = (a as usize, b as usize);
            if !neighbours[a].contains(&b) {
                neighbours[a].push(b);
                neighbours[b].push(a);
            }
        }
    }
    neighbours
}

/// An observation's closest surface point.
#[derive(Clone, Copy, Debug)]
struct SurfaceMatch {
    observation: usize,
    triangle: usize,
    weights: [f64; 3],
    point: Vector3<f64>,
    distance: f64,
}

/// Closest surface points of the observations within `max_distance`.
fn closest_points(
    vertices: &[Vector3<f64>],
    triangles: &[[u32; 3]],
    observations: &[Vector3<f64>],
    max_distance: f64,
) -> Vec<SurfaceMatch> {
    observations
        .iter()
        .enumerate()
        .filter_map(|(observation, q)| {
            let mut best: Option<SurfaceMatch> = None;
            for (triangle, tri) in triangles.iter().enumerate() {
                let [a, b, c] = tri.map(|v| vertices[v as usize]);
                let weights = closest_on_triangle(q, &a, &b, &c);
                let point = a * weights[0] + b * weights[1] + c * weights[2];
                let distance = (point - q).norm();
                if best.is_none_or(|m| distance < m.distance) {
                    best = Some(SurfaceMatch {
                        observation,
                        triangle,
                        weights,
                        point,
                        distance,
                    });
                }
            }
            best.filter(|m| m.distance <= max_distance)
        })
        .collect()
}

/// Barycentric weights of the point of triangle abc closest to p (Ericson,
/// Real-Time Collision Detection, 5.1.5).
fn closest_on_triangle(
    p: &Vector3<f64>,
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    c: &Vector3<f64>,
) -> [f64; 3] {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(&ap), ac.dot(&ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return [1.0, 0.0, 0.0];
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(&bp), ac.dot(&bp));
    if d3 >= 0.0 && d4 <= d3 {
        return [0.0, 1.0, 0.0];
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return [1.0 - v, v, 0.0];
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(&cp), ac.dot(&cp));
    if d6 >= 0.0 && d5 <= d6 {
        return [0.0, 0.0, 1.0];
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return [1.0 - w, 0.0, w];
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return [0.0, 1.0 - w, w];
    }
    let denominator = 1.0 / (va + vb + vc);
    let (v, w) = (vb * denominator, vc * denominator);
    [1.0 - v - w, v, w]
}

/// The rigid motion taking `from` onto `to` in least squares (Kabsch).
pub fn kabsch(from: &[Vector3<f64>], to: &[Vector3<f64>]) -> Isometry3<f64> {
    let count = from.len().min(to.len()).max(1) as f64;
    let centre_from = from.iter().sum::<Vector3<f64>>() / count;
    let centre_to = to.iter().sum::<Vector3<f64>>() / count;
    let cross = from.iter().zip(to).fold(Matrix3::zeros(), |sum, (a, b)| {
        sum + (b - centre_to) * (a - centre_from).transpose()
    });
    let rotation = UnitQuaternion::from_matrix(&procrustes_rotation(&cross));
    let translation = centre_to - rotation * centre_from;
    Isometry3::from_parts(Translation3::from(translation), rotation)
}

fn median(mut values: Vec<f64>) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let middle = (values.len() - 1) / 2;
    *values.select_nth_unstable_by(middle, f64::total_cmp).1
}
