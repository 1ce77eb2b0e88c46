//! Finite-difference checks (f64, central differences) of every backward
//! kernel of dm-splat: the projection, the rasterizer, and the whole
//! render → loss. Error measure: `common::grad_rel_err` (max abs difference
//! over the gradient's scale). Run with `--nocapture` for the measured maxima.
//!
//! The rasterizer is piecewise smooth: α is clamped at 0.99, splats below
//! α = 1/255 are skipped, the walk stops at T < 1e-4 and tile membership
//! changes with the integer radius. A central difference with step h only
//! straddles such a kink when a pixel sits within ~h of it, which for random
//! configurations and h = 1e-6 has probability ~1e-5 per pixel-splat pair:
//! the seeds used here do not.

mod common;

use common::{
    camera, fd_gradient, grad_rel_err, pack, pack_grads, random_gaussians, random_quat, rng,
    uniform, unpack,
};
use dm_splat::gaussians::logit;
use dm_splat::project::{CameraParams, ProjectedOne, project_gaussians, project_one};
use dm_splat::project_backward::project_one_vjp;
use dm_splat::rasterize::rasterize;
use dm_splat::rasterize_backward::rasterize_backward;
use dm_splat::tiles::TileBins;
use dm_splat::{Gaussians, RenderSettings, render, render_backward};
use nalgebra::Vector3;

/// Projection: smooth rational/exp functions of O(1)-scaled inputs; with
/// h = 1e-6 truncation is O(h²)·|f'''| ≈ 1e-10 relative and round-off
/// ε/h ≈ 1e-10, so 1e-6 leaves room for large third derivatives (conic
/// entries go like 1/σ⁴).
const PROJECT_RTOL: f64 = 1e-6;
/// Rasterizer on projected inputs: exp of quadratic forms times products of
/// (1 − α); same reasoning, inputs are pixels (O(10)) and conics (O(0.1)).
const RASTER_RTOL: f64 = 1e-6;
/// Whole render: the two above chained, plus the transmittance reconstructed
/// by division in the backward walk (relative round-off ≲ 1e-13 per splat).
const RENDER_RTOL: f64 = 1e-5;
/// Step for all inputs (metres, log-scales, quaternion entries, logits,
/// colours, pixels and conic entries are all O(0.01–10)).
const FD_STEP: f64 = 1e-6;

fn settings() -> RenderSettings {
    RenderSettings {
        background: [0.2, 0.4, 0.6],
        ..RenderSettings::default()
    }
}

/// Weighted sum of the projection outputs (a random linear "loss").
fn projection_objective(p: &ProjectedOne<f64>, wm: &[f64; 2], wc: &[f64; 3]) -> f64 {
    p.mean2d[0] * wm[0]
        + p.mean2d[1] * wm[1]
        + p.conic[0] * wc[0]
        + p.conic[1] * wc[1]
        + p.conic[2] * wc[2]
}

fn check_projection(
    cam: &CameraParams<f64>,
    mean: Vector3<f64>,
    seed: u64,
    expect_clamped: bool,
) -> f64 {
    let mut r = rng(seed);
    let log_scale = Vector3::from_fn(|_, _| uniform(&mut r, 0.01f64.ln(), 0.06f64.ln()));
    let quat = random_quat(&mut r);
    let wm = [uniform(&mut r, -1.0, 1.0), uniform(&mut r, -1.0, 1.0)];
    let wc = [0; 3].map(|_| uniform(&mut r, -1.0, 1.0));
    let (near, low_pass) = (0.01, 0.3);
    let p = project_one(cam, &mean, &log_scale, &quat, near, low_pass).expect("visible");
    let ratio =
        (cam.rotation * mean + cam.translation).x / (cam.rotation * mean + cam.translation).z;
    assert_eq!(
        ratio > cam.lim_x_pos || ratio < -cam.lim_x_neg,
        expect_clamped,
        "clamp branch"
    );
    let g = project_one_vjp(cam, &mean, &log_scale, &quat, near, low_pass, &p, wm, wc);
    let mut x: Vec<f64> = mean.iter().chain(log_scale.iter()).copied().collect();
    x.extend(quat);
    let objective = |x: &[f64]| {
        let p = project_one(
            cam,
            &Vector3::new(x[0], x[1], x[2]),
            &Vector3::new(x[3], x[4], x[5]),
            &[x[6], x[7], x[8], x[9]],
            near,
            low_pass,
        )
        .expect("visible");
        projection_objective(&p, &wm, &wc)
    };
    let fd = fd_gradient(objective, &x, FD_STEP);
    let mut analytic: Vec<f64> = g.mean.iter().chain(g.log_scale.iter()).copied().collect();
    analytic.extend(g.rotation);
    grad_rel_err(&analytic, &fd)
}

#[test]
fn projection_vjp_matches_finite_differences() {
    let cam = CameraParams::<f64>::new(&camera(64, 48));
    let mut worst = 0.0f64;
    let mut r = rng(11);
    for seed in 0..24 {
        let mean = Vector3::from_fn(|_, _| uniform(&mut r, -0.15, 0.15));
        let err = check_projection(&cam, mean, seed, false);
        assert!(err <= PROJECT_RTOL, "seed {seed}: relative error {err:.3e}");
        worst = worst.max(err);
    }
    println!("projection (unclamped): max relative error {worst:.3e}");
}

#[test]
fn projection_vjp_matches_finite_differences_when_clamped() {
    // Far to the camera's right: x/z beyond the clamp limit, so the
    // Jacobian uses the clamped ratio and x reaches it only through z.
    let camera = camera(64, 48);
    let cam = CameraParams::<f64>::new(&camera);
    let right = camera
        .world_to_camera
        .inverse_transform_vector(&Vector3::x());
    let mut worst = 0.0f64;
    for seed in 0..8 {
        let mean = right * (0.6 + 0.05 * seed as f64);
        let err = check_projection(&cam, mean, 100 + seed, true);
        assert!(err <= PROJECT_RTOL, "seed {seed}: relative error {err:.3e}");
        worst = worst.max(err);
    }
    println!("projection (clamped): max relative error {worst:.3e}");
}

#[test]
fn rasterizer_vjp_matches_finite_differences() {
    let camera = camera(64, 48);
    let cam = CameraParams::<f64>::new(&camera);
    let mut r = rng(5);
    let mut gaussians = random_gaussians(&mut r, 14, (0.2, 0.9));
    // One above the 0.99 alpha clamp near its centre.
    gaussians.opacity_logits[3] = logit(0.997);
    let projected = project_gaussians(&gaussians, &cam, 0.01, 0.3);
    let bins = TileBins::build(&projected, cam.tiles_x(), cam.tiles_y());
    let background = [0.2, 0.4, 0.6];
    let pixels = 64 * 48;
    let weights: Vec<[f64; 3]> = (0..pixels)
        .map(|_| [0; 3].map(|_| uniform(&mut r, -1.0, 1.0)))
        .collect();
    let visible: Vec<usize> = (0..gaussians.len())
        .filter(|&i| !projected.tile_rect[i].is_empty())
        .collect();
    assert!(visible.len() >= 10, "only {} visible", visible.len());

    let forward = rasterize(&projected, &gaussians.colors, &bins, 64, 48, background);
    let grads = rasterize_backward(
        &projected,
        &gaussians.colors,
        &bins,
        &forward,
        background,
        &weights,
    );
    // Variables per visible Gaussian: mean2d (2), conic (3), opacity, colour (3).
    let mut x = Vec::new();
    let mut analytic = Vec::new();
    for &i in &visible {
        x.extend(projected.mean2d[i]);
        x.extend(projected.conic[i]);
        x.push(projected.opacity[i]);
        x.extend(gaussians.colors[i].iter());
        analytic.extend(grads.mean2d[i]);
        analytic.extend(grads.conic[i]);
        analytic.push(grads.opacity[i]);
        analytic.extend(grads.color[i].iter());
    }
    let objective = |x: &[f64]| {
        let mut p = projected.clone();
        let mut colors = gaussians.colors.clone();
        for (k, &i) in visible.iter().enumerate() {
            let v = &x[9 * k..9 * k + 9];
            p.mean2d[i] = [v[0], v[1]];
            p.conic[i] = [v[2], v[3], v[4]];
            p.opacity[i] = v[5];
            colors[i] = Vector3::new(v[6], v[7], v[8]);
        }
        let out = rasterize(&p, &colors, &bins, 64, 48, background);
        out.image
            .iter()
            .zip(&weights)
            .map(|(c, w)| c[0] * w[0] + c[1] * w[1] + c[2] * w[2])
            .sum()
    };
    let fd = fd_gradient(objective, &x, FD_STEP);
    let err = grad_rel_err(&analytic, &fd);
    println!(
        "rasterizer: max relative error {err:.3e} over {} inputs",
        x.len()
    );
    assert!(err <= RASTER_RTOL, "relative error {err:.3e}");
    // The clamped splat must have had pixels with zero opacity gradient
    // contribution, but the test is only meaningful if clamping happened.
    let centre_alpha = projected.opacity[3];
    assert!(centre_alpha > 0.99);
}

/// `L = ½ Σ (image − target)²` and its image gradient.
fn squared_error(image: &[[f64; 3]], target: &[[f64; 3]]) -> (f64, Vec<[f64; 3]>) {
    let mut loss = 0.0;
    let grad = image
        .iter()
        .zip(target)
        .map(|(a, b)| {
            let d = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
            loss += 0.5 * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
            d
        })
        .collect();
    (loss, grad)
}

/// Relative gradient error of the whole render, and how many pixels
/// stopped on the transmittance bound.
fn check_render(gaussians: &Gaussians<f64>, seed: u64) -> (f64, usize) {
    let camera = camera(48, 40);
    let settings = settings();
    let mut r = rng(seed);
    let target: Vec<[f64; 3]> = (0..48 * 40)
        .map(|_| [0; 3].map(|_| uniform(&mut r, 0.0, 1.0)))
        .collect();
    let forward = render(gaussians, &camera, &settings).expect("render");
    let (_, grad_image) = squared_error(forward.image(), &target);
    let grads =
        render_backward(gaussians, &camera, &settings, &forward, &grad_image).expect("backward");
    let objective = |x: &[f64]| {
        let out = render(&unpack(x), &camera, &settings).expect("render");
        squared_error(out.image(), &target).0
    };
    let x = pack(gaussians);
    let fd = fd_gradient(objective, &x, FD_STEP);
    let stopped = (0..48 * 40)
        .filter(|&p| {
            let (px, py) = (p % 48, p / 48);
            let tile = (py / 16) * forward.bins.tiles_x as usize + px / 16;
            (forward.raster.walk_end[p] as usize) < forward.bins.tile_list(tile).len()
        })
        .count();
    (grad_rel_err(&pack_grads(&grads), &fd), stopped)
}

#[test]
fn render_loss_gradient_matches_finite_differences() {
    let mut worst = 0.0f64;
    for seed in 0..3 {
        let gaussians = random_gaussians(&mut rng(20 + seed), 10, (0.2, 0.9));
        let (err, _) = check_render(&gaussians, seed);
        assert!(err <= RENDER_RTOL, "seed {seed}: relative error {err:.3e}");
        worst = worst.max(err);
    }
    println!("render → loss: max relative error {worst:.3e}");
}

#[test]
fn render_loss_gradient_with_dense_opaque_stack() {
    // Many nearly opaque splats on one spot: the transmittance stop and the
    // back-to-front reconstruction (division by 1 − α) are exercised.
    let mut gaussians = random_gaussians(&mut rng(31), 16, (0.9, 0.97));
    for m in gaussians.means.iter_mut() {
        *m *= 0.1;
    }
    for s in gaussians.log_scales.iter_mut() {
        s.add_scalar_mut(0.7); // twice as wide: broad opaque cores
    }
    let (err, stopped) = check_render(&gaussians, 9);
    println!(
        "render → loss (dense stack): max relative error {err:.3e}, {stopped} pixels stopped early"
    );
    assert!(
        stopped > 50,
        "the transmittance stop was not exercised ({stopped} pixels)"
    );
    assert!(err <= RENDER_RTOL, "relative error {err:.3e}");
}
