//! Unit tests of the pure functions of dm-mpm: constitutive experts, 3x3
//! decompositions, material patches and bounds, the B-spline stencil, the
//! grid boundary conditions, actuator couplings and config validation.

mod common;

use common::{random_f, random_rotation, rel_err, rng, uniform, with_singular_values};
use dm_mpm::actuators::Actuators;
use dm_mpm::experts::{
    Expert, expert_stress, fixed_corotated, lame, mixture_kirchhoff, mixture_stress, neo_hookean,
    neo_hookean_kirchhoff, st_venant_kirchhoff,
};
use dm_mpm::grid::{Grid, offsets, stencil};
use dm_mpm::grid_update::grid_update;
use dm_mpm::material::{MaterialBounds, MaterialPatches, PatchParams, sigmoid, softmax3};
use dm_mpm::neighbors::{PointIndex, farthest_point_sampling};
use dm_mpm::real::{Lane4, Mat3, Real, Vec3, cast_mat};
use dm_mpm::state::Consts;
use dm_mpm::svd::{
    clamp_singular_values, polar_rotation, singular_values_surely_within, svd3, symmetric_eigen,
    symmetric_eigenvalues,
};
use dm_mpm::viscosity::ViscousSolver;
use dm_mpm::{
    ActuatorConfig, ActuatorMode, FloorConfig, ParticleMaterial, PhysicsConfig, SimError, World,
};

// ---------------------------------------------------------------- tolerances

/// f64 round-off on O(1) matrix products, amplified by a handful of ops.
const F64_RTOL: f64 = 1e-12;
/// f64 stress through the polar/Jacobi iterations (converged to ~1e-14).
const F64_STRESS_RTOL: f64 = 1e-10;
/// f32 round-off on O(1) entries after an iterative decomposition.
const F32_RTOL: f64 = 2e-5;
/// Linearised (small-strain) stress vs the nonlinear experts: O(eps) error.
const LINEARISATION_RTOL_PER_STRAIN: f64 = 5.0;
/// Slack for log/exp round trips of material bounds.
const BOUNDS_RTOL: f64 = 1e-12;

const E: f64 = 1e5; // Pa
const NU: f64 = 0.3;

fn all_experts(f: &Mat3<f64>, mu: f64, lambda: f64) -> [Mat3<f64>; 3] {
    Expert::ALL.map(|e| expert_stress(e, f, mu, lambda))
}

// ---------------------------------------------------------------- experts

#[test]
fn lame_matches_textbook_values() {
    let (mu, lambda) = lame(1e5_f64, 0.3);
    // mu = E / (2 (1 + nu)) = 1e5 / 2.6; lambda = E nu / ((1 + nu)(1 - 2 nu)) = 3e4 / 0.52.
    assert!((mu - 38_461.538_461_538_46).abs() < 1e-8, "mu = {mu}");
    assert!(
        (lambda - 57_692.307_692_307_69).abs() < 1e-8,
        "lambda = {lambda}"
    );
    let (mu0, lambda0) = lame(2e5_f64, 0.0);
    assert_eq!(lambda0, 0.0);
    assert_eq!(mu0, 1e5);
}

#[test]
fn every_expert_is_stress_free_at_identity() {
    let (mu, lambda) = lame(E, NU);
    let id = Mat3::<f64>::identity();
    for (k, p) in all_experts(&id, mu, lambda).iter().enumerate() {
        assert!(p.amax() == 0.0, "expert {k}: P(I) = {p}");
    }
    let tau = mixture_kirchhoff(&id, mu, lambda, &[0.2, 0.5, 0.3]);
    assert!(tau.amax() == 0.0, "mixture Kirchhoff at I = {tau}");
    // A pure rotation is stress free too (frame indifference).
    let q = random_rotation(&mut rng(1));
    for (k, p) in all_experts(&q, mu, lambda).iter().enumerate() {
        assert!(p.amax() < F64_STRESS_RTOL * mu, "expert {k}: P(Q) = {p}");
    }
}

#[test]
fn experts_are_rotation_equivariant() {
    let (mu, lambda) = lame(E, NU);
    let mut r = rng(2);
    for _ in 0..200 {
        let f = random_f(&mut r, 0.6, 1.6);
        let q = random_rotation(&mut r);
        let p = all_experts(&f, mu, lambda);
        let p_rot = all_experts(&(q * f), mu, lambda);
        for k in 0..3 {
            let err = rel_err(&p_rot[k], &(q * p[k]));
            assert!(
                err < F64_STRESS_RTOL,
                "expert {k}: P(QF) vs Q P(F): {err:e}"
            );
        }
    }
}

#[test]
fn experts_match_closed_form_for_diagonal_stretch() {
    let (mu, lambda) = lame(E, NU);
    let mut r = rng(3);
    for _ in 0..100 {
        let s = [0; 3].map(|_| uniform(&mut r, 0.6, 1.6));
        let f = Mat3::from_diagonal(&Vec3::new(s[0], s[1], s[2]));
        let j = s[0] * s[1] * s[2];
        let sum_sq = s.iter().map(|x| x * x).sum::<f64>();
        let nh = s.map(|a| mu * (a - 1.0 / a) + lambda * j.ln() / a);
        let fcr = s.map(|a| 2.0 * mu * (a - 1.0) + lambda * (j - 1.0) * j / a);
        let stvk = s.map(|a| a * (mu * (a * a - 1.0) + 0.5 * lambda * (sum_sq - 3.0)));
        let expected = [nh, fcr, stvk].map(|d| Mat3::from_diagonal(&Vec3::new(d[0], d[1], d[2])));
        let got = [
            neo_hookean(&f, mu, lambda),
            fixed_corotated(&f, mu, lambda),
            st_venant_kirchhoff(&f, mu, lambda),
        ];
        for k in 0..3 {
            let err = (got[k] - expected[k]).amax() / mu;
            assert!(err < F64_STRESS_RTOL, "expert {k} at {s:?}: {err:e}");
        }
    }
}

#[test]
fn experts_agree_with_linear_elasticity_at_small_strain() {
    let (mu, lambda) = lame(E, NU);
    let eps = 1e-4;
    let tol = LINEARISATION_RTOL_PER_STRAIN * eps;
    // Uniaxial strain: P_xx = (lambda + 2 mu) eps, P_yy = P_zz = lambda eps.
    let f = Mat3::from_diagonal(&Vec3::new(1.0 + eps, 1.0, 1.0));
    for (k, p) in all_experts(&f, mu, lambda).iter().enumerate() {
        let pxx = (lambda + 2.0 * mu) * eps;
        assert!((p[(0, 0)] / pxx - 1.0).abs() < tol, "expert {k}: {p}");
        assert!(
            (p[(1, 1)] / (lambda * eps) - 1.0).abs() < tol,
            "expert {k}: {p}"
        );
    }
    // Uniaxial stress (lateral contraction nu eps): P_xx = E eps, P_yy ~ 0.
    let f = Mat3::from_diagonal(&Vec3::new(1.0 + eps, 1.0 - NU * eps, 1.0 - NU * eps));
    for (k, p) in all_experts(&f, mu, lambda).iter().enumerate() {
        assert!((p[(0, 0)] / (E * eps) - 1.0).abs() < tol, "expert {k}: {p}");
        assert!(p[(1, 1)].abs() < tol * E * eps, "expert {k}: {p}");
    }
    // Simple shear: P_xy = mu gamma.
    let mut f = Mat3::identity();
    f[(0, 1)] = eps;
    for (k, p) in all_experts(&f, mu, lambda).iter().enumerate() {
        assert!(
            (p[(0, 1)] / (mu * eps) - 1.0).abs() < tol,
            "expert {k}: {p}"
        );
    }
}

#[test]
fn kirchhoff_forms_equal_piola_times_f_transpose() {
    let (mu, lambda) = lame(E, NU);
    let mut r = rng(4);
    let weight_sets = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for i in 0..200 {
        let f = random_f(&mut r, 0.5, 2.0);
        let w = if i < 3 {
            weight_sets[i]
        } else {
            let raw = [0; 3].map(|_| uniform(&mut r, 0.0, 1.0));
            let s: f64 = raw.iter().sum();
            raw.map(|x| x / s)
        };
        let expected = mixture_stress(&f, mu, lambda, &w) * f.transpose();
        let tau = mixture_kirchhoff(&f, mu, lambda, &w);
        let err = rel_err(&tau, &expected);
        assert!(err < F64_STRESS_RTOL, "weights {w:?}: {err:e}");
        let nh = neo_hookean_kirchhoff(&f, mu, lambda);
        let err = rel_err(&nh, &(neo_hookean(&f, mu, lambda) * f.transpose()));
        assert!(err < F64_STRESS_RTOL, "NH Kirchhoff: {err:e}");
    }
}

#[test]
fn mixture_is_the_weighted_sum_of_experts() {
    let (mu, lambda) = lame(E, NU);
    let mut r = rng(5);
    for _ in 0..50 {
        let f = random_f(&mut r, 0.6, 1.6);
        let w = [0.5, 0.3, 0.2];
        let p = all_experts(&f, mu, lambda);
        let expected = p[0] * w[0] + p[1] * w[1] + p[2] * w[2];
        assert!(rel_err(&mixture_stress(&f, mu, lambda, &w), &expected) < F64_RTOL);
        // A single expert's weight triple reproduces that expert exactly.
        for (k, single) in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
            .iter()
            .enumerate()
        {
            assert_eq!(mixture_stress(&f, mu, lambda, single), p[k]);
        }
    }
}

#[test]
fn f32_experts_match_f64() {
    let (mu, lambda) = lame(E, NU);
    let mut r = rng(6);
    for _ in 0..100 {
        let f = random_f(&mut r, 0.6, 1.6);
        let f32m: Mat3<f32> = cast_mat(&f);
        let f64m: Mat3<f64> = cast_mat(&f32m); // the same input in both precisions
        let w = [0.5, 0.3, 0.2];
        let t32 = mixture_kirchhoff(&f32m, mu as f32, lambda as f32, &w.map(|x| x as f32));
        let t64 = mixture_kirchhoff(&f64m, mu, lambda, &w);
        // Scale by mu: the stress of a near-rest F is small against round-off of mu F Fᵀ.
        let err = (cast_mat::<f32, f64>(&t32) - t64).amax() / mu;
        assert!(err < F32_RTOL, "f32 vs f64 Kirchhoff: {err:e}");
    }
}

// ---------------------------------------------------------------- svd

fn check_svd<T: Real>(f: &Mat3<f64>, tol: f64) {
    let ft: Mat3<T> = cast_mat(f);
    let s = svd3(&ft);
    let (u, v): (Mat3<f64>, Mat3<f64>) = (cast_mat(&s.u), cast_mat(&s.v));
    let sigma = Vec3::new(s.sigma.x.to_f64(), s.sigma.y.to_f64(), s.sigma.z.to_f64());
    let f_in: Mat3<f64> = cast_mat(&ft);
    let rebuilt = u * Mat3::from_diagonal(&sigma) * v.transpose();
    assert!(rel_err(&rebuilt, &f_in) < tol, "F = U S Vᵀ fails for {f}");
    for (name, q) in [("U", u), ("V", v)] {
        assert!(
            rel_err(&(q.transpose() * q), &Mat3::identity()) < tol,
            "{name} not orthogonal for {f}"
        );
        assert!(
            (q.determinant() - 1.0).abs() < tol,
            "{name} not proper for {f}"
        );
    }
    // Sorted up to round-off (repeated singular values may swap by an ulp).
    let slack = tol * sigma.x;
    assert!(
        sigma.x >= sigma.y - slack && sigma.y >= sigma.z.abs() - slack,
        "sigma not sorted: {sigma}"
    );
    assert_eq!(sigma.z < 0.0, f_in.determinant() < 0.0, "sign of sigma_3");
}

#[test]
fn svd_reconstructs_random_matrices() {
    let mut r = rng(7);
    for _ in 0..300 {
        let f = random_f(&mut r, 0.5, 2.0);
        check_svd::<f64>(&f, F64_RTOL);
        check_svd::<f32>(&f, F32_RTOL);
        // Singular values match the ones the matrix was built with.
        let expected = {
            let mut s = svd3(&f).sigma;
            s.as_mut_slice().sort_by(|a, b| b.total_cmp(a));
            s
        };
        let mut sv = nalgebra::SVD::new(f, false, false).singular_values;
        sv.as_mut_slice().sort_by(|a, b| b.total_cmp(a));
        assert!(
            (expected - sv).amax() < F64_RTOL,
            "{expected} vs nalgebra {sv}"
        );
    }
    // Reflections: det F < 0 puts the sign on the smallest singular value.
    for _ in 0..50 {
        let f = random_f(&mut r, 0.5, 2.0) * Mat3::from_diagonal(&Vec3::new(1.0, 1.0, -1.0));
        check_svd::<f64>(&f, F64_RTOL);
    }
}

#[test]
fn svd_handles_degenerate_matrices() {
    let mut r = rng(8);
    let q = random_rotation(&mut r);
    let cases = [
        Mat3::identity(),
        q,
        q * 1.3,
        Mat3::from_diagonal(&Vec3::new(2.0, 1.0, 1.0)),
        Mat3::from_diagonal(&Vec3::new(0.5, 0.5, 1.5)),
        with_singular_values(&mut r, [1.2, 1.2, 0.7]),
        with_singular_values(&mut r, [1.4, 0.8, 0.8]),
        with_singular_values(&mut r, [1.0, 1.0 + 1e-9, 0.8]),
        with_singular_values(&mut r, [1.0, 1.0 - 1e-7, 1.0 + 1e-7]),
    ];
    for f in &cases {
        check_svd::<f64>(f, F64_RTOL);
        check_svd::<f32>(f, F32_RTOL);
    }
    // A rank-deficient F still gives rotations (no NaN).
    let flat = Mat3::from_diagonal(&Vec3::new(1.0, 0.5, 0.0));
    let s = svd3(&flat);
    assert!(s.u.iter().chain(s.v.iter()).all(|x: &f64| x.is_finite()));
    assert!(
        rel_err(
            &(s.u * Mat3::from_diagonal(&s.sigma) * s.v.transpose()),
            &flat
        ) < F64_RTOL
    );
}

#[test]
fn polar_rotation_matches_svd_rotation() {
    let mut r = rng(9);
    for _ in 0..300 {
        let f = random_f(&mut r, 0.5, 2.0);
        let s = svd3(&f);
        let expected = s.u * s.v.transpose();
        let got = polar_rotation(&f);
        assert!(rel_err(&got, &expected) < F64_RTOL, "f64 polar of {f}");
        let f32m: Mat3<f32> = cast_mat(&f);
        let got32: Mat3<f64> = cast_mat(&polar_rotation(&f32m));
        assert!(rel_err(&got32, &expected) < F32_RTOL, "f32 polar of {f}");
    }
    // Degenerate inputs: identity, a rotation, a scaled rotation.
    let q = random_rotation(&mut r);
    for (f, expected) in [(Mat3::identity(), Mat3::identity()), (q, q), (q * 0.7, q)] {
        assert!(rel_err(&polar_rotation(&f), &expected) < F64_RTOL);
    }
}

#[test]
fn symmetric_eigen_solvers_match_construction() {
    let mut r = rng(10);
    let mut spectra: Vec<[f64; 3]> = (0..200)
        .map(|_| [0; 3].map(|_| uniform(&mut r, 0.25, 4.0)))
        .collect();
    spectra.extend([
        [1.0; 3],
        [2.0, 2.0, 0.5],
        [0.5, 3.0, 3.0],
        [1.0, 1.0 + 1e-10, 1.0],
    ]);
    for lam in spectra {
        let q = random_rotation(&mut r);
        let a = q * Mat3::from_diagonal(&Vec3::new(lam[0], lam[1], lam[2])) * q.transpose();
        let mut sorted = lam;
        sorted.sort_by(|x, y| y.total_cmp(x));
        let closed = symmetric_eigenvalues(&a);
        for i in 0..3 {
            assert!(
                (closed[i] - sorted[i]).abs() < F64_STRESS_RTOL * sorted[0],
                "closed form {closed:?} vs {sorted:?}"
            );
        }
        let (values, vectors) = symmetric_eigen(&a);
        let rebuilt = vectors * Mat3::from_diagonal(&values) * vectors.transpose();
        assert!(rel_err(&rebuilt, &a) < F64_RTOL, "Jacobi reconstruction");
        assert!(rel_err(&(vectors.transpose() * vectors), &Mat3::identity()) < F64_RTOL);
    }
}

#[test]
fn clamp_singular_values_projects_only_outside_values() {
    let (lo, hi) = (0.5, 2.0);
    // Keep away from the clamp limits: inside a tiny band the answer may go
    // either way by round-off, which is harmless.
    let band = 1e-3;
    let near_limit = |s: f64| (s - lo).abs() < band || (s - hi).abs() < band;
    let mut r = rng(11);
    let mut clamped_cases = 0;
    for _ in 0..500 {
        let s = [0; 3].map(|_| uniform(&mut r, 0.3, 3.0));
        if s.iter().any(|&x| near_limit(x)) {
            continue;
        }
        let f = with_singular_values(&mut r, s);
        let inside = s.iter().all(|&x| (lo..=hi).contains(&x));
        let result = clamp_singular_values(&f, lo, hi);
        assert_eq!(result.is_none(), inside, "sigma {s:?}");
        if singular_values_surely_within(&f, lo, hi) {
            assert!(inside, "Gershgorin test claimed {s:?} inside");
        }
        if let Some(g) = result {
            clamped_cases += 1;
            let mut want = s.map(|x| x.clamp(lo, hi));
            want.sort_by(|a, b| b.total_cmp(a));
            let got = svd3(&g).sigma;
            for i in 0..3 {
                assert!((got[i] - want[i]).abs() < F64_RTOL, "{got} vs {want:?}");
            }
            // The rotation is kept: only the stretch is projected.
            assert!(rel_err(&polar_rotation(&g), &polar_rotation(&f)) < F64_STRESS_RTOL);
        }
        // f32 makes the same decision.
        let f32m: Mat3<f32> = cast_mat(&f);
        assert_eq!(
            clamp_singular_values(&f32m, lo as f32, hi as f32).is_none(),
            inside
        );
    }
    assert!(
        clamped_cases > 100,
        "too few clamped samples: {clamped_cases}"
    );
    // Degenerate inputs: identity and rotations are inside; scaled identity is not.
    let q = random_rotation(&mut r);
    assert!(clamp_singular_values(&Mat3::<f64>::identity(), lo, hi).is_none());
    assert!(clamp_singular_values(&q, lo, hi).is_none());
    let g = clamp_singular_values(&(q * 3.0), lo, hi).expect("3 I must be clamped");
    assert!(rel_err(&g, &(q * 2.0)) < F64_RTOL);
    let g = clamp_singular_values(&(q * 0.1), lo, hi).expect("0.1 I must be clamped");
    assert!(rel_err(&g, &(q * 0.5)) < F64_RTOL);
}

// ---------------------------------------------------------------- material

#[test]
fn softmax3_is_a_distribution() {
    let mut r = rng(12);
    for _ in 0..200 {
        let l = [0; 3].map(|_| uniform(&mut r, -30.0, 30.0));
        let q = softmax3(&l);
        assert!((q.iter().sum::<f64>() - 1.0).abs() < F64_RTOL);
        assert!(q.iter().all(|&x| (0.0..=1.0).contains(&x)));
        // Order preserving.
        for i in 0..3 {
            for j in 0..3 {
                if l[i] > l[j] {
                    assert!(q[i] >= q[j]);
                }
            }
        }
    }
    let q = softmax3(&[1000.0, -1000.0, 0.0]);
    assert_eq!(q, [1.0, 0.0, 0.0]);
    let q = softmax3(&[0.0; 3]);
    assert!(q.iter().all(|&x| (x - 1.0 / 3.0).abs() < F64_RTOL));
}

#[test]
fn material_bounds_hold_for_any_raw_value_and_invert() {
    for bounds in [MaterialBounds::THIN, MaterialBounds::VOLUMETRIC] {
        let [elo, ehi] = bounds.youngs_pa;
        let [nlo, nhi] = bounds.poisson;
        for raw in [-1e6, -50.0, -3.0, -0.1, 0.0, 0.7, 4.0, 50.0, 1e6] {
            let e = bounds.youngs(raw);
            assert!(e >= elo * (1.0 - BOUNDS_RTOL) && e <= ehi * (1.0 + BOUNDS_RTOL));
            let nu = bounds.poisson(raw);
            assert!((nlo..=nhi).contains(&nu), "nu {nu}");
        }
        assert!(bounds.youngs(1.0) > bounds.youngs(0.0), "monotone");
        // Round trips inside the bounds.
        for t in [0.01, 0.2, 0.5, 0.9, 0.99] {
            let e = (elo.ln() + t * (ehi.ln() - elo.ln())).exp();
            let back = bounds.youngs(bounds.youngs_raw(e));
            assert!((back / e - 1.0).abs() < 1e-9, "E {e} -> {back}");
            let nu = nlo + t * (nhi - nlo);
            let back = bounds.poisson(bounds.poisson_raw(nu));
            assert!((back - nu).abs() < 1e-9, "nu {nu} -> {back}");
        }
        // Values outside the bounds map to finite raws at the edge.
        for e in [elo * 0.1, ehi * 10.0] {
            let raw = bounds.youngs_raw(e);
            assert!(raw.is_finite());
            let back = bounds.youngs(raw);
            assert!(back >= elo * (1.0 - BOUNDS_RTOL) && back <= ehi * (1.0 + BOUNDS_RTOL));
        }
    }
    assert_eq!(sigmoid(0.0), 0.5);
}

/// Brute-force reference of the patch blend: 3 nearest centres, 1/d weights.
fn reference_beta(p: &[f64; 3], centres: &[[f64; 3]]) -> Vec<(usize, f64)> {
    let mut d: Vec<(usize, f64)> = centres
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let d2: f64 = (0..3).map(|a| (p[a] - c[a]).powi(2)).sum();
            (i, d2.sqrt())
        })
        .collect();
    d.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
    d.truncate(3);
    if d[0].1 < 1e-9 {
        return vec![(d[0].0, 1.0)];
    }
    let total: f64 = d.iter().map(|x| 1.0 / x.1).sum();
    d.iter().map(|&(i, di)| (i, (1.0 / di) / total)).collect()
}

#[test]
fn material_patches_blend_with_normalised_inverse_distance() {
    let mut r = rng(13);
    let points: Vec<[f64; 3]> = (0..400)
        .map(|_| [0; 3].map(|_| uniform(&mut r, -0.1, 0.1)))
        .collect();
    for patch_count in [1, 2, 3, 16] {
        let patches = MaterialPatches::build(&points, patch_count);
        assert_eq!(patches.patch_count(), patch_count);
        assert_eq!(patches.beta.len(), points.len());
        for (p, (ids, beta)) in points
            .iter()
            .zip(patches.neighbours.iter().zip(&patches.beta))
        {
            assert!(
                (beta.iter().sum::<f64>() - 1.0).abs() < F64_RTOL,
                "{beta:?}"
            );
            assert!(beta.iter().all(|&b| b >= 0.0));
            assert!(ids.iter().all(|&i| (i as usize) < patch_count));
            let nonzero = beta.iter().filter(|&&b| b > 0.0).count();
            assert!(nonzero >= 1 && nonzero <= 3.min(patch_count));
            // Same blend as the definition in method.md §3.
            for (slot, (id, b)) in reference_beta(p, &patches.centres).into_iter().enumerate() {
                assert_eq!(ids[slot] as usize, id);
                assert!((beta[slot] - b).abs() < F64_RTOL);
            }
        }
        // Centres are input points; a particle on a centre takes it alone.
        for (c_idx, c) in patches.centres.iter().enumerate() {
            let i = points
                .iter()
                .position(|p| p == c)
                .expect("centre is a point");
            assert_eq!(patches.neighbours[i][0] as usize, c_idx);
            assert_eq!(patches.beta[i], [1.0, 0.0, 0.0]);
        }
    }
}

#[test]
fn material_patches_survive_lattices_and_duplicates() {
    // Many equal coordinates per axis, plus exact duplicates.
    let mut points = common::lattice([0.0; 3], [0.1, 0.1, 0.05], 0.01);
    points.extend_from_slice(&points.clone()[..50]);
    let patches = MaterialPatches::build(&points, 8);
    for beta in &patches.beta {
        assert!((beta.iter().sum::<f64>() - 1.0).abs() < F64_RTOL);
    }
    // Asking for more patches than points gives one patch per point.
    let few = &points[..2];
    let patches = MaterialPatches::build(few, 5);
    assert_eq!(patches.patch_count(), 2);
    assert!(patches.beta.iter().all(|b| b == &[1.0, 0.0, 0.0]));
}

#[test]
fn particle_fields_are_bounded_and_weights_sum_to_one() {
    let mut r = rng(14);
    let points: Vec<[f64; 3]> = (0..300)
        .map(|_| [0; 3].map(|_| uniform(&mut r, 0.0, 0.2)))
        .collect();
    let patches = MaterialPatches::build(&points, 10);
    let bounds = MaterialBounds::VOLUMETRIC;
    let params = PatchParams {
        youngs_raw: (0..10).map(|_| uniform(&mut r, -8.0, 8.0)).collect(),
        poisson_raw: (0..10).map(|_| uniform(&mut r, -8.0, 8.0)).collect(),
        logits: (0..10)
            .map(|_| [0; 3].map(|_| uniform(&mut r, -5.0, 5.0)))
            .collect(),
    };
    let (e, nu, w) = patches.particle_fields(&params, &bounds);
    assert_eq!((e.len(), nu.len(), w.len()), (300, 300, 300));
    for i in 0..300 {
        assert!(e[i] >= bounds.youngs_pa[0] * (1.0 - BOUNDS_RTOL));
        assert!(e[i] <= bounds.youngs_pa[1] * (1.0 + BOUNDS_RTOL));
        assert!(nu[i] >= bounds.poisson[0] && nu[i] <= bounds.poisson[1]);
        assert!(
            (w[i].iter().sum::<f64>() - 1.0).abs() < F64_RTOL,
            "{:?}",
            w[i]
        );
        assert!(w[i].iter().all(|&x| (0.0..=1.0).contains(&x)));
    }
    // Uniform parameters give exactly that material everywhere.
    let uniform = PatchParams::uniform(10, &bounds, 3e5, 0.3, [0.0, 0.0, 0.0]);
    let (e, nu, w) = patches.particle_fields(&uniform, &bounds);
    for i in 0..300 {
        assert!((e[i] / 3e5 - 1.0).abs() < 1e-9);
        assert!((nu[i] - 0.3).abs() < 1e-9);
        assert!(w[i].iter().all(|&x| (x - 1.0 / 3.0).abs() < F64_RTOL));
    }
    let material: ParticleMaterial<f32> = patches.particle_material(&uniform, &bounds);
    assert_eq!(material.len(), 300);
    assert!(!material.is_pure_neo_hookean());
    let nh = ParticleMaterial::<f32>::uniform(4, 1e5, 0.3, [1.0, 0.0, 0.0]);
    assert!(nh.is_pure_neo_hookean());
}

// ---------------------------------------------------------------- neighbours

#[test]
fn point_index_matches_brute_force() {
    let mut r = rng(15);
    let points: Vec<[f64; 3]> = (0..500)
        .map(|_| [0; 3].map(|_| uniform(&mut r, 0.0, 1.0)))
        .collect();
    let index = PointIndex::new(&points);
    assert_eq!(index.len(), 500);
    let dist = |a: &[f64; 3], b: &[f64; 3]| -> f64 {
        (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt()
    };
    for _ in 0..50 {
        let q = [0; 3].map(|_| uniform(&mut r, 0.0, 1.0));
        let mut all: Vec<(usize, f64)> = points
            .iter()
            .enumerate()
            .map(|(i, p)| (i, dist(p, &q)))
            .collect();
        all.sort_by(|a, b| a.1.total_cmp(&b.1));
        let near = index.nearest(&q, 5);
        assert_eq!(
            near.iter().map(|n| n.0).collect::<Vec<_>>(),
            all[..5].iter().map(|n| n.0).collect::<Vec<_>>()
        );
        let within = index.within(&q, 0.15);
        let expected: Vec<usize> = {
            let mut v: Vec<usize> = all.iter().filter(|n| n.1 <= 0.15).map(|n| n.0).collect();
            v.sort();
            v
        };
        assert_eq!(within.iter().map(|n| n.0).collect::<Vec<_>>(), expected);
    }
    assert!(PointIndex::new(&[]).nearest(&[0.0; 3], 3).is_empty());
}

#[test]
fn farthest_point_sampling_spreads_distinct_points() {
    let mut r = rng(16);
    let points: Vec<[f64; 3]> = (0..300)
        .map(|_| [0; 3].map(|_| uniform(&mut r, 0.0, 1.0)))
        .collect();
    let chosen = farthest_point_sampling(&points, 20);
    assert_eq!(chosen.len(), 20);
    let mut unique = chosen.clone();
    unique.sort();
    unique.dedup();
    assert_eq!(unique.len(), 20);
    // The second pick is the point farthest from the first.
    let d2 = |a: &[f64; 3], b: &[f64; 3]| (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>();
    let farthest = (0..300)
        .max_by(|&a, &b| {
            d2(&points[a], &points[chosen[0]]).total_cmp(&d2(&points[b], &points[chosen[0]]))
        })
        .expect("non-empty");
    assert_eq!(chosen[1], farthest);
    assert_eq!(farthest_point_sampling(&points, 1000).len(), 300);
    assert!(farthest_point_sampling(&[], 3).is_empty());
}

// ---------------------------------------------------------------- grid

#[test]
fn quadratic_stencil_reproduces_constants_and_linears() {
    // Partition of unity, zero first moment (momentum conservation of APIC)
    // and second moment dx²/4 I (the 4/dx² factor of MLS-MPM).
    let mut r = rng(17);
    let origin = Vec3::new(-0.3, 0.1, 0.2);
    let dx = 1.0 / 32.0;
    for _ in 0..200 {
        let x = origin + Vec3::from_fn(|_, _| uniform(&mut r, 2.0, 29.0)) * dx;
        let st = stencil(&x, &origin, 1.0 / dx, 32);
        let off = offsets::<f64>();
        let (mut w_sum, mut first, mut second) = (0.0, Vec3::zeros(), Mat3::zeros());
        for i in 0..3 {
            for j in 0..3 {
                for k in 0..3 {
                    let w = st.w[0][i] * st.w[1][j] * st.w[2][k];
                    assert!(w >= 0.0);
                    let node = origin
                        + Vec3::new(
                            (st.base[0] as f64 + off[i]) * dx,
                            (st.base[1] as f64 + off[j]) * dx,
                            (st.base[2] as f64 + off[k]) * dx,
                        );
                    let d = node - x;
                    w_sum += w;
                    first += d * w;
                    second += d * d.transpose() * w;
                }
            }
        }
        assert!((w_sum - 1.0).abs() < F64_RTOL);
        assert!(first.amax() < F64_RTOL * dx);
        assert!(rel_err(&second, &(Mat3::identity() * (dx * dx / 4.0))) < 1e-10);
        assert!(st.frac.iter().all(|&f| (0.5..1.5).contains(&f)));
    }
}

fn boundary_config() -> PhysicsConfig {
    let mut c = PhysicsConfig::volumetric([0.0, 0.0, -0.25], 1.0, [0.0, 0.0, 1.0]);
    c.grid_res = 16;
    c.position_clip = [0.1, 0.9];
    c.gravity = [0.0; 3];
    c.grid_damping = 1.0;
    c
}

/// Velocity at node `(i, j, k)` after one grid update of a single node.
fn updated_velocity(config: &PhysicsConfig, idx: [usize; 3], v: [f64; 3]) -> [f64; 3] {
    let k = Consts::<f64>::new(config, 1.0);
    let mut grid = Grid::<f64>::new(config.grid_res);
    let n = grid.index(idx[0], idx[1], idx[2]);
    let m = 2.0;
    grid.nodes[n] = Lane4::from_array([v[0] * m, v[1] * m, v[2] * m, m]);
    grid_update(&k, &mut grid, &mut ViscousSolver::default(), None);
    let out = grid.nodes[n].to_array();
    assert_eq!(out[3], m, "mass is kept");
    [out[0], out[1], out[2]]
}

#[test]
fn grid_update_applies_walls_floor_and_friction() {
    let mut c = boundary_config();
    c.floor = None;
    let res = c.grid_res;
    // Interior node: unchanged.
    assert_eq!(
        updated_velocity(&c, [8, 8, 8], [1.0, -2.0, 3.0]),
        [1.0, -2.0, 3.0]
    );
    // Walls stop outward motion only.
    assert_eq!(
        updated_velocity(&c, [0, 8, 8], [-1.0, 0.5, 0.0]),
        [0.0, 0.5, 0.0]
    );
    assert_eq!(
        updated_velocity(&c, [2, 8, 8], [1.0, 0.5, 0.0]),
        [1.0, 0.5, 0.0]
    );
    assert_eq!(
        updated_velocity(&c, [8, res - 3, 8], [0.0, 1.0, 0.0]),
        [0.0; 3]
    );
    assert_eq!(
        updated_velocity(&c, [8, res - 4, 8], [0.0, 1.0, 0.0]),
        [0.0, 1.0, 0.0]
    );
    // Gravity and damping.
    c.gravity = [0.0, 0.0, -10.0];
    c.grid_damping = 0.5;
    let v = updated_velocity(&c, [8, 8, 8], [0.0, 0.0, 1.0]);
    assert!((v[2] - (1.0 - 10.0 * c.dt) * 0.5).abs() < F64_RTOL);
    // The factor is per GRID_DAMPING_REFERENCE_DT: half the substep, its root.
    assert_eq!(c.dt, dm_mpm::GRID_DAMPING_REFERENCE_DT);
    c.dt /= 2.0;
    let v = updated_velocity(&c, [8, 8, 8], [0.0, 0.0, 1.0]);
    assert!((v[2] - (1.0 - 10.0 * c.dt) * 0.5f64.sqrt()).abs() < F64_RTOL);
    // Floor at z = 0 (node k = 4 with origin z = -0.25, dx = 1/16).
    let mut c = boundary_config();
    c.floor = Some(FloorConfig {
        up: [0.0, 0.0, 1.0],
        height: 0.0,
        margin: 0.0,
    });
    assert_eq!(
        updated_velocity(&c, [8, 8, 4], [0.3, 0.0, -1.0]),
        [0.3, 0.0, 0.0]
    );
    assert_eq!(
        updated_velocity(&c, [8, 8, 4], [0.3, 0.0, 1.0]),
        [0.3, 0.0, 1.0]
    );
    assert_eq!(
        updated_velocity(&c, [8, 8, 5], [0.3, 0.0, -1.0]),
        [0.3, 0.0, -1.0]
    );
    c.effects.floor_friction = 0.2;
    let v = updated_velocity(&c, [8, 8, 4], [0.3, 0.0, -1.0]);
    assert!((v[0] - 0.1).abs() < F64_RTOL && v[2] == 0.0, "{v:?}");
    let v = updated_velocity(&c, [8, 8, 4], [0.1, 0.0, -1.0]);
    assert_eq!(v, [0.0; 3], "static friction");
    // Light nodes are emptied.
    let k = Consts::<f64>::new(&c, 1.0);
    let mut grid = Grid::<f64>::new(c.grid_res);
    let n = grid.index(8, 8, 8);
    let m = 0.5 * k.empty_node_mass;
    grid.nodes[n] = Lane4::from_array([m, m, m, m]);
    grid_update(&k, &mut grid, &mut ViscousSolver::default(), None);
    assert_eq!(grid.nodes[n].to_array(), [0.0; 4]);
}

// ---------------------------------------------------------------- actuators

fn v3(p: [f64; 3]) -> Vec3<f64> {
    Vec3::new(p[0], p[1], p[2])
}

#[test]
fn actuator_couplings_follow_the_modes() {
    // Particles on a line; two anchors whose grasp balls overlap in the middle.
    let x: Vec<Vec3<f64>> = (0..11).map(|i| v3([i as f64 * 0.01, 0.0, 0.0])).collect();
    let anchors = [v3([0.03, 0.0, 0.005]), v3([0.07, 0.0, 0.005])];
    let config = |mode| ActuatorConfig {
        mode,
        kp: 100.0,
        kd: 10.0,
        grasp_radius: 0.035,
    };
    let mut dist = Actuators::<f64>::new(config(ActuatorMode::Distributed), x.len());
    dist.grasp(&x, &anchors, &[true, true]);
    let mut single = Actuators::<f64>::new(config(ActuatorMode::Single), x.len());
    single.grasp(&x, &anchors, &[true, true]);
    let mut inactive = Actuators::<f64>::new(config(ActuatorMode::Distributed), x.len());
    inactive.grasp(&x, &anchors, &[false, false]);
    assert_eq!(inactive.coupling_count(), 0);
    let within = |p: &Vec3<f64>, a: &Vec3<f64>| (p - a).norm() <= 0.035;
    let mut shared = 0;
    for (p, xp) in x.iter().enumerate() {
        let expected: Vec<usize> = (0..2).filter(|&a| within(xp, &anchors[a])).collect();
        let got: Vec<(usize, Vec3<f64>)> = dist.couplings_of(p).collect();
        assert_eq!(got.iter().map(|c| c.0).collect::<Vec<_>>(), expected);
        for (a, offset) in &got {
            assert!((offset - (anchors[*a] - xp)).amax() < F64_RTOL);
        }
        shared += usize::from(expected.len() == 2);
        let one: Vec<(usize, Vec3<f64>)> = single.couplings_of(p).collect();
        assert_eq!(one.len(), usize::from(!expected.is_empty()));
        if let Some(&(a, _)) = one.first() {
            let d = |b: usize| (xp - anchors[b]).norm();
            assert!(expected.iter().all(|&b| d(a) <= d(b)), "not the nearest");
        }
    }
    assert!(shared > 0, "the scene must exercise shared particles");
    assert_eq!(single.coupled_particle_count(), single.coupling_count());
    assert_eq!(
        dist.coupled_particle_count() + shared,
        dist.coupling_count()
    );

    // a_p = n^{-1/2} Σ_c [kp ((x_c - x_p) - o) + kd (v_c - v_p)].
    let shift = v3([0.0, 0.0, 0.01]);
    let moved = [anchors[0] + shift, anchors[1] + shift];
    let anchor_v = [v3([0.0, 0.0, 0.2]); 2];
    let v = vec![Vec3::zeros(); x.len()];
    let mut acc = vec![Vec3::zeros(); x.len()];
    dist.accelerations(&x, &v, &moved, &anchor_v, &mut acc);
    for (p, a) in acc.iter().enumerate() {
        let n = dist.couplings_of(p).count() as f64;
        let per = shift * 100.0 + anchor_v[0] * 10.0;
        let expected = if n > 0.0 {
            per * (n / n.sqrt())
        } else {
            Vec3::zeros()
        };
        assert!(
            (a - expected).amax() < F64_RTOL,
            "particle {p}: {a} vs {expected}"
        );
    }
    // Rigid: no forces; coupled particles are placed at the mean anchor target.
    let mut rigid = Actuators::<f64>::new(config(ActuatorMode::Rigid), x.len());
    rigid.grasp(&x, &anchors, &[true, true]);
    rigid.accelerations(&x, &v, &moved, &anchor_v, &mut acc);
    assert!(acc.iter().all(|a| a.amax() == 0.0));
    let (mut xr, mut vr) = (x.clone(), v.clone());
    rigid.enforce_rigid(&mut xr, &mut vr, &moved, &anchor_v);
    for p in 0..x.len() {
        let coupled = rigid.couplings_of(p).count() > 0;
        let want_x = if coupled { x[p] + shift } else { x[p] };
        let want_v = if coupled { anchor_v[0] } else { Vec3::zeros() };
        assert!((xr[p] - want_x).amax() < F64_RTOL && (vr[p] - want_v).amax() < F64_RTOL);
    }
}

// ---------------------------------------------------------------- config and inputs

#[test]
fn config_validation_names_the_bad_field() {
    let good = PhysicsConfig::volumetric([0.0; 3], 1.0, [0.0, 0.0, 1.0]);
    good.validate().expect("volumetric defaults are valid");
    PhysicsConfig::thin_object([0.0; 3], 1.0, [0.0, 1.0, 0.0])
        .validate()
        .expect("thin defaults are valid");
    assert_eq!(good.gravity, [0.0, 0.0, -9.8]);
    type Edit = Box<dyn Fn(&mut PhysicsConfig)>;
    let cases: Vec<(&str, Edit)> = vec![
        ("grid_res", Box::new(|c| c.grid_res = 4)),
        // A damaged model file must not allocate a grid without bound.
        ("grid_res", Box::new(|c| c.grid_res = 100_000)),
        ("domain_size", Box::new(|c| c.domain_size = -1.0)),
        ("dt", Box::new(|c| c.dt = f64::NAN)),
        ("substeps_per_frame", Box::new(|c| c.substeps_per_frame = 0)),
        ("wall_cells", Box::new(|c| c.wall_cells = 15)),
        ("position_clip", Box::new(|c| c.position_clip = [0.0, 1.0])),
        ("position_clip", Box::new(|c| c.grid_res = 16)), // 0.05 < 1.5 cells
        // Exactly 1.5 cells from the top face puts the stencil out of the grid.
        (
            "position_clip",
            Box::new(|c| c.position_clip = [0.1, 1.0 - 1.5 / 32.0]),
        ),
        ("svd_clamp", Box::new(|c| c.svd_clamp = [1.5, 2.0])),
        ("density", Box::new(|c| c.density = 0.0)),
        ("density", Box::new(|c| c.density = f64::NAN)),
        ("gravity", Box::new(|c| c.gravity[1] = f64::INFINITY)),
        (
            "floor.up",
            Box::new(|c| c.floor.as_mut().expect("floor").up = [0.0, 0.0, 2.0]),
        ),
        (
            "effects.viscosity",
            Box::new(|c| c.effects.viscosity = -1.0),
        ),
        (
            "effects.air_drag_linear",
            Box::new(|c| c.effects.air_drag_linear = f64::NAN),
        ),
        (
            "effects.plastic_yield",
            Box::new(|c| c.effects.plastic_yield = Some(0.0)),
        ),
        (
            "effects.force_field.uniform",
            Box::new(|c| c.effects.force_field.uniform[1] = f64::INFINITY),
        ),
        (
            "effects.force_field.axis_drag",
            Box::new(|c| c.effects.force_field.axis_drag[2] = -1.0),
        ),
        (
            "effects.force_field.axis_drag",
            Box::new(|c| c.effects.force_field.axis_drag[0] = 2.0 / c.dt),
        ),
        (
            "effects.force_field.attractor_stiffness",
            Box::new(|c| c.effects.force_field.attractor_stiffness = 1.0 / (c.dt * c.dt)),
        ),
        (
            "effects.force_field.attractor_point",
            Box::new(|c| c.effects.force_field.attractor_point[0] = f64::NAN),
        ),
    ];
    for (field, edit) in cases {
        let mut c = good.clone();
        edit(&mut c);
        match c.validate() {
            Err(SimError::InvalidConfig { field: f, .. }) => assert_eq!(f, field),
            other => panic!("{field}: expected InvalidConfig, got {other:?}"),
        }
    }
}

#[test]
fn world_rejects_bad_inputs() {
    let config = PhysicsConfig::volumetric([0.0; 3], 1.0, [0.0, 0.0, 1.0]);
    let points = vec![[0.5, 0.5, 0.5], [0.52, 0.5, 0.5]];
    let material = || ParticleMaterial::<f32>::uniform(2, 1e5, 0.3, [1.0, 0.0, 0.0]);
    let act = ActuatorConfig::default();
    let new = |pts: &[[f64; 3]], vol: f64, m: ParticleMaterial<f32>| {
        World::new(config.clone(), pts, vol, m, act)
    };
    assert!(matches!(
        new(&[], 1e-6, material()),
        Err(SimError::InvalidInput(_))
    ));
    let nan = [[0.5, f64::NAN, 0.5], [0.5, 0.5, 0.5]];
    assert!(matches!(
        new(&nan, 1e-6, material()),
        Err(SimError::InvalidInput(_))
    ));
    assert!(matches!(
        new(&points, 0.0, material()),
        Err(SimError::InvalidInput(_))
    ));
    let short = ParticleMaterial::<f32>::uniform(1, 1e5, 0.3, [1.0, 0.0, 0.0]);
    assert!(matches!(
        new(&points, 1e-6, short),
        Err(SimError::InvalidInput(_))
    ));
    let mut bad_config = config.clone();
    bad_config.dt = 0.0;
    assert!(matches!(
        World::new(bad_config, &points, 1e-6, material(), act),
        Err(SimError::InvalidConfig { .. })
    ));
    let mut world = new(&points, 1e-6, material()).expect("valid world");
    assert!(world.set_velocities(&[[0.0; 3]]).is_err());
    let three = ParticleMaterial::<f32>::uniform(3, 1e5, 0.3, [1.0, 0.0, 0.0]);
    assert!(world.set_material(three).is_err());
    let mut ragged = material();
    ragged.expert_weights.pop();
    assert!(
        world.set_material(ragged).is_err(),
        "ragged material must be rejected"
    );
    assert!(matches!(
        world.step_frame(&[[0.5; 3]], &[[0.5; 3], [0.5; 3]], &[true]),
        Err(SimError::InvalidInput(_))
    ));
    assert!(matches!(
        world.step_frame(&[[f64::NAN; 3]], &[[0.5; 3]], &[true]),
        Err(SimError::InvalidInput(_))
    ));
}

/// A block of `length` × 4 × 4 particles 2 cm apart above the floor of a
/// unit volumetric domain, with the default hands: (physics, particles,
/// actuators, particle volume).
fn small_block(length: usize) -> (PhysicsConfig, Vec<[f64; 3]>, ActuatorConfig, f64) {
    let config = PhysicsConfig::volumetric([0.0; 3], 1.0, [0.0, 0.0, 1.0]);
    let mut points = Vec::new();
    for i in 0..length {
        for j in 0..4 {
            for k in 0..4 {
                points.push([
                    0.45 + 0.02 * i as f64,
                    0.45 + 0.02 * j as f64,
                    0.2 + 0.02 * k as f64,
                ]);
            }
        }
    }
    (config, points, ActuatorConfig::default(), 0.02f64.powi(3))
}

/// A released world keeps its particle state and no hand holds it: it
/// steps without anchors (a held world refuses to) and, bit for bit, as a
/// world that never grasped, built from the same state.
#[test]
fn a_released_world_steps_as_one_that_never_grasped() {
    let (config, points, act, volume) = small_block(4);
    let n = points.len();
    let material = || ParticleMaterial::<f32>::uniform(n, 1e5, 0.3, [1.0, 0.0, 0.0]);
    let mut held = World::new(config.clone(), &points, volume, material(), act).expect("world");
    let hand = [0.48, 0.48, 0.26];
    let raised = [0.48, 0.48, 0.30];
    held.step_frame(&[hand], &[raised], &[true]).expect("grasp");
    assert!(held.actuators().coupled_particle_count() > 0);
    assert!(
        held.step_frame_free().is_err(),
        "a held world needs its anchors"
    );
    held.release_grasps();
    assert_eq!(held.actuators().coupled_particle_count(), 0);
    let mut fresh = World::new(config, &points, volume, material(), act).expect("world");
    fresh.set_state(&held.state()).expect("state");
    held.step_frame(&[raised], &[[0.48, 0.48, 0.34]], &[false])
        .expect("released step");
    fresh.step_frame_free().expect("free step");
    assert_eq!(held.positions(), fresh.positions());
    assert_eq!(held.velocities(), fresh.velocities());
}

/// A world given another's state and grip steps as that world does: the
/// couplings (anchors, rest offsets) move between worlds whatever order
/// each keeps its particles in, and anchors that grasped take hold of
/// nothing more. Tolerance 1e-6 m: the worlds list the particles in
/// opposite orders, so the grid sums f32 terms in another order (seen
/// 1.5e-8 m); a coupling on the wrong particle moves it by millimetres.
#[test]
fn a_world_given_another_worlds_grip_steps_as_that_world() {
    let (config, points, act, volume) = small_block(5);
    let n = points.len();
    let material = || ParticleMaterial::<f32>::uniform(n, 1e5, 0.3, [1.0, 0.0, 0.0]);
    let mut held = World::new(config.clone(), &points, volume, material(), act).expect("world");
    let hands = [[0.46, 0.48, 0.26], [0.52, 0.48, 0.26]];
    let raised = [[0.46, 0.48, 0.30], [0.53, 0.48, 0.31]];
    held.step_frame(&hands, &raised, &[true, true])
        .expect("grasp");
    let all: Vec<usize> = (0..n).collect();
    let grip = held.grip(&all).expect("grip");
    assert!(grip.couplings.iter().any(|c| !c.is_empty()));
    assert_eq!(grip.grasped, vec![true, true]);
    // The same particles listed in reverse: the world keeps another order.
    let reversed: Vec<[f64; 3]> = points.iter().rev().copied().collect();
    let order: Vec<usize> = (0..n).rev().collect();
    let mut fresh = World::new(config, &reversed, volume, material(), act).expect("world");
    let state = held.state();
    let mut state_reversed = state.clone();
    for (p, &i) in order.iter().enumerate() {
        state_reversed.x[p] = state.x[i];
        state_reversed.v[p] = state.v[i];
        state_reversed.f[p] = state.f[i];
        state_reversed.c[p] = state.c[i];
    }
    fresh.set_state(&state_reversed).expect("state");
    fresh.set_grip(&grip.subset(&order)).expect("grip");
    assert_eq!(
        fresh.grip(&(0..n).collect::<Vec<_>>()).expect("grip"),
        grip.subset(&order)
    );
    let further = [[0.47, 0.49, 0.33], [0.55, 0.48, 0.35]];
    // Grasp asked again: the anchors have grasped, so nothing changes.
    held.step_frame(&raised, &further, &[true, true])
        .expect("step");
    fresh
        .step_frame(&raised, &further, &[true, true])
        .expect("step");
    let (a, b) = (held.positions(), fresh.positions());
    for (p, &i) in order.iter().enumerate() {
        let apart = (0..3)
            .map(|k| (b[p][k] - a[i][k]).abs())
            .fold(0.0, f64::max);
        assert!(apart < 1e-6, "particle {i}: {apart:e} m apart");
    }
    assert!(
        fresh.set_grip(&grip.subset(&order[1..])).is_err(),
        "a grip for fewer particles is refused"
    );
}
