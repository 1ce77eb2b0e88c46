//! The residual networks on candle: [`ResidualKind::Pgnd`] (particle
//! encoder → grid decoder → particles) and [`ResidualKind::Mlp`].
//!
//! The bound: the decoder's raw output y becomes α·tanh(|y|)·y/|y|, a
//! vector no longer than α (method.md writes α·tanh per component, whose
//! norm can reach √3·α); Δv is a convex combination of such vectors (the
//! B-spline weights sum to one), so |Δv| ≤ α holds exactly.

use crate::ResidualError;
use crate::features::{CHANNELS, FrameInputs};
use candle_core::{D, DType, Device, Tensor, Var};
use candle_nn::{GroupNorm, Linear, Module};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

/// Which residual a model carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum ResidualKind {
    /// Particle-grid network (PNPGD, method.md §5).
    Pgnd,
    /// Per-particle MLP, no spatial structure (the paper's ablation).
    Mlp,
    /// Physics only.
    None,
}

/// Layer widths (method.md §5 by default; tests use a tiny one).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct NetworkSize {
    /// PointNet encoder widths; the last is the feature size.
    pub encoder: [usize; 3],
    /// Width of the 4 decoder layers (of the MLP residual's layers).
    pub decoder: usize,
    /// GroupNorm groups (must divide the encoder widths).
    pub groups: usize,
}

impl Default for NetworkSize {
    fn default() -> Self {
        Self {
            encoder: [64, 128, 64],
            decoder: 128,
            groups: 8,
        }
    }
}

/// Everything needed to rebuild a residual besides its weights (saved in
/// model.json; the weights go to a safetensors file beside it).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResidualSpec {
    pub kind: ResidualKind,
    pub size: NetworkSize,
    /// Bound on |Δv|, m/s.
    pub alpha: f64,
    /// MPM grid: origin (m), spacing (m) and the domain's edge (m).
    pub grid_origin: [f64; 3],
    pub grid_dx: f64,
    pub domain_size: f64,
    /// Seed of the initial weights.
    pub seed: u64,
}

/// Scale of the decoder's raw output before the bound. Adam's first steps
/// move every weight by about the learning rate whatever the gradient's
/// size; from a zero last layer that alone gave |Δv| ≈ 0.8 m/s (2.5 cm a
/// frame) and the train loss jumped 170× in a rope fit. Scaled by 1e-2,
/// early steps make cm/s corrections and the network grows into α.
pub const OUTPUT_SCALE: f64 = 1e-2;

/// Smallest B-spline weight sum a grid node's particle-to-node average
/// divides by (see the node features in `forward_tensors`).
pub const MIN_NODE_WEIGHT: f64 = 1e-6;

/// Fourier bands of the node-position encoding (method.md §5: L = 6).
pub const FOURIER_BANDS: usize = 6;
const NODE_ENCODING: usize = 3 + 6 * FOURIER_BANDS;
const STENCIL: usize = 27;

/// The result of [`Residual::vjp`]: gradients of ⟨Δv, Δv̄⟩.
#[derive(Clone, Debug, PartialEq)]
pub struct ResidualGrads {
    /// Parameter gradient in [`Residual::parameters`] order.
    pub parameters: Vec<f64>,
    pub x_tilde: Vec<[f64; 3]>,
    pub v_tilde: Vec<[f64; 3]>,
    pub x_start: Vec<[f64; 3]>,
}

/// A residual network with its weights.
#[derive(Debug)]
pub struct Residual {
    spec: ResidualSpec,
    dtype: DType,
    /// Sorted by name: the order of the flat parameter vector.
    vars: BTreeMap<String, Var>,
}

/// The particle↔node transfer of one frame: node ids and the constant
/// integer base of each particle's stencil.
struct Stencil {
    base: Tensor,
    node_index: Tensor,
    owner: Tensor,
    node_encoding: Tensor,
    nodes: usize,
}

fn layer_shapes(spec: &ResidualSpec) -> Vec<(String, usize, usize)> {
    let [e1, e2, e3] = spec.size.encoder;
    let h = spec.size.decoder;
    match spec.kind {
        ResidualKind::Pgnd => {
            let node_in = e3 + NODE_ENCODING;
            vec![
                ("enc1".into(), CHANNELS, e1),
                ("enc2".into(), e1, e2),
                ("enc3".into(), 2 * e2, e3),
                ("dec1".into(), node_in, h),
                ("dec2".into(), h, h),
                ("dec3".into(), h + node_in, h),
                ("dec4".into(), h, 3),
            ]
        }
        ResidualKind::Mlp => vec![
            ("mlp1".into(), CHANNELS, h),
            ("mlp2".into(), h, h),
            ("mlp3".into(), h + CHANNELS, h),
            ("mlp4".into(), h, 3),
        ],
        ResidualKind::None => Vec::new(),
    }
}

/// SplitMix64: seeded, platform-independent initial weights.
fn uniform_stream(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed;
    move || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn rows(values: &[[f64; 3]], dtype: DType) -> Result<Tensor, ResidualError> {
    let flat: Vec<f64> = values.iter().flatten().copied().collect();
    Ok(Tensor::from_vec(flat, (values.len(), 3), &Device::Cpu)?.to_dtype(dtype)?)
}

fn to_rows(t: &Tensor) -> Result<Vec<[f64; 3]>, ResidualError> {
    Ok(t.to_dtype(DType::F64)?
        .to_vec2::<f64>()?
        .into_iter()
        .map(|r| [r[0], r[1], r[2]])
        .collect())
}

impl Residual {
    /// A freshly initialised network: PyTorch's default uniform
    /// initialisation, except the last layer, which starts at zero so that
    /// an untrained residual changes nothing.
    pub fn new(spec: ResidualSpec, dtype: DType) -> Result<Self, ResidualError> {
        if spec.kind == ResidualKind::None {
            return Err(ResidualError::Input {
                field: "kind".into(),
                problem: "`none` has no network".into(),
            });
        }
        let groups = spec.size.groups;
        if groups == 0 || spec.size.encoder.iter().any(|w| w % groups != 0) {
            return Err(ResidualError::Input {
                field: "size.groups".into(),
                problem: format!("{groups} groups must divide every encoder width"),
            });
        }
        if !(spec.alpha > 0.0 && spec.grid_dx > 0.0 && spec.domain_size > 0.0) {
            return Err(ResidualError::Input {
                field: "alpha / grid_dx / domain_size".into(),
                problem: "must be positive".into(),
            });
        }
        let mut uniform = uniform_stream(spec.seed);
        let mut vars = BTreeMap::new();
        let shapes = layer_shapes(&spec);
        let last = shapes.len() - 1;
        for (i, (name, inputs, outputs)) in shapes.into_iter().enumerate() {
            let bound = if i == last {
                0.0
            } else {
                1.0 / (inputs as f64).sqrt()
            };
            let w: Vec<f64> = (0..inputs * outputs)
                .map(|_| bound * (2.0 * uniform() - 1.0))
                .collect();
            let b: Vec<f64> = (0..outputs)
                .map(|_| bound * (2.0 * uniform() - 1.0))
                .collect();
            let w = Tensor::from_vec(w, (outputs, inputs), &Device::Cpu)?.to_dtype(dtype)?;
            let b = Tensor::from_vec(b, outputs, &Device::Cpu)?.to_dtype(dtype)?;
            vars.insert(format!("{name}.weight"), Var::from_tensor(&w)?);
            vars.insert(format!("{name}.bias"), Var::from_tensor(&b)?);
            if name == "enc1" || name == "enc2" {
                let ones = Tensor::ones(outputs, dtype, &Device::Cpu)?;
                let zeros = Tensor::zeros(outputs, dtype, &Device::Cpu)?;
                vars.insert(format!("{name}.norm.weight"), Var::from_tensor(&ones)?);
                vars.insert(format!("{name}.norm.bias"), Var::from_tensor(&zeros)?);
            }
        }
        Ok(Self { spec, dtype, vars })
    }

    pub fn spec(&self) -> &ResidualSpec {
        &self.spec
    }

    fn var(&self, name: &str) -> Result<&Var, ResidualError> {
        self.vars.get(name).ok_or_else(|| ResidualError::Input {
            field: name.into(),
            problem: "missing weight".into(),
        })
    }

    fn linear(&self, name: &str) -> Result<Linear, ResidualError> {
        Ok(Linear::new(
            self.var(&format!("{name}.weight"))?.as_tensor().clone(),
            Some(self.var(&format!("{name}.bias"))?.as_tensor().clone()),
        ))
    }

    /// Per-point GroupNorm: (n, c) is normalised as one (1, c, n) sample.
    fn norm(&self, name: &str, x: &Tensor) -> Result<Tensor, ResidualError> {
        let weight = self
            .var(&format!("{name}.norm.weight"))?
            .as_tensor()
            .clone();
        let bias = self.var(&format!("{name}.norm.bias"))?.as_tensor().clone();
        let channels = weight.dim(0)?;
        let gn = GroupNorm::new(weight, bias, channels, self.spec.size.groups, 1e-5)?;
        Ok(gn.forward(&x.t()?.unsqueeze(0)?)?.squeeze(0)?.t()?)
    }

    /// The 27 input channels (n, 27), positions centred on x̃'s centroid.
    fn input_channels(
        &self,
        x_tilde: &Tensor,
        v_tilde: &Tensor,
        x_start: &Tensor,
        inputs: &FrameInputs,
    ) -> Result<Tensor, ResidualError> {
        let centroid = x_tilde.mean_keepdim(0)?;
        let mut channels = vec![
            x_tilde.broadcast_sub(&centroid)?,
            v_tilde.clone(),
            (x_tilde - x_start)?,
        ];
        for (x, v) in &inputs.history {
            channels.push(rows(x, self.dtype)?.broadcast_sub(&centroid)?);
            channels.push(rows(v, self.dtype)?);
        }
        Ok(Tensor::cat(&channels, 1)?)
    }

    fn stencil(&self, x_tilde: &[[f64; 3]]) -> Result<Stencil, ResidualError> {
        let s = &self.spec;
        let mut ids: HashMap<[i64; 3], u32> = HashMap::new();
        let mut node_cells: Vec<[i64; 3]> = Vec::new();
        let mut base = Vec::with_capacity(x_tilde.len() * 3);
        let mut node_index = Vec::with_capacity(x_tilde.len() * STENCIL);
        for x in x_tilde {
            let cell =
                [0, 1, 2].map(|a| ((x[a] - s.grid_origin[a]) / s.grid_dx - 0.5).floor() as i64);
            base.extend(cell.map(|c| c as f64));
            for i in 0..3 {
                for j in 0..3 {
                    for k in 0..3 {
                        let node = [cell[0] + i, cell[1] + j, cell[2] + k];
                        let next = node_cells.len() as u32;
                        let id = *ids.entry(node).or_insert_with(|| {
                            node_cells.push(node);
                            next
                        });
                        node_index.push(id);
                    }
                }
            }
        }
        let nodes = node_cells.len();
        let mut encoding = Vec::with_capacity(nodes * NODE_ENCODING);
        for node in &node_cells {
            let q = [0, 1, 2].map(|a| node[a] as f64 * s.grid_dx / s.domain_size);
            encoding.extend(q);
            for band in 0..FOURIER_BANDS {
                let frequency = (1u32 << band) as f64 * std::f64::consts::PI;
                encoding.extend(q.map(|c| (frequency * c).sin()));
                encoding.extend(q.map(|c| (frequency * c).cos()));
            }
        }
        let n = x_tilde.len();
        let owner: Vec<u32> = (0..n as u32).flat_map(|p| [p; STENCIL]).collect();
        let cpu = &Device::Cpu;
        Ok(Stencil {
            base: Tensor::from_vec(base, (n, 3), cpu)?.to_dtype(self.dtype)?,
            node_index: Tensor::from_vec(node_index, n * STENCIL, cpu)?,
            owner: Tensor::from_vec(owner, n * STENCIL, cpu)?,
            node_encoding: Tensor::from_vec(encoding, (nodes, NODE_ENCODING), cpu)?
                .to_dtype(self.dtype)?,
            nodes,
        })
    }

    /// Quadratic B-spline weights (n·27, 1) of each particle's stencil,
    /// differentiable in x̃ (the stencil's base cell is piecewise constant).
    fn spline_weights(&self, x_tilde: &Tensor, stencil: &Stencil) -> Result<Tensor, ResidualError> {
        let s = &self.spec;
        let n = x_tilde.dim(0)?;
        let origin =
            Tensor::from_vec(s.grid_origin.to_vec(), (1, 3), &Device::Cpu)?.to_dtype(self.dtype)?;
        let fx = ((x_tilde.broadcast_sub(&origin)? / s.grid_dx)? - &stencil.base)?;
        let w0 = ((fx.affine(-1.0, 1.5)?.sqr()?) * 0.5)?;
        let w1 = (fx.affine(1.0, -1.0)?.sqr()?.affine(-1.0, 0.75))?;
        let w2 = ((fx.affine(1.0, -0.5)?.sqr()?) * 0.5)?;
        // (n, 3 axes, 3 offsets)
        let w = Tensor::stack(&[w0, w1, w2], 2)?;
        let wx = w.narrow(1, 0, 1)?.reshape((n, 3, 1, 1))?;
        let wy = w.narrow(1, 1, 1)?.reshape((n, 1, 3, 1))?;
        let wz = w.narrow(1, 2, 1)?.reshape((n, 1, 1, 3))?;
        Ok(wx
            .broadcast_mul(&wy)?
            .broadcast_mul(&wz)?
            .reshape((n * STENCIL, 1))?)
    }

    /// α·tanh(|y|)·y/|y| row by row, for y = OUTPUT_SCALE · raw output.
    fn bound(&self, y: &Tensor) -> Result<Tensor, ResidualError> {
        let y = (y * OUTPUT_SCALE)?;
        let y = &y;
        let norm = (y.sqr()?.sum_keepdim(D::Minus1)? + 1e-12)?.sqrt()?;
        Ok((y.broadcast_mul(&(norm.tanh()? / &norm)?)? * self.spec.alpha)?)
    }

    fn forward_tensors(
        &self,
        x_tilde: &Tensor,
        v_tilde: &Tensor,
        x_start: &Tensor,
        inputs: &FrameInputs,
    ) -> Result<Tensor, ResidualError> {
        let channels = self.input_channels(x_tilde, v_tilde, x_start, inputs)?;
        match self.spec.kind {
            ResidualKind::Mlp => {
                let h = self.linear("mlp1")?.forward(&channels)?.relu()?;
                let h = self.linear("mlp2")?.forward(&h)?.relu()?;
                let h = self
                    .linear("mlp3")?
                    .forward(&Tensor::cat(&[&h, &channels], 1)?)?
                    .relu()?;
                self.bound(&self.linear("mlp4")?.forward(&h)?)
            }
            ResidualKind::Pgnd => {
                let n = inputs.particle_count();
                let h = self
                    .norm("enc1", &self.linear("enc1")?.forward(&channels)?)?
                    .relu()?;
                let h = self
                    .norm("enc2", &self.linear("enc2")?.forward(&h)?)?
                    .relu()?;
                let global = h.max_keepdim(0)?.broadcast_as(h.shape())?;
                let feature = self
                    .linear("enc3")?
                    .forward(&Tensor::cat(&[&h, &global], 1)?)?;
                let stencil = self.stencil(&inputs.x_tilde)?;
                let w = self.spline_weights(x_tilde, &stencil)?;
                let width = feature.dim(1)?;
                let cpu = &Device::Cpu;
                // Nodes that only a particle's vanishing spline tail reaches
                // have a tiny weight sum: their feature is a ratio of two
                // tiny numbers and its derivative with respect to the sum
                // (−a/b²) overflows f32 (NaN gradients in a toy fit). Such
                // nodes count as nearly empty.
                let weight_sum = Tensor::zeros((stencil.nodes, 1), self.dtype, cpu)?
                    .index_add(&stencil.node_index, &w, 0)?
                    .clamp(MIN_NODE_WEIGHT, f64::MAX)?;
                let spread = feature.index_select(&stencil.owner, 0)?.broadcast_mul(&w)?;
                let node_feature = Tensor::zeros((stencil.nodes, width), self.dtype, cpu)?
                    .index_add(&stencil.node_index, &spread, 0)?
                    .broadcast_div(&weight_sum)?;
                let node_in = Tensor::cat(&[&node_feature, &stencil.node_encoding], 1)?;
                let h = self.linear("dec1")?.forward(&node_in)?.relu()?;
                let h = self.linear("dec2")?.forward(&h)?.relu()?;
                let h = self
                    .linear("dec3")?
                    .forward(&Tensor::cat(&[&h, &node_in], 1)?)?
                    .relu()?;
                let node_velocity = self.bound(&self.linear("dec4")?.forward(&h)?)?;
                Ok(node_velocity
                    .index_select(&stencil.node_index, 0)?
                    .broadcast_mul(&w)?
                    .reshape((n, STENCIL, 3))?
                    .sum(1)?)
            }
            ResidualKind::None => Err(ResidualError::Input {
                field: "kind".into(),
                problem: "`none` has no network".into(),
            }),
        }
    }

    /// Δv for one frame (m/s, caller's order).
    pub fn predict(&self, inputs: &FrameInputs) -> Result<Vec<[f64; 3]>, ResidualError> {
        inputs.validate()?;
        let x = rows(&inputs.x_tilde, self.dtype)?;
        let v = rows(&inputs.v_tilde, self.dtype)?;
        let s = rows(&inputs.x_start, self.dtype)?;
        to_rows(&self.forward_tensors(&x, &v, &s, inputs)?)
    }

    /// Vector-Jacobian product: the gradients of ⟨Δv(inputs), `grad_dv`⟩
    /// with respect to the parameters and to x̃, ṽ and x_t (the history is
    /// treated as data: truncated back-propagation across frames goes
    /// through the physics state only).
    pub fn vjp(
        &self,
        inputs: &FrameInputs,
        grad_dv: &[[f64; 3]],
    ) -> Result<ResidualGrads, ResidualError> {
        inputs.validate()?;
        if grad_dv.len() != inputs.particle_count() {
            return Err(ResidualError::Input {
                field: "grad_dv".into(),
                problem: "length differs from the particle count".into(),
            });
        }
        let x = Var::from_tensor(&rows(&inputs.x_tilde, self.dtype)?)?;
        let v = Var::from_tensor(&rows(&inputs.v_tilde, self.dtype)?)?;
        let s = Var::from_tensor(&rows(&inputs.x_start, self.dtype)?)?;
        let dv = self.forward_tensors(x.as_tensor(), v.as_tensor(), s.as_tensor(), inputs)?;
        let surrogate = (dv * rows(grad_dv, self.dtype)?)?.sum_all()?;
        let grads = surrogate.backward()?;
        let mut parameters = Vec::with_capacity(self.parameter_count());
        for var in self.vars.values() {
            match grads.get(var.as_tensor()) {
                Some(g) => {
                    parameters.extend(g.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?)
                }
                None => parameters.extend(std::iter::repeat_n(0.0, var.elem_count())),
            }
        }
        let input_grad = |var: &Var| -> Result<Vec<[f64; 3]>, ResidualError> {
            match grads.get(var.as_tensor()) {
                Some(g) => to_rows(g),
                None => Ok(vec![[0.0; 3]; inputs.particle_count()]),
            }
        };
        Ok(ResidualGrads {
            parameters,
            x_tilde: input_grad(&x)?,
            v_tilde: input_grad(&v)?,
            x_start: input_grad(&s)?,
        })
    }

    pub fn parameter_count(&self) -> usize {
        self.vars.values().map(|v| v.elem_count()).sum()
    }

    /// All weights as one flat vector (sorted by tensor name).
    pub fn parameters(&self) -> Result<Vec<f64>, ResidualError> {
        let mut out = Vec::with_capacity(self.parameter_count());
        for var in self.vars.values() {
            out.extend(
                var.as_tensor()
                    .to_dtype(DType::F64)?
                    .flatten_all()?
                    .to_vec1::<f64>()?,
            );
        }
        Ok(out)
    }

    /// Replaces all weights from a flat vector in [`Residual::parameters`] order.
    pub fn set_parameters(&mut self, values: &[f64]) -> Result<(), ResidualError> {
        if values.len() != self.parameter_count() {
            return Err(ResidualError::Input {
                field: "parameters".into(),
                problem: format!(
                    "{} values for {} weights",
                    values.len(),
                    self.parameter_count()
                ),
            });
        }
        if values.iter().any(|v| !v.is_finite()) {
            return Err(ResidualError::Input {
                field: "parameters".into(),
                problem: "not finite".into(),
            });
        }
        let mut offset = 0;
        for var in self.vars.values() {
            let count = var.elem_count();
            let t = Tensor::from_vec(
                values[offset..offset + count].to_vec(),
                var.shape(),
                &Device::Cpu,
            )?
            .to_dtype(self.dtype)?;
            var.set(&t)?;
            offset += count;
        }
        Ok(())
    }

    /// Writes the weights as safetensors (to a temporary name, then renamed).
    pub fn save(&self, path: &Path) -> Result<(), ResidualError> {
        let tensors: HashMap<String, Tensor> = self
            .vars
            .iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
            .collect();
        let file_err = |e: &dyn std::fmt::Display| ResidualError::File {
            path: path.to_path_buf(),
            problem: format!("writing weights: {e}"),
        };
        let mut tmp = path.as_os_str().to_owned();
        tmp.push(".tmp");
        let tmp = std::path::PathBuf::from(tmp);
        candle_core::safetensors::save(&tensors, &tmp).map_err(|e| file_err(&e))?;
        std::fs::rename(&tmp, path).map_err(|e| file_err(&e))
    }

    /// Loads weights saved by [`Residual::save`] for `spec`, checking every
    /// tensor's name and shape.
    pub fn load(spec: ResidualSpec, path: &Path, dtype: DType) -> Result<Self, ResidualError> {
        let mut residual = Self::new(spec, dtype)?;
        let loaded = candle_core::safetensors::load(path, &Device::Cpu).map_err(|e| {
            ResidualError::File {
                path: path.to_path_buf(),
                problem: format!("reading weights: {e}"),
            }
        })?;
        for (name, var) in &mut residual.vars {
            let tensor = loaded.get(name).ok_or_else(|| ResidualError::File {
                path: path.to_path_buf(),
                problem: format!("tensor `{name}` is missing"),
            })?;
            if tensor.shape() != var.shape() {
                return Err(ResidualError::File {
                    path: path.to_path_buf(),
                    problem: format!(
                        "tensor `{name}` has shape {:?}, expected {:?}",
                        tensor.dims(),
                        var.dims()
                    ),
                });
            }
            var.set(&tensor.to_dtype(dtype)?)?;
        }
        if loaded.len() != residual.vars.len() {
            return Err(ResidualError::File {
                path: path.to_path_buf(),
                problem: format!("{} tensors, expected {}", loaded.len(), residual.vars.len()),
            });
        }
        Ok(residual)
    }
}
