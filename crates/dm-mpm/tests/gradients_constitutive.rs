//! Gradient checks of the constitutive reverse-mode kernels (experts,
//! polar rotation, singular-value clamp, Lamé conversion, material
//! patches): every vector-Jacobian product against central finite
//! differences in f64.
//!
//! Error measure: for a gradient vector `a` (VJP) and `b` (finite
//! differences) over all inputs of a kernel, `max_i |a_i − b_i| /
//! max(max_i |a_i|, max_i |b_i|, 1e-8)` — relative to the gradient's scale,
//! so that entries that happen to be near zero do not blow it up. Run with
//! `--nocapture` to see the measured maxima.

mod common;

use common::{random_f, rng, uniform, with_singular_values};
use dm_mpm::experts::{Expert, lame, mixture_kirchhoff, neo_hookean_kirchhoff};
use dm_mpm::experts_backward::{
    expert_kirchhoff_vjp, mixture_kirchhoff_vjp, neo_hookean_kirchhoff_vjp,
};
use dm_mpm::material::{MaterialBounds, MaterialPatches, PatchParams};
use dm_mpm::material_backward::lame_vjp;
use dm_mpm::real::{Mat3, cast_mat};
use dm_mpm::svd::{clamp_singular_values, polar_rotation};
use dm_mpm::svd_backward::{clamp_singular_values_vjp, polar_rotation_vjp};
use rand_chacha::ChaCha8Rng;

// ---------------------------------------------------------------- tolerances

/// Central differences with h = 1e-6 on O(1) inputs: O(h²) ≈ 1e-12
/// truncation plus ≈ ε/h ≈ 1e-10 round-off, well below this on O(1)
/// derivatives.
const FD_RTOL: f64 = 1e-5;
/// Step for inputs of order one (F entries, μ, λ, weights, raw values).
const FD_STEP: f64 = 1e-6;
/// Relative step for Young's modulus (≈ 1e5 Pa): the same relative step.
const FD_STEP_YOUNGS_REL: f64 = 1e-6;
/// f32 against f64 mixture VJP: f32 round-off (≈ 6e-8) amplified by a few
/// dozen operations and the 3x3 solve of the polar VJP (its system has
/// eigenvalues σᵢ + σⱼ ≥ 1.2, so it is well conditioned). The polar
/// iteration converges quadratically, so stopping at |det X − 1| ≤ 1e-6
/// leaves R at round-off.
const F32_RTOL: f64 = 1e-5;
/// f32 against f64 clamp VJP: the f32 SVD goes through FᵀF, whose condition
/// number (up to (2.6/0.3)² ≈ 75 here) multiplies the f32 round-off, and
/// the rotation terms divide by singular-value gaps ≥ 0.3.
const F32_CLAMP_RTOL: f64 = 1e-4;
/// Floor of the error measure's denominator (a gradient that vanishes).
const SCALE_FLOOR: f64 = 1e-8;

/// Singular values of the random deformation gradients.
const SIGMA_RANGE: (f64, f64) = (0.6, 1.6);
/// Random deformation gradients per test.
const SAMPLES: usize = 24;
/// Clamp bounds of method.md §2.
const CLAMP: (f64, f64) = (0.5, 2.0);

// ---------------------------------------------------------------- helpers

/// Central-difference gradient of `objective` at `x`, step `steps[i]` per input.
fn fd_gradient(objective: impl Fn(&[f64]) -> f64, x: &[f64], steps: &[f64]) -> Vec<f64> {
    let mut probe = x.to_vec();
    (0..x.len())
        .map(|i| {
            let h = steps[i];
            probe[i] = x[i] + h;
            let up = objective(&probe);
            probe[i] = x[i] - h;
            let down = objective(&probe);
            probe[i] = x[i];
            (up - down) / (h + h)
        })
        .collect()
}

/// The error measure of the module docs.
fn grad_rel_err(vjp: &[f64], fd: &[f64]) -> f64 {
    assert_eq!(vjp.len(), fd.len());
    let amax = |v: &[f64]| v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let diff = vjp
        .iter()
        .zip(fd)
        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    diff / amax(vjp).max(amax(fd)).max(SCALE_FLOOR)
}

fn frobenius(a: &Mat3<f64>, b: &Mat3<f64>) -> f64 {
    a.component_mul(b).sum()
}

fn random_matrix(rng: &mut ChaCha8Rng) -> Mat3<f64> {
    Mat3::from_fn(|_, _| uniform(rng, -1.0, 1.0))
}

fn mat_from(x: &[f64]) -> Mat3<f64> {
    Mat3::from_column_slice(&x[..9])
}

/// Tracks the largest error of a test and asserts each sample.
struct MaxError {
    name: &'static str,
    max: f64,
}

impl MaxError {
    fn new(name: &'static str) -> Self {
        Self { name, max: 0.0 }
    }

    fn check(&mut self, err: f64, tol: f64, context: &str) {
        assert!(
            err <= tol,
            "{}: relative error {err:.3e} > {tol:.0e} ({context})",
            self.name
        );
        self.max = self.max.max(err);
    }
}

impl Drop for MaxError {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            println!("{}: max relative error {:.3e}", self.name, self.max);
        }
    }
}

/// Expert weight triples covering one-hot, zero entries and full mixtures.
const WEIGHT_SETS: [[f64; 3]; 6] = [
    [1.0, 0.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.5, 0.0, 0.5],
    [0.0, 0.7, 0.3],
    [0.2, 0.3, 0.5],
];

// ---------------------------------------------------------------- experts

/// Inputs of the mixture packed as F (column-major), μ, λ, w₀, w₁, w₂.
fn pack(f: &Mat3<f64>, mu: f64, lambda: f64, w: &[f64; 3]) -> Vec<f64> {
    let mut x = f.as_slice().to_vec();
    x.extend([mu, lambda, w[0], w[1], w[2]]);
    x
}

#[test]
fn mixture_kirchhoff_vjp_matches_finite_differences() {
    let mut rng = rng(11);
    let mut worst = MaxError::new("mixture_kirchhoff_vjp");
    for sample in 0..SAMPLES {
        let f = random_f(&mut rng, SIGMA_RANGE.0, SIGMA_RANGE.1);
        let mu = uniform(&mut rng, 0.5, 2.0);
        let lambda = uniform(&mut rng, 0.5, 2.0);
        let grad_tau = random_matrix(&mut rng);
        for weights in WEIGHT_SETS {
            let objective = |x: &[f64]| {
                let tau = mixture_kirchhoff(&mat_from(x), x[9], x[10], &[x[11], x[12], x[13]]);
                frobenius(&grad_tau, &tau)
            };
            let x = pack(&f, mu, lambda, &weights);
            let fd = fd_gradient(objective, &x, &[FD_STEP; 14]);
            let g = mixture_kirchhoff_vjp(&f, mu, lambda, &weights, &grad_tau);
            let vjp = pack(&g.f, g.mu, g.lambda, &g.weights);
            worst.check(
                grad_rel_err(&vjp, &fd),
                FD_RTOL,
                &format!("sample {sample}, weights {weights:?}"),
            );
        }
    }
}

#[test]
fn each_expert_vjp_matches_finite_differences() {
    let mut rng = rng(12);
    for expert in Expert::ALL {
        let mut worst = MaxError::new(match expert {
            Expert::NeoHookean => "expert_kirchhoff_vjp(neo_hookean)",
            Expert::FixedCorotated => "expert_kirchhoff_vjp(fixed_corotated)",
            Expert::StVenantKirchhoff => "expert_kirchhoff_vjp(st_venant_kirchhoff)",
        });
        let mut one_hot = [0.0; 3];
        one_hot[expert as usize] = 1.0;
        for sample in 0..SAMPLES {
            let f = random_f(&mut rng, SIGMA_RANGE.0, SIGMA_RANGE.1);
            let mu = uniform(&mut rng, 0.5, 2.0);
            let lambda = uniform(&mut rng, 0.5, 2.0);
            let grad_tau = random_matrix(&mut rng);
            let objective = |x: &[f64]| {
                frobenius(
                    &grad_tau,
                    &mixture_kirchhoff(&mat_from(x), x[9], x[10], &one_hot),
                )
            };
            let mut x = f.as_slice().to_vec();
            x.extend([mu, lambda]);
            let fd = fd_gradient(objective, &x, &[FD_STEP; 11]);
            let g = expert_kirchhoff_vjp(expert, &f, mu, lambda, &grad_tau);
            let mut vjp = g.f.as_slice().to_vec();
            vjp.extend([g.mu, g.lambda]);
            worst.check(
                grad_rel_err(&vjp, &fd),
                FD_RTOL,
                &format!("{expert:?}, sample {sample}"),
            );
        }
    }
}

#[test]
fn neo_hookean_fast_path_vjp_matches_finite_differences() {
    let mut rng = rng(13);
    let mut worst = MaxError::new("neo_hookean_kirchhoff_vjp");
    for sample in 0..SAMPLES {
        let f = random_f(&mut rng, SIGMA_RANGE.0, SIGMA_RANGE.1);
        let mu = uniform(&mut rng, 0.5, 2.0);
        let lambda = uniform(&mut rng, 0.5, 2.0);
        let grad_tau = random_matrix(&mut rng);
        let objective =
            |x: &[f64]| frobenius(&grad_tau, &neo_hookean_kirchhoff(&mat_from(x), x[9], x[10]));
        let mut x = f.as_slice().to_vec();
        x.extend([mu, lambda]);
        let fd = fd_gradient(objective, &x, &[FD_STEP; 11]);
        let g = neo_hookean_kirchhoff_vjp(&f, mu, lambda, &grad_tau);
        let mut vjp = g.f.as_slice().to_vec();
        vjp.extend([g.mu, g.lambda]);
        worst.check(
            grad_rel_err(&vjp, &fd),
            FD_RTOL,
            &format!("sample {sample}"),
        );
    }
}

#[test]
fn mixture_kirchhoff_vjp_f32_agrees_with_f64() {
    let mut rng = rng(14);
    let mut worst = MaxError::new("mixture_kirchhoff_vjp f32 vs f64");
    for sample in 0..SAMPLES {
        let f = random_f(&mut rng, SIGMA_RANGE.0, SIGMA_RANGE.1);
        let mu = uniform(&mut rng, 0.5, 2.0);
        let lambda = uniform(&mut rng, 0.5, 2.0);
        let grad_tau = random_matrix(&mut rng);
        for weights in WEIGHT_SETS {
            // Inputs rounded to f32 first, so both sides see the same values.
            let f32_in: Mat3<f32> = cast_mat(&f);
            let grad_tau32: Mat3<f32> = cast_mat(&grad_tau);
            let (mu32, lambda32) = (mu as f32, lambda as f32);
            let weights32 = weights.map(|w| w as f32);
            let g32 = mixture_kirchhoff_vjp(&f32_in, mu32, lambda32, &weights32, &grad_tau32);
            let g64_on_f32_inputs = mixture_kirchhoff_vjp(
                &cast_mat(&f32_in),
                mu32 as f64,
                lambda32 as f64,
                &weights32.map(f64::from),
                &cast_mat(&grad_tau32),
            );
            let reference = pack(
                &g64_on_f32_inputs.f,
                g64_on_f32_inputs.mu,
                g64_on_f32_inputs.lambda,
                &g64_on_f32_inputs.weights,
            );
            let single = pack(
                &cast_mat(&g32.f),
                g32.mu as f64,
                g32.lambda as f64,
                &g32.weights.map(f64::from),
            );
            worst.check(
                grad_rel_err(&single, &reference),
                F32_RTOL,
                &format!("sample {sample}, weights {weights:?}"),
            );
        }
    }
}

// ---------------------------------------------------------------- svd

#[test]
fn polar_rotation_vjp_matches_finite_differences() {
    let mut rng = rng(21);
    let mut worst = MaxError::new("polar_rotation_vjp");
    for sample in 0..SAMPLES {
        let f = random_f(&mut rng, SIGMA_RANGE.0, SIGMA_RANGE.1);
        let grad_r = random_matrix(&mut rng);
        let objective = |x: &[f64]| frobenius(&grad_r, &polar_rotation(&mat_from(x)));
        let fd = fd_gradient(objective, f.as_slice(), &[FD_STEP; 9]);
        let vjp = polar_rotation_vjp(&f, &polar_rotation(&f), &grad_r);
        worst.check(
            grad_rel_err(vjp.as_slice(), &fd),
            FD_RTOL,
            &format!("sample {sample}"),
        );
    }
}

#[test]
fn clamp_vjp_is_identity_when_no_clamp_is_active() {
    let mut rng = rng(22);
    for _ in 0..SAMPLES {
        let f = random_f(&mut rng, SIGMA_RANGE.0, SIGMA_RANGE.1);
        let grad_out = random_matrix(&mut rng);
        assert!(clamp_singular_values(&f, CLAMP.0, CLAMP.1).is_none());
        assert_eq!(
            clamp_singular_values_vjp(&f, CLAMP.0, CLAMP.1, &grad_out),
            grad_out
        );
    }
}

#[test]
fn clamp_vjp_matches_finite_differences_when_active() {
    // Distinct singular values away from the bounds (FD must not cross
    // them), plus two equal clamped ones (the divided-difference guard).
    let cases: [[f64; 3]; 6] = [
        [2.5, 1.2, 0.8],
        [1.5, 1.0, 0.3],
        [2.5, 1.1, 0.3],
        [2.6, 2.3, 1.0],
        [1.4, 0.35, 0.3],
        [2.5, 2.5, 0.9],
    ];
    let mut rng = rng(23);
    let mut worst = MaxError::new("clamp_singular_values_vjp (active)");
    for sigma in cases {
        for sample in 0..SAMPLES / 4 {
            let f = with_singular_values(&mut rng, sigma);
            let grad_out = random_matrix(&mut rng);
            assert!(clamp_singular_values(&f, CLAMP.0, CLAMP.1).is_some());
            let objective = |x: &[f64]| {
                let f = mat_from(x);
                let out = clamp_singular_values(&f, CLAMP.0, CLAMP.1).unwrap_or(f);
                frobenius(&grad_out, &out)
            };
            let fd = fd_gradient(objective, f.as_slice(), &[FD_STEP; 9]);
            let vjp = clamp_singular_values_vjp(&f, CLAMP.0, CLAMP.1, &grad_out);
            worst.check(
                grad_rel_err(vjp.as_slice(), &fd),
                FD_RTOL,
                &format!("sigma {sigma:?}, sample {sample}"),
            );
        }
    }
}

#[test]
fn clamp_vjp_f32_agrees_with_f64() {
    let cases: [[f64; 3]; 4] = [
        [2.5, 1.2, 0.8],
        [1.5, 1.0, 0.3],
        [2.5, 1.1, 0.3],
        [2.6, 2.3, 1.0],
    ];
    let mut rng = rng(24);
    let mut worst = MaxError::new("clamp_singular_values_vjp f32 vs f64");
    for sigma in cases {
        for sample in 0..SAMPLES / 4 {
            let f32_in: Mat3<f32> = cast_mat(&with_singular_values(&mut rng, sigma));
            let grad32: Mat3<f32> = cast_mat(&random_matrix(&mut rng));
            let single = clamp_singular_values_vjp(&f32_in, 0.5f32, 2.0f32, &grad32);
            let reference =
                clamp_singular_values_vjp(&cast_mat(&f32_in), CLAMP.0, CLAMP.1, &cast_mat(&grad32));
            worst.check(
                grad_rel_err(
                    cast_mat::<f32, f64>(&single).as_slice(),
                    reference.as_slice(),
                ),
                F32_CLAMP_RTOL,
                &format!("sigma {sigma:?}, sample {sample}"),
            );
        }
    }
}

// ---------------------------------------------------------------- material

#[test]
fn lame_vjp_matches_finite_differences() {
    let mut rng = rng(31);
    let mut worst = MaxError::new("lame_vjp");
    for sample in 0..SAMPLES {
        let youngs = 10f64.powf(uniform(&mut rng, 4.0, 7.0));
        let poisson = uniform(&mut rng, 0.0, 0.45);
        let grad_mu = uniform(&mut rng, -1.0, 1.0);
        let grad_lambda = uniform(&mut rng, -1.0, 1.0);
        let objective = |x: &[f64]| {
            let (mu, lambda) = lame(x[0], x[1]);
            grad_mu * mu + grad_lambda * lambda
        };
        let steps = [youngs * FD_STEP_YOUNGS_REL, FD_STEP];
        let fd = fd_gradient(objective, &[youngs, poisson], &steps);
        let (grad_youngs, grad_poisson) = lame_vjp(youngs, poisson, grad_mu, grad_lambda);
        // E and ν gradients differ by ~E in scale: check each on its own.
        for (name, vjp, fd) in [("E", grad_youngs, fd[0]), ("nu", grad_poisson, fd[1])] {
            worst.check(
                grad_rel_err(&[vjp], &[fd]),
                FD_RTOL,
                &format!("d/d{name}, sample {sample}"),
            );
        }
    }
}

/// 50 particles, 6 patches, random parameters and upstream gradients.
fn patch_fixture(seed: u64) -> (ChaCha8Rng, MaterialPatches, MaterialBounds, PatchParams) {
    let mut rng = rng(seed);
    let points: Vec<[f64; 3]> = (0..50)
        .map(|_| [0; 3].map(|_| uniform(&mut rng, 0.0, 1.0)))
        .collect();
    let patches = MaterialPatches::build(&points, 6);
    let bounds = MaterialBounds::VOLUMETRIC;
    let n = patches.patch_count();
    let params = PatchParams {
        youngs_raw: (0..n).map(|_| uniform(&mut rng, -2.0, 2.0)).collect(),
        poisson_raw: (0..n).map(|_| uniform(&mut rng, -2.0, 2.0)).collect(),
        logits: (0..n)
            .map(|_| [0; 3].map(|_| uniform(&mut rng, -2.0, 2.0)))
            .collect(),
    };
    (rng, patches, bounds, params)
}

/// Patch parameters packed as youngs_raw, poisson_raw, logits.
fn pack_params(p: &PatchParams) -> Vec<f64> {
    let mut x = p.youngs_raw.clone();
    x.extend(&p.poisson_raw);
    x.extend(p.logits.iter().flatten());
    x
}

fn unpack_params(x: &[f64], n: usize) -> PatchParams {
    PatchParams {
        youngs_raw: x[..n].to_vec(),
        poisson_raw: x[n..2 * n].to_vec(),
        logits: x[2 * n..]
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect(),
    }
}

#[test]
fn particle_fields_vjp_matches_finite_differences() {
    let (mut rng, patches, bounds, params) = patch_fixture(41);
    let particles = patches.neighbours.len();
    let n = patches.patch_count();
    // E is ~1e5–1e7 Pa: scale its upstream gradient so all terms are O(1).
    let grad_youngs: Vec<f64> = (0..particles)
        .map(|_| uniform(&mut rng, -1.0, 1.0) * 1e-6)
        .collect();
    let grad_poisson: Vec<f64> = (0..particles)
        .map(|_| uniform(&mut rng, -1.0, 1.0))
        .collect();
    let grad_weights: Vec<[f64; 3]> = (0..particles)
        .map(|_| [0; 3].map(|_| uniform(&mut rng, -1.0, 1.0)))
        .collect();
    let objective = |x: &[f64]| {
        let (e, nu, w) = patches.particle_fields(&unpack_params(x, n), &bounds);
        let mut total = 0.0;
        for p in 0..particles {
            total += grad_youngs[p] * e[p] + grad_poisson[p] * nu[p];
            total += (0..3).map(|k| grad_weights[p][k] * w[p][k]).sum::<f64>();
        }
        total
    };
    let x = pack_params(&params);
    let fd = fd_gradient(objective, &x, &vec![FD_STEP; x.len()]);
    let g =
        patches.particle_fields_vjp(&params, &bounds, &grad_youngs, &grad_poisson, &grad_weights);
    let mut worst = MaxError::new("particle_fields_vjp");
    worst.check(grad_rel_err(&pack_params(&g), &fd), FD_RTOL, "all patches");
}

#[test]
fn particle_material_vjp_matches_finite_differences() {
    let (mut rng, patches, bounds, params) = patch_fixture(42);
    let particles = patches.neighbours.len();
    let n = patches.patch_count();
    // μ, λ are ~1e4–1e7 Pa: scale their upstream gradients to keep O(1) terms.
    let grad_mu: Vec<f64> = (0..particles)
        .map(|_| uniform(&mut rng, -1.0, 1.0) * 1e-6)
        .collect();
    let grad_lambda: Vec<f64> = (0..particles)
        .map(|_| uniform(&mut rng, -1.0, 1.0) * 1e-6)
        .collect();
    let grad_weights: Vec<[f64; 3]> = (0..particles)
        .map(|_| [0; 3].map(|_| uniform(&mut rng, -1.0, 1.0)))
        .collect();
    let objective = |x: &[f64]| {
        let m = patches.particle_material::<f64>(&unpack_params(x, n), &bounds);
        let mut total = 0.0;
        for p in 0..particles {
            total += grad_mu[p] * m.mu[p] + grad_lambda[p] * m.lambda[p];
            total += (0..3)
                .map(|k| grad_weights[p][k] * m.expert_weights[p][k])
                .sum::<f64>();
        }
        total
    };
    let x = pack_params(&params);
    let fd = fd_gradient(objective, &x, &vec![FD_STEP; x.len()]);
    let g = patches.particle_material_vjp(&params, &bounds, &grad_mu, &grad_lambda, &grad_weights);
    let mut worst = MaxError::new("particle_material_vjp");
    worst.check(grad_rel_err(&pack_params(&g), &fd), FD_RTOL, "all patches");
}
