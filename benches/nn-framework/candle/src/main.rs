use candle_core::{DType, Device, Module, Result, Tensor, Var};
use candle_nn::{GroupNorm, Linear};
include!("../../scene.rs");

fn linear(inputs: usize, outputs: usize, vars: &mut Vec<Var>, dev: &Device) -> Result<Linear> {
    let w = Var::randn(0f32, (2.0 / inputs as f32).sqrt(), (outputs, inputs), dev)?;
    let b = Var::zeros(outputs, DType::F32, dev)?;
    vars.push(w.clone());
    vars.push(b.clone());
    Ok(Linear::new(w.as_tensor().clone(), Some(b.as_tensor().clone())))
}

fn group_norm(channels: usize, vars: &mut Vec<Var>, dev: &Device) -> Result<GroupNorm> {
    let w = Var::ones(channels, DType::F32, dev)?;
    let b = Var::zeros(channels, DType::F32, dev)?;
    vars.push(w.clone());
    vars.push(b.clone());
    GroupNorm::new(w.as_tensor().clone(), b.as_tensor().clone(), channels, 8, 1e-5)
}

// Per-point (n, c) → GroupNorm over (1, c, n).
fn norm(gn: &GroupNorm, x: &Tensor) -> Result<Tensor> {
    gn.forward(&x.t()?.unsqueeze(0)?)?.squeeze(0)?.t()
}

fn main() -> Result<()> {
    let particles: usize = std::env::args().nth(1).and_then(|a| a.parse().ok()).unwrap_or(8000);
    let dev = Device::Cpu;
    let s = scene(particles);
    let mut vars = vec![];
    let (e1, n1) = (linear(27, 64, &mut vars, &dev)?, group_norm(64, &mut vars, &dev)?);
    let (e2, n2) = (linear(64, 128, &mut vars, &dev)?, group_norm(128, &mut vars, &dev)?);
    let e3 = linear(256, 64, &mut vars, &dev)?;
    let d1 = linear(64 + 39, 128, &mut vars, &dev)?;
    let d2 = linear(128, 128, &mut vars, &dev)?;
    let d3 = linear(128 + 64 + 39, 128, &mut vars, &dev)?;
    let d4 = linear(128, 3, &mut vars, &dev)?;
    let inputs = Tensor::from_vec(s.inputs.clone(), (particles, 27), &dev)?;
    let index = Tensor::from_vec(s.node_index.clone(), particles * 27, &dev)?;
    let weight = Tensor::from_vec(s.node_weight.clone(), (particles * 27, 1), &dev)?;
    let encoding = Tensor::from_vec(s.node_encoding.clone(), (s.nodes, 39), &dev)?;
    let owner: Vec<u32> = (0..particles as u32).flat_map(|p| [p; 27]).collect();
    let owner = Tensor::from_vec(owner, particles * 27, &dev)?;
    let weight_sum = Tensor::zeros((s.nodes, 1), DType::F32, &dev)?.index_add(&index, &weight, 0)?;
    let index_k: Vec<Tensor> = (0..27).map(|k| Tensor::from_vec((0..particles).map(|p| s.node_index[p * 27 + k]).collect::<Vec<u32>>(), particles, &dev)).collect::<Result<_>>()?;
    let weight_k: Vec<Tensor> = (0..27).map(|k| Tensor::from_vec((0..particles).map(|p| s.node_weight[p * 27 + k]).collect::<Vec<f32>>(), (particles, 1), &dev)).collect::<Result<_>>()?;
    let mut times = vec![];
    for _ in 0..7 {
        let start = std::time::Instant::now();
        let h1 = norm(&n1, &e1.forward(&inputs)?)?.relu()?;
        let h2 = norm(&n2, &e2.forward(&h1)?)?.relu()?;
        let global = h2.max_keepdim(0)?.broadcast_as((particles, 128))?;
        let feature = e3.forward(&Tensor::cat(&[&h2, &global], 1)?)?;
        let node = if std::env::var("PER_OFFSET").is_ok() {
            let mut node = Tensor::zeros((s.nodes, 64), DType::F32, &dev)?;
            for k in 0..27 {
                node = node.index_add(&index_k[k], &feature.broadcast_mul(&weight_k[k])?, 0)?;
            }
            node.broadcast_div(&weight_sum)?
        } else {
            let spread = feature.index_select(&owner, 0)?.broadcast_mul(&weight)?;
            Tensor::zeros((s.nodes, 64), DType::F32, &dev)?.index_add(&index, &spread, 0)?.broadcast_div(&weight_sum)?
        };
        let x = Tensor::cat(&[&node, &encoding], 1)?;
        let h = d2.forward(&d1.forward(&x)?.relu()?)?.relu()?;
        let h = d3.forward(&Tensor::cat(&[&h, &x], 1)?)?.relu()?;
        let u = d4.forward(&h)?.tanh()?;
        let dv = if std::env::var("PER_OFFSET").is_ok() {
            let mut dv = Tensor::zeros((particles, 3), DType::F32, &dev)?;
            for k in 0..27 {
                dv = (dv + u.index_select(&index_k[k], 0)?.broadcast_mul(&weight_k[k])?)?;
            }
            dv
        } else {
            u.index_select(&index, 0)?.broadcast_mul(&weight)?.reshape((particles, 27, 3))?.sum(1)?
        };
        let loss = dv.sqr()?.sum_all()?;
        let t_fwd = start.elapsed().as_secs_f64();
        if std::env::var("PROFILE").is_ok() { eprintln!("forward {:.1} ms", t_fwd * 1e3); }
        let grads = loss.backward()?;
        let total: f32 = vars.iter().map(|v| grads.get(v).map_or(0.0, |g| g.sqr().unwrap().sum_all().unwrap().to_scalar::<f32>().unwrap())).sum();
        times.push(start.elapsed().as_secs_f64());
        std::hint::black_box(total);
    }
    println!("candle particles {particles} nodes {} forward+backward median {:.1} ms", s.nodes, median_ms(times));
    Ok(())
}
