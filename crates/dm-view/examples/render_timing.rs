//! Times `render` for 50k random splats at 640x480 (with floor) and optionally writes
//! a preview: `cargo run --release -p dm-view --example render_timing [-- out.png]`.

use std::time::Instant;

use dm_view::{Camera, FloorPlane, RenderOptions, Splat, orbit_cameras, render, side_by_side};
use nalgebra::{Point3, Vector3};

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

fn main() {
    let cameras = orbit_cameras(
        Point3::new(0.0, 0.0, 0.1),
        0.9,
        30.0,
        3,
        0.0,
        Vector3::z(),
        640,
        480,
        55.0,
    );
    let options = RenderOptions {
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
        ..options
    };
    let dense = blob(50_000, [0.15, 0.1, 0.1], 0.004, 7);
    let sparse = blob(50_000, [0.3, 0.3, 0.15], 0.008, 11);
    let cases: [(&str, &[Splat], &RenderOptions); 4] = [
        (
            "dense object (r=4mm in 30x20x10cm) + floor",
            &dense,
            &options,
        ),
        (
            "sparse cloud (r=8mm in 60x60x30cm) + floor",
            &sparse,
            &options,
        ),
        ("dense object, no floor", &dense, &no_floor),
        ("floor only, no splats", &[], &options),
    ];
    let camera = &cameras[0];
    for threads in [rayon::current_num_threads(), 1] {
        let pool = match rayon::ThreadPoolBuilder::new().num_threads(threads).build() {
            Ok(pool) => pool,
            Err(error) => {
                eprintln!("thread pool: {error}");
                return;
            }
        };
        println!("rayon threads: {threads}");
        for (name, splats, options) in &cases {
            let times_ms = pool.install(|| time_renders(camera, splats, options));
            println!(
                "  {name}: {} splats at {}x{}: median {:.2} ms, min {:.2} ms",
                splats.len(),
                camera.width,
                camera.height,
                times_ms[times_ms.len() / 2],
                times_ms[0],
            );
        }
    }

    if let Some(path) = std::env::args().nth(1) {
        let images: Vec<_> = cameras
            .iter()
            .map(|camera| render(camera, &dense, &options).to_rgb8())
            .collect();
        match side_by_side(&images, &["cam0", "cam1", "cam2"]).save(&path) {
            Ok(()) => println!("wrote {path}"),
            Err(error) => eprintln!("could not write {path}: {error}"),
        }
    }
}

/// Sorted wall times (ms) of 20 renders after one warm-up render.
fn time_renders(camera: &Camera, splats: &[Splat], options: &RenderOptions) -> Vec<f64> {
    let _ = render(camera, splats, options);
    let mut times_ms: Vec<f64> = (0..20)
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
