//! The residual network's benchmark (`dm-bench residual`) and its GPU
//! parity check (part of `dm-bench cuda-parity`).

use anyhow::{Context, Result};
use dm_cuda::{CudaDevice, CudaResidual, DeviceReal};
use dm_mpm::scenes::{BenchExperts, bench_block};
use dm_residual::{
    FrameInputs, HISTORY, NetworkSize, Precision, Residual, ResidualGrads, ResidualKind,
    ResidualSpec,
};
use std::sync::Arc;
use std::time::Instant;

/// A network of `kind` at method.md §5's sizes on the reference block's
/// grid, its weights non-zero throughout (the last layer included, so the
/// backward pass does all its work), with one frame's inputs on the
/// block's particles and an upstream gradient.
fn setup(
    kind: ResidualKind,
    precision: Precision,
    particles: usize,
    grid: usize,
) -> Result<(Residual, FrameInputs, Vec<[f64; 3]>)> {
    let world = bench_block::<f32>(particles, grid, BenchExperts::NeoHookean, 0)
        .context("building the benchmark block")?;
    let config = world.config();
    let mut network = Residual::new(
        ResidualSpec {
            kind,
            size: NetworkSize::default(),
            alpha: 1.0,
            grid_origin: config.domain_origin,
            grid_dx: config.dx(),
            domain_size: config.domain_size,
            seed: 0,
        },
        precision,
    )?;
    let weights: Vec<f64> = (0..network.parameter_count())
        .map(|i| 0.05 * ((i as f64) * 0.618_034).fract() - 0.025)
        .collect();
    network.set_parameters(&weights)?;
    let x = world.positions();
    let v: Vec<[f64; 3]> = x.iter().map(|p| [0.1 * p[1], -0.1 * p[0], 0.05]).collect();
    let inputs = FrameInputs {
        x_tilde: x.clone(),
        v_tilde: v.clone(),
        x_start: x.clone(),
        history: vec![(x.clone(), v.clone()); HISTORY],
    };
    let upstream = vec![[1e-3, -2e-3, 5e-4]; x.len()];
    Ok((network, inputs, upstream))
}

/// `dm-bench residual`: forward + VJP of one PNPGD frame, timed `repeats`
/// times after a warm-up, on the CPU or (with `device`) the GPU.
pub fn frame(
    particles: usize,
    grid: usize,
    repeats: usize,
    device: Option<Arc<CudaDevice>>,
) -> Result<()> {
    let (network, inputs, upstream) = setup(ResidualKind::Pgnd, Precision::F32, particles, grid)?;
    let on_gpu = match &device {
        Some(device) => Some(CudaResidual::<f32>::new(device.clone(), &network)?),
        None => None,
    };
    let mut timings = Vec::new();
    let mut checksum = 0.0;
    for repeat in 0..=repeats.max(1) {
        let start = Instant::now();
        let (dv, grads) = match &on_gpu {
            Some(gpu) => (gpu.predict(&inputs)?, gpu.vjp(&inputs, &upstream)?),
            None => (network.predict(&inputs)?, network.vjp(&inputs, &upstream)?),
        };
        if repeat > 0 {
            timings.push(start.elapsed().as_secs_f64());
        }
        checksum = dv.iter().flatten().sum::<f64>() + grads.parameters.iter().sum::<f64>();
    }
    timings.sort_by(f64::total_cmp);
    println!("residual_frame_s {:.4}", timings[timings.len() / 2]);
    let place = match &device {
        Some(device) => format!("on {} ({})", device.name(), device.arch()),
        None => format!("{} threads", rayon::current_num_threads()),
    };
    eprintln!(
        "# {particles} particles, grid {grid}^3, {} weights, forward + vjp; checksum {checksum:.4e}; {place}; min {:.4} s, max {:.4} s",
        network.parameter_count(),
        timings[0],
        timings[timings.len() - 1],
    );
    Ok(())
}

/// Δv's largest difference, as a fraction of α, that parity allows (f32
/// sums in another order; a wrong layer moves Δv by far more).
pub const DV_PARITY: f64 = 1e-4;

/// The residual on the GPU against the CPU network (both kinds, T's
/// precision) on varied inputs: Δv within [`DV_PARITY`] of α, and each
/// weight tensor's and input's gradient within the gradient tolerances.
/// Whether every check passed.
pub fn parity<T: DeviceReal>(device: &Arc<CudaDevice>, particles: usize) -> Result<bool> {
    let precision = match T::PRECISION {
        dm_cuda::Precision::F32 => Precision::F32,
        dm_cuda::Precision::F64 => Precision::F64,
    };
    let mut passed = true;
    for kind in [ResidualKind::Pgnd, ResidualKind::Mlp] {
        let (mut network, mut inputs, _) = setup(kind, precision, particles, 32)?;
        // Distinct frames, so every channel and its adjoint differ.
        let wobble = |k: usize, scale: f64| {
            move |(p, c): (usize, &[f64; 3])| -> [f64; 3] {
                let phase = (p * 7 + k * 13) as f64;
                [0, 1, 2].map(|a| c[a] + scale * (0.37 * phase + a as f64).sin())
            }
        };
        inputs.x_start = inputs
            .x_tilde
            .iter()
            .enumerate()
            .map(wobble(1, 2e-3))
            .collect();
        inputs.v_tilde = inputs
            .v_tilde
            .iter()
            .enumerate()
            .map(wobble(2, 0.05))
            .collect();
        for (k, (hx, hv)) in inputs.history.iter_mut().enumerate() {
            *hx = hx
                .iter()
                .enumerate()
                .map(wobble(3 + k, 4e-3 * (k + 1) as f64))
                .collect();
            *hv = hv.iter().enumerate().map(wobble(7 + k, 0.03)).collect();
        }
        let upstream: Vec<[f64; 3]> = (0..inputs.particle_count())
            .map(|p| {
                let s = (p as f64 * 0.71).sin();
                [1e-3 * s, -2e-3 * s.cos(), 5e-4]
            })
            .collect();
        // The last layer scaled until the largest Δv nears α: the bound's
        // tanh is then far from linear, so its adjoint is checked too.
        let largest = network
            .predict(&inputs)?
            .iter()
            .flatten()
            .fold(0.0f64, |m, v| m.max(v.abs()))
            / network.spec().alpha;
        let mut weights = network.parameters()?;
        let last = if kind == ResidualKind::Pgnd {
            "dec4"
        } else {
            "mlp4"
        };
        for tensor in ["weight", "bias"] {
            if let Some((_, range)) = network.tensor(&format!("{last}.{tensor}")) {
                weights[range]
                    .iter_mut()
                    .for_each(|w| *w /= largest.max(1e-12));
            }
        }
        network.set_parameters(&weights)?;
        let gpu = CudaResidual::<T>::new(device.clone(), &network)?;
        let start = Instant::now();
        let cpu_dv = network.predict(&inputs)?;
        let cpu_grads = network.vjp(&inputs, &upstream)?;
        let cpu_s = start.elapsed().as_secs_f64();
        let start = Instant::now();
        let gpu_dv = gpu.predict(&inputs)?;
        let gpu_grads = gpu.vjp(&inputs, &upstream)?;
        let gpu_s = start.elapsed().as_secs_f64();
        let alpha = network.spec().alpha;
        let dv_error = cpu_dv
            .iter()
            .zip(&gpu_dv)
            .flat_map(|(a, b)| (0..3).map(move |c| (a[c] - b[c]).abs()))
            .fold(0.0, f64::max)
            / alpha;
        let largest = cpu_dv.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs())) / alpha;
        let dv_ok = dv_error <= DV_PARITY;
        println!(
            "residual {kind:?} {}: Δv max difference {dv_error:.3e} of α (largest |Δv| {largest:.3e} of α){}",
            precision_name(precision),
            if dv_ok { "" } else { " FAIL" }
        );
        passed &= dv_ok;
        let (want, got) = (
            gradient_groups(&network, &cpu_grads),
            gradient_groups(&network, &gpu_grads),
        );
        if precision == Precision::F64 {
            passed &= entrywise_agreement(&format!("residual {kind:?} f64"), &want, &got);
            passed &= finite_differences(device, &network, &inputs, &upstream, kind)?;
        }
        passed &= crate::cuda::report_agreement(
            &format!("residual {kind:?} {} gradients", precision_name(precision)),
            want,
            got,
        );
        eprintln!(
            "# residual {kind:?}: {} particles, {} weights: cpu {cpu_s:.3} s, gpu {gpu_s:.3} s (first call)",
            inputs.particle_count(),
            network.parameter_count()
        );
    }
    Ok(passed)
}

/// In f64 every gradient entry within this fraction of its group's
/// largest entry: sums in another order leave round-off of about 1e-15
/// there, where a few wrong entries could still pass the cosine.
const F64_ENTRY_PARITY: f64 = 1e-9;

/// Whether every entry of every group agrees within [`F64_ENTRY_PARITY`];
/// prints the worst group.
fn entrywise_agreement(
    label: &str,
    want: &[(&'static str, Vec<f64>)],
    got: &[(&'static str, Vec<f64>)],
) -> bool {
    let mut worst = (0.0f64, "");
    for ((name, a), (_, b)) in want.iter().zip(got) {
        let scale = a
            .iter()
            .fold(0.0f64, |m, v| m.max(v.abs()))
            .max(f64::MIN_POSITIVE);
        let error = a
            .iter()
            .zip(b)
            .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
            / scale;
        if error > worst.0 || worst.1.is_empty() {
            worst = (error, name);
        }
    }
    let ok = worst.0 <= F64_ENTRY_PARITY;
    println!(
        "{label} gradients entry by entry: largest difference {:.3e} of the group's largest entry ({}){}",
        worst.0,
        worst.1,
        if ok { "" } else { " FAIL" }
    );
    ok
}

/// Central-difference step along a direction of O(1) entries. With 1e-6
/// some of the MLP's 150 000 ReLU inputs cross zero between the two
/// evaluations (relative error 1.6e-4); at 1e-8 almost none do, and f64
/// round-off (~1e-16 / 1e-8) stays far below the tolerance.
const FD_STEP: f64 = 1e-8;
/// Relative error allowed between the GPU's VJP and central differences
/// of its own forward pass in f64: round-off (the atomic sums' order
/// included) plus the O(h²) truncation, as for the CPU network's check.
const FD_RTOL: f64 = 1e-5;

/// The GPU network's VJP along one direction of weights, x̃ and ṽ against
/// central differences of its forward pass, in f64; whether it agrees.
fn finite_differences(
    device: &Arc<CudaDevice>,
    network: &Residual,
    inputs: &FrameInputs,
    upstream: &[[f64; 3]],
    kind: ResidualKind,
) -> Result<bool> {
    let mut gpu = CudaResidual::<f64>::new(device.clone(), network)?;
    let grads = gpu.vjp(inputs, upstream)?;
    let wave = |i: usize, phase: f64| (0.618_034 * i as f64 + phase).fract() - 0.5;
    let base = network.parameters()?;
    let d_weights: Vec<f64> = (0..base.len()).map(|i| wave(i, 0.1)).collect();
    let d_x: Vec<[f64; 3]> = (0..inputs.particle_count())
        .map(|p| [0, 1, 2].map(|a| wave(3 * p + a, 0.3)))
        .collect();
    let d_v: Vec<[f64; 3]> = (0..inputs.particle_count())
        .map(|p| [0, 1, 2].map(|a| wave(3 * p + a, 0.7)))
        .collect();
    let dot = |a: &[[f64; 3]], b: &[[f64; 3]]| -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| x[0] * y[0] + x[1] * y[1] + x[2] * y[2])
            .sum()
    };
    let analytic = grads
        .parameters
        .iter()
        .zip(&d_weights)
        .map(|(g, d)| g * d)
        .sum::<f64>()
        + dot(&grads.x_tilde, &d_x)
        + dot(&grads.v_tilde, &d_v);
    let moved = |values: &[[f64; 3]], direction: &[[f64; 3]], h: f64| -> Vec<[f64; 3]> {
        values
            .iter()
            .zip(direction)
            .map(|(v, d)| [0, 1, 2].map(|a| v[a] + h * d[a]))
            .collect()
    };
    let mut loss_at = |h: f64| -> Result<f64> {
        let weights: Vec<f64> = base
            .iter()
            .zip(&d_weights)
            .map(|(w, d)| w + h * d)
            .collect();
        gpu.set_parameters(&weights)?;
        let shifted = FrameInputs {
            x_tilde: moved(&inputs.x_tilde, &d_x, h),
            v_tilde: moved(&inputs.v_tilde, &d_v, h),
            ..inputs.clone()
        };
        Ok(dot(&gpu.predict(&shifted)?, upstream))
    };
    let numeric = (loss_at(FD_STEP)? - loss_at(-FD_STEP)?) / (2.0 * FD_STEP);
    let error = (analytic - numeric).abs() / analytic.abs().max(numeric.abs()).max(1e-8);
    let ok = error <= FD_RTOL && analytic.abs() > 1e-8;
    println!(
        "residual {kind:?} f64 on the GPU, VJP against finite differences: {analytic:.10e} vs {numeric:.10e} (relative error {error:.2e}){}",
        if ok { "" } else { " FAIL" }
    );
    Ok(ok)
}

fn precision_name(precision: Precision) -> &'static str {
    match precision {
        Precision::F32 => "f32",
        Precision::F64 => "f64",
    }
}

/// Each weight tensor's gradient and each input's adjoint, by name.
fn gradient_groups(network: &Residual, g: &ResidualGrads) -> Vec<(&'static str, Vec<f64>)> {
    const TENSORS: [&str; 26] = [
        "enc1.weight",
        "enc1.bias",
        "enc1.norm.weight",
        "enc1.norm.bias",
        "enc2.weight",
        "enc2.bias",
        "enc2.norm.weight",
        "enc2.norm.bias",
        "enc3.weight",
        "enc3.bias",
        "dec1.weight",
        "dec1.bias",
        "dec2.weight",
        "dec2.bias",
        "dec3.weight",
        "dec3.bias",
        "dec4.weight",
        "dec4.bias",
        "mlp1.weight",
        "mlp1.bias",
        "mlp2.weight",
        "mlp2.bias",
        "mlp3.weight",
        "mlp3.bias",
        "mlp4.weight",
        "mlp4.bias",
    ];
    let flat = |v: &[[f64; 3]]| v.iter().flatten().copied().collect::<Vec<_>>();
    let mut groups: Vec<(&'static str, Vec<f64>)> = TENSORS
        .iter()
        .filter_map(|name| {
            let (_, range) = network.tensor(name)?;
            Some((*name, g.parameters[range].to_vec()))
        })
        .collect();
    groups.push(("x_tilde", flat(&g.x_tilde)));
    groups.push(("v_tilde", flat(&g.v_tilde)));
    groups.push(("x_start", flat(&g.x_start)));
    groups.push((
        "history",
        g.history
            .iter()
            .flat_map(|(x, v)| flat(x).into_iter().chain(flat(v)))
            .collect(),
    ));
    groups
}
