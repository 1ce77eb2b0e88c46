//! Time per frame of the image metrics at the benchmark's resolution
//! (848×480), on two deterministic textured images:
//!
//!     cargo run --release -p dm-eval --example metric_timing [-- THREADS]
//!
//! THREADS = LPIPS intra-op threads (default 0: all cores). Needs the LPIPS
//! cache (`make lpips`).

use dm_eval::image_metrics::{psnr, ssim};
use dm_eval::lpips::{Lpips, LpipsPaths};
use image::{Rgb, RgbImage};
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let threads: usize = std::env::args().nth(1).map_or(Ok(0), |s| s.parse())?;
    let (w, h) = (848u32, 480u32);
    let pattern = |shift: u32| {
        RgbImage::from_fn(w, h, |x, y| {
            let v = ((x + shift) * 7 + y * 3) % 256;
            Rgb([v as u8, ((x * y + shift) % 251) as u8, (y % 200) as u8])
        })
    };
    let (a, b) = (pattern(0), pattern(5));
    let repeats = 10;
    let time = |f: &mut dyn FnMut()| {
        f(); // warm-up
        let start = Instant::now();
        for _ in 0..repeats {
            f();
        }
        1e3 * start.elapsed().as_secs_f64() / f64::from(repeats)
    };
    let psnr_ms = time(&mut || {
        let _ = psnr(&a, &b);
    });
    let ssim_ms = time(&mut || {
        let _ = ssim(&a, &b);
    });
    let mut network = Lpips::load(&LpipsPaths::discover()?, threads)?;
    let mut value = 0.0;
    let lpips_ms = time(&mut || {
        value = network.distance(&a, &b).unwrap_or(f64::NAN);
    });
    println!(
        "{w}x{h}: PSNR {psnr_ms:.1} ms, SSIM {ssim_ms:.1} ms, LPIPS {lpips_ms:.1} ms per frame (threads {threads}, LPIPS {value:.4})"
    );
    Ok(())
}
