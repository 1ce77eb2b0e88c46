use dm_view::{Camera, FloorPlane, Frame, RenderOptions, Splat, render};
use nalgebra::{Point3, Vector3};

/// Small deterministic generator so the test needs no rand dependency.
fn next_unit(state: &mut u64) -> f32 {
    *state ^= *state << 13;
    *state ^= *state >> 7;
    *state ^= *state << 17;
    (*state >> 40) as f32 / (1u64 << 24) as f32
}

fn scene() -> (Camera, Vec<Splat>, RenderOptions) {
    let camera = Camera::look_at(
        Point3::new(0.8, -1.2, 0.7),
        Point3::new(0.0, 0.0, 0.1),
        Vector3::z(),
        203,
        157,
        55.0,
    );
    let mut state = 0x1234_5678_9abc_def0u64;
    let mut splats = Vec::new();
    for i in 0..4000 {
        // Quantised positions create many exact depth ties.
        let q = |s: &mut u64| (next_unit(s) * 20.0).floor() / 20.0 - 0.5;
        splats.push(Splat {
            position: [q(&mut state), q(&mut state), q(&mut state) * 0.5 + 0.25],
            radius: 0.01 + 0.03 * next_unit(&mut state),
            color: [
                next_unit(&mut state),
                next_unit(&mut state),
                next_unit(&mut state),
            ],
            label: (i % 3 + 1) as u8,
        });
    }
    let options = RenderOptions {
        floor: Some(FloorPlane {
            point: [0.0, 0.0, 0.0],
            normal: [0.0, 0.0, 1.0],
            checker_size_m: 0.05,
            color_a: [0.8, 0.8, 0.75],
            color_b: [0.3, 0.3, 0.35],
        }),
        ..RenderOptions::default()
    };
    (camera, splats, options)
}

fn render_with_threads(threads: usize) -> Frame {
    let (camera, splats, options) = scene();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    pool.install(|| render(&camera, &splats, &options))
}

fn bits(frame: &Frame) -> (Vec<u32>, Vec<u32>) {
    (
        frame.rgb.iter().flatten().map(|c| c.to_bits()).collect(),
        frame.depth.iter().map(|d| d.to_bits()).collect(),
    )
}

#[test]
fn identical_for_any_thread_count() {
    let reference = render_with_threads(1);
    assert!(reference.splat_index.iter().any(|&i| i != u32::MAX));
    for threads in [2, 3, 8] {
        let frame = render_with_threads(threads);
        assert_eq!(bits(&frame), bits(&reference), "{threads} threads");
        assert_eq!(frame.label, reference.label);
        assert_eq!(frame.splat_index, reference.splat_index);
    }
}
