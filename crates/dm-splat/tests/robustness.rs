//! Thread-count independence and NaN/Inf robustness of the rasterizer.

mod common;

use common::{camera, random_gaussians, rng, uniform};
use dm_splat::gaussians::logit;
use dm_splat::{Gaussians, RenderSettings, SplatError, render, render_backward};
use nalgebra::Vector3;

fn render_with_threads(
    threads: usize,
    gaussians: &Gaussians<f32>,
    grad_image: &[[f32; 3]],
) -> (Vec<[f32; 3]>, dm_splat::GaussianGrads<f32>) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    pool.install(|| {
        let camera = camera(160, 120);
        let settings = RenderSettings::default();
        let out = render(gaussians, &camera, &settings).expect("render");
        let grads =
            render_backward(gaussians, &camera, &settings, &out, grad_image).expect("backward");
        (out.image().to_vec(), grads)
    })
}

#[test]
fn results_are_bitwise_independent_of_thread_count() {
    let mut r = rng(3);
    let gaussians = random_gaussians(&mut r, 3000, (0.1, 0.95)).cast::<f32>();
    let grad_image: Vec<[f32; 3]> = (0..160 * 120)
        .map(|_| [0; 3].map(|_| uniform(&mut r, -1.0, 1.0) as f32))
        .collect();
    let (image1, grads1) = render_with_threads(1, &gaussians, &grad_image);
    let (image2, grads2) = render_with_threads(2, &gaussians, &grad_image);
    let (image3, grads3) = render_with_threads(3, &gaussians, &grad_image);
    let bits = |img: &[[f32; 3]]| {
        img.iter()
            .flatten()
            .map(|v| v.to_bits())
            .collect::<Vec<_>>()
    };
    assert_eq!(bits(&image1), bits(&image2));
    assert_eq!(bits(&image1), bits(&image3));
    // PartialEq on f32 would accept -0.0 == 0.0; compare the bit patterns.
    let grad_bits = |g: &dm_splat::GaussianGrads<f32>| {
        let mut v: Vec<u32> = Vec::new();
        for i in 0..g.len() {
            v.extend(g.means[i].iter().map(|x| x.to_bits()));
            v.extend(g.log_scales[i].iter().map(|x| x.to_bits()));
            v.extend(g.rotations[i].iter().map(|x| x.to_bits()));
            v.push(g.opacity_logits[i].to_bits());
            v.extend(g.colors[i].iter().map(|x| x.to_bits()));
        }
        v
    };
    assert_eq!(grad_bits(&grads1), grad_bits(&grads2));
    assert_eq!(grad_bits(&grads1), grad_bits(&grads3));
    assert!(
        grad_bits(&grads1).iter().any(|b| *b != 0),
        "gradients all zero"
    );
}

fn all_finite_f64(values: impl IntoIterator<Item = f64>) -> bool {
    values.into_iter().all(f64::is_finite)
}

/// Renders and back-propagates a set of degenerate Gaussians in f32 and
/// f64; everything must come out finite.
fn assert_finite_render(g: &Gaussians<f64>) {
    fn run<T: dm_mpm::real::Real>(g: &Gaussians<T>) {
        let camera = camera(64, 48);
        let settings = RenderSettings {
            background: [0.3, 0.3, 0.3],
            ..RenderSettings::default()
        };
        let out = render(g, &camera, &settings).expect("render");
        assert!(all_finite_f64(
            out.image().iter().flatten().map(|v| v.to_f64())
        ));
        let grad_image = vec![[T::one(); 3]; out.image().len()];
        let grads = render_backward(g, &camera, &settings, &out, &grad_image).expect("backward");
        for i in 0..grads.len() {
            let values = grads.means[i]
                .iter()
                .chain(grads.log_scales[i].iter())
                .chain(grads.rotations[i].iter())
                .chain(std::iter::once(&grads.opacity_logits[i]))
                .chain(grads.colors[i].iter())
                .map(|v| v.to_f64());
            assert!(
                all_finite_f64(values),
                "non-finite gradient of Gaussian {i}"
            );
        }
    }
    run::<f64>(g);
    run::<f32>(&g.cast::<f32>());
}

#[test]
fn degenerate_gaussians_give_finite_images_and_gradients() {
    let camera = camera(64, 48);
    let eye = camera.center().coords;
    let forward = camera.forward_world();
    let mut g = random_gaussians(&mut rng(8), 20, (0.3, 0.9));
    let unit = [1.0, 0.0, 0.0, 0.0];
    let grey = Vector3::new(0.5, 0.5, 0.5);
    // Vanishing scales (covariance → 0: the low-pass alone sets the footprint).
    g.push(Vector3::zeros(), Vector3::repeat(-60.0), unit, 0.0, grey);
    // Huge scales (f32 covariance overflows to inf: culled, not NaN).
    g.push(Vector3::zeros(), Vector3::repeat(60.0), unit, 0.0, grey);
    // A needle: one axis 1e-20 of the others.
    g.push(
        Vector3::zeros(),
        Vector3::new(-2.0, -48.0, -2.0),
        unit,
        0.0,
        grey,
    );
    // Behind the camera, exactly at its centre, and on the near plane.
    g.push(eye - forward * 0.5, Vector3::repeat(-3.0), unit, 0.0, grey);
    g.push(eye, Vector3::repeat(-3.0), unit, 0.0, grey);
    g.push(eye + forward * 0.01, Vector3::repeat(-3.0), unit, 0.0, grey);
    // Just in front of the near plane: an enormous footprint.
    g.push(
        eye + forward * 0.0101,
        Vector3::repeat(-3.0),
        unit,
        0.0,
        grey,
    );
    // Zero, saturated and extreme opacities.
    g.push(Vector3::zeros(), Vector3::repeat(-3.0), unit, -1e4, grey);
    g.push(Vector3::zeros(), Vector3::repeat(-3.0), unit, 1e4, grey);
    g.push(
        Vector3::zeros(),
        Vector3::repeat(-3.0),
        unit,
        logit(1.0 - 1e-12),
        grey,
    );
    // A tiny (but accepted) quaternion.
    g.push(
        Vector3::zeros(),
        Vector3::repeat(-3.0),
        [1e-9, 0.0, 1e-9, 0.0],
        0.0,
        grey,
    );
    // Far away and far off-axis.
    g.push(
        Vector3::new(1e6, 0.0, 0.0),
        Vector3::repeat(-3.0),
        unit,
        0.0,
        grey,
    );
    g.push(
        Vector3::repeat(1e30),
        Vector3::repeat(-3.0),
        unit,
        0.0,
        grey,
    );
    assert_finite_render(&g);
}

#[test]
fn empty_set_renders_the_background() {
    let camera = camera(20, 10);
    let settings = RenderSettings {
        background: [0.1, 0.2, 0.3],
        ..RenderSettings::default()
    };
    let out = render(&Gaussians::<f32>::default(), &camera, &settings).expect("render");
    assert!(out.image().iter().all(|p| *p == [0.1, 0.2, 0.3]));
}

#[test]
fn invalid_inputs_are_clear_errors() {
    let camera = camera(32, 24);
    let settings = RenderSettings::default();
    let base = random_gaussians(&mut rng(1), 4, (0.3, 0.9));

    let mut g = base.clone();
    g.means[2].x = f64::NAN;
    let err = render(&g, &camera, &settings).expect_err("NaN mean");
    assert!(
        matches!(
            err,
            SplatError::NonFinite {
                index: 2,
                field: "mean"
            }
        ),
        "{err}"
    );

    let mut g = base.clone();
    g.log_scales[1].y = f64::INFINITY;
    assert!(matches!(
        render(&g, &camera, &settings),
        Err(SplatError::NonFinite {
            index: 1,
            field: "log_scale"
        })
    ));

    let mut g = base.clone();
    g.rotations[0] = [0.0; 4];
    assert!(matches!(
        render(&g, &camera, &settings),
        Err(SplatError::ZeroQuaternion { index: 0 })
    ));

    let mut g = base.clone();
    g.colors.pop();
    assert!(matches!(
        render(&g, &camera, &settings),
        Err(SplatError::LengthMismatch(_))
    ));

    let bad = RenderSettings {
        near_plane: 0.0,
        ..RenderSettings::default()
    };
    assert!(matches!(
        render(&base, &camera, &bad),
        Err(SplatError::InvalidSettings(_))
    ));

    let mut empty_camera = camera.clone();
    empty_camera.width = 0;
    assert!(matches!(
        render(&base, &empty_camera, &settings),
        Err(SplatError::EmptyImage { .. })
    ));

    let out = render(&base, &camera, &settings).expect("render");
    let short = vec![[0.0; 3]; 5];
    assert!(matches!(
        render_backward(&base, &camera, &settings, &out, &short),
        Err(SplatError::GradientSize { got: 5, .. })
    ));
}
