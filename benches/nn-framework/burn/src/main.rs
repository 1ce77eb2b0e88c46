use burn::tensor::activation::relu;
use burn::tensor::{Distribution, Int, Tensor, TensorData, IndexingUpdateOp};
include!("../../scene.rs");

struct Linear { w: Tensor<2>, b: Tensor<2> }
impl Linear {
    fn new(inputs: usize, outputs: usize, params: &mut Vec<Tensor<2>>) -> Self {
        let dev = Default::default();
        let s = (2.0 / inputs as f64).sqrt();
        let w = Tensor::<2>::random([inputs, outputs], Distribution::Normal(0.0, s), &dev).autodiff().require_grad();
        let b = Tensor::<2>::zeros([1, outputs], &dev).autodiff().require_grad();
        params.push(w.clone());
        params.push(b.clone());
        Self { w, b }
    }
    fn forward(&self, x: Tensor<2>) -> Tensor<2> { x.matmul(self.w.clone()) + self.b.clone() }
}

// GroupNorm over per-point features (n, c) with 8 groups, affine.
struct GroupNorm { g: Tensor<2>, b: Tensor<2>, c: usize }
impl GroupNorm {
    fn new(c: usize, params: &mut Vec<Tensor<2>>) -> Self {
        let dev = Default::default();
        let g = Tensor::<2>::ones([1, c], &dev).autodiff().require_grad();
        let b = Tensor::<2>::zeros([1, c], &dev).autodiff().require_grad();
        params.push(g.clone());
        params.push(b.clone());
        Self { g, b, c }
    }
    fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let n = x.dims()[0];
        let grouped = x.reshape([n, 8, self.c / 8]).swap_dims(0, 1).reshape([8, n * self.c / 8]);
        let (var, mean) = grouped.clone().var_mean_bias(1);
        let normed = (grouped - mean) / (var + 1e-5).sqrt();
        normed.reshape([8, n, self.c / 8]).swap_dims(0, 1).reshape([n, self.c]) * self.g.clone() + self.b.clone()
    }
}

fn main() {
    let particles: usize = std::env::args().nth(1).and_then(|a| a.parse().ok()).unwrap_or(8000);
    let dev = Default::default();
    let s = scene(particles);
    let mut params = vec![];
    let (e1, n1) = (Linear::new(27, 64, &mut params), GroupNorm::new(64, &mut params));
    let (e2, n2) = (Linear::new(64, 128, &mut params), GroupNorm::new(128, &mut params));
    let e3 = Linear::new(256, 64, &mut params);
    let d1 = Linear::new(64 + 39, 128, &mut params);
    let d2 = Linear::new(128, 128, &mut params);
    let d3 = Linear::new(128 + 64 + 39, 128, &mut params);
    let d4 = Linear::new(128, 3, &mut params);
    let inputs = Tensor::<2>::from_data(TensorData::new(s.inputs.clone(), [particles, 27]), &dev);
    let index_data: Vec<i64> = s.node_index.iter().map(|&i| i as i64).collect();
    let index = Tensor::<1, Int>::from_data(TensorData::new(index_data, [particles * 27]), &dev);
    let owner: Vec<i64> = (0..particles as i64).flat_map(|p| [p; 27]).collect();
    let owner = Tensor::<1, Int>::from_data(TensorData::new(owner, [particles * 27]), &dev);
    let weight = Tensor::<2>::from_data(TensorData::new(s.node_weight.clone(), [particles * 27, 1]), &dev);
    let encoding = Tensor::<2>::from_data(TensorData::new(s.node_encoding.clone(), [s.nodes, 39]), &dev);
    let weight_sum = Tensor::<2>::zeros([s.nodes, 1], &dev).select_assign(0, index.clone(), weight.clone(), IndexingUpdateOp::Add);
    let mut times = vec![];
    for _ in 0..7 {
        let start = std::time::Instant::now();
        let h1 = relu(n1.forward(e1.forward(inputs.clone())));
        let h2 = relu(n2.forward(e2.forward(h1)));
        let global = h2.clone().max_dim(0).expand([particles, 128]);
        let feature = e3.forward(Tensor::cat(vec![h2, global], 1));
        let spread = feature.select(0, owner.clone()) * weight.clone();
        let node = Tensor::<2>::zeros([s.nodes, 64], &dev).autodiff()
            .select_assign(0, index.clone(), spread, IndexingUpdateOp::Add) / weight_sum.clone();
        let x = Tensor::cat(vec![node, encoding.clone()], 1);
        let h = relu(d2.forward(relu(d1.forward(x.clone()))));
        let h = relu(d3.forward(Tensor::cat(vec![h, x], 1)));
        let u = d4.forward(h).tanh();
        let dv = (u.select(0, index.clone()) * weight.clone()).reshape([particles, 27, 3]).sum_dim(1);
        let loss = (dv.clone() * dv).sum();
        let grads = loss.backward();
        let total: f32 = params.iter().map(|p| p.grad(&grads).map_or(0.0, |g| (g.clone() * g).sum().into_scalar::<f32>())).sum();
        times.push(start.elapsed().as_secs_f64());
        std::hint::black_box(total);
    }
    println!("burn particles {particles} nodes {} forward+backward median {:.1} ms", s.nodes, median_ms(times));
}
