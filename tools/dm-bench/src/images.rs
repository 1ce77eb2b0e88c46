//! Image-side timings: dm-eval's image metrics and dm-view's sphere-splat
//! renderer.

use anyhow::{Context, Result};
use dm_eval::image_metrics::{psnr, ssim};
use dm_eval::lpips::{Lpips, LpipsPaths};
use dm_view::{Camera, FloorPlane, RenderOptions, Splat, orbit_cameras, render, side_by_side};
use image::{Rgb, RgbImage};
use nalgebra::{Point3, Vector3};
use std::path::Path;
use std::time::Instant;

/// Mean milliseconds of `repeats` calls of `f` after one warm-up call.
fn mean_ms(repeats: usize, f: &mut dyn FnMut() -> Result<()>) -> Result<f64> {
    f()?;
    let start = Instant::now();
    for _ in 0..repeats {
        f()?;
    }
    Ok(1e3 * start.elapsed().as_secs_f64() / repeats as f64)
}

/// PSNR, SSIM and LPIPS of two deterministic textured `width`×`height`
/// images, each the mean of `repeats` calls after a warm-up; LPIPS with
/// `lpips_threads` intra-op threads (0: all cores) from the `make lpips`
/// cache.
pub fn metrics(width: u32, height: u32, repeats: usize, lpips_threads: usize) -> Result<()> {
    let repeats = repeats.max(1);
    let pattern = |shift: u32| {
        RgbImage::from_fn(width, height, |x, y| {
            let v = ((x + shift) * 7 + y * 3) % 256;
            Rgb([v as u8, ((x * y + shift) % 251) as u8, (y % 200) as u8])
        })
    };
    let (a, b) = (pattern(0), pattern(5));
    let psnr_ms = mean_ms(repeats, &mut || {
        std::hint::black_box(psnr(&a, &b)?);
        Ok(())
    })?;
    println!("psnr_ms {psnr_ms:.2}");
    let ssim_ms = mean_ms(repeats, &mut || {
        std::hint::black_box(ssim(&a, &b)?);
        Ok(())
    })?;
    println!("ssim_ms {ssim_ms:.2}");
    let paths = LpipsPaths::discover().context("finding the LPIPS network (make lpips)")?;
    let mut network = Lpips::load(&paths, lpips_threads).context("loading LPIPS")?;
    let mut value = 0.0;
    let lpips_ms = mean_ms(repeats, &mut || {
        value = network.distance(&a, &b)?;
        Ok(())
    })?;
    println!("lpips_ms {lpips_ms:.2}");
    eprintln!(
        "# {width}x{height}, mean of {repeats} after a warm-up; LPIPS {value:.4} with {lpips_threads} intra-op threads (0: all cores)"
    );
    Ok(())
}

/// xorshift64: deterministic and dependency-free.
fn next_unit(state: &mut u64) -> f32 {
    *state ^= *state << 13;
    *state ^= *state >> 7;
    *state ^= *state << 17;
    (*state >> 40) as f32 / (1u64 << 24) as f32
}

/// `count` splats filling an ellipsoid of half-axes `half_extent` above the floor.
fn blob(count: usize, half_extent: [f32; 3], radius: f32, seed: u64) -> Vec<Splat> {
    let mut state = seed;
    let mut splats = Vec::with_capacity(count);
    while splats.len() < count {
        let p = [0, 1, 2].map(|_| 2.0 * next_unit(&mut state) - 1.0);
        if p.iter().map(|c| c * c).sum::<f32>() > 1.0 {
            continue;
        }
        let position = [
            p[0] * half_extent[0],
            p[1] * half_extent[1],
            p[2] * half_extent[2] + half_extent[2],
        ];
        let tint = 0.9 + 0.1 * next_unit(&mut state);
        splats.push(Splat {
            position,
            radius,
            color: [0.85 * tint, 0.35 * tint, 0.25 * tint],
            label: if position[0] > 0.0 { 1 } else { 2 },
        });
    }
    splats
}

/// Sorted wall times (ms) of `repeats` renders after one warm-up render.
fn time_renders(
    camera: &Camera,
    splats: &[Splat],
    options: &RenderOptions,
    repeats: usize,
) -> Vec<f64> {
    let _ = render(camera, splats, options);
    let mut times_ms: Vec<f64> = (0..repeats.max(1))
        .map(|_| {
            let start = Instant::now();
            let frame = render(camera, splats, options);
            let elapsed = start.elapsed().as_secs_f64() * 1e3;
            std::hint::black_box(frame);
            elapsed
        })
        .collect();
    times_ms.sort_by(f64::total_cmp);
    times_ms
}

/// dm-view's sphere-splat render of `count` seeded splats at
/// `width`×`height` in four cases (a dense object and a sparse cloud over
/// the checker floor, the object without it, the floor alone); the median
/// of `repeats` renders each. With `preview`, three orbit views of the
/// dense object side by side are written there.
pub fn sphere_render(
    count: usize,
    width: u32,
    height: u32,
    repeats: usize,
    preview: Option<&Path>,
) -> Result<()> {
    let cameras = orbit_cameras(
        Point3::new(0.0, 0.0, 0.1),
        0.9,
        30.0,
        3,
        0.0,
        Vector3::z(),
        width,
        height,
        55.0,
    );
    let floor = RenderOptions {
        floor: Some(FloorPlane {
            point: [0.0, 0.0, 0.0],
            normal: [0.0, 0.0, 1.0],
            checker_size_m: 0.05,
            color_a: [0.8, 0.8, 0.78],
            color_b: [0.45, 0.45, 0.5],
        }),
        ..RenderOptions::default()
    };
    let no_floor = RenderOptions {
        floor: None,
        ..floor
    };
    let dense = blob(count, [0.15, 0.1, 0.1], 0.004, 7);
    let sparse = blob(count, [0.3, 0.3, 0.15], 0.008, 11);
    let cases: [(&str, &str, &[Splat], &RenderOptions); 4] = [
        (
            "dense_floor",
            "dense object (r = 4 mm in 30x20x10 cm) over the floor",
            &dense,
            &floor,
        ),
        (
            "sparse_floor",
            "sparse cloud (r = 8 mm in 60x60x30 cm) over the floor",
            &sparse,
            &floor,
        ),
        ("dense", "dense object, no floor", &dense, &no_floor),
        ("floor", "the floor alone", &[], &floor),
    ];
    let camera = &cameras[0];
    for (key, description, splats, options) in cases {
        let times_ms = time_renders(camera, splats, options, repeats);
        println!("sphere_render_{key}_ms {:.2}", times_ms[times_ms.len() / 2]);
        eprintln!(
            "# {description}: {} splats, min {:.2} ms",
            splats.len(),
            times_ms[0]
        );
    }
    eprintln!(
        "# {width}x{height}, median of {repeats} renders after a warm-up, {} threads",
        rayon::current_num_threads()
    );
    if let Some(path) = preview {
        let images: Vec<_> = cameras
            .iter()
            .map(|camera| render(camera, &dense, &floor).to_rgb8())
            .collect();
        side_by_side(&images, &["cam0", "cam1", "cam2"])
            .save(path)
            .with_context(|| format!("writing {}", path.display()))?;
        eprintln!("# wrote {}", path.display());
    }
    Ok(())
}
