//! The residual networks: [`ResidualKind::Pgnd`] (particle encoder → grid
//! decoder → particles) and [`ResidualKind::Mlp`], forward and
//! vector-Jacobian product written out layer by layer (`kernels`,
//! `transfer`).
//!
//! The bound: the decoder's raw output y becomes α·tanh(|y|)·y/|y|, a
//! vector no longer than α (method.md writes α·tanh per component, whose
//! norm can reach √3·α); Δv is a convex combination of such vectors (the
//! B-spline weights sum to one), so |Δv| ≤ α holds exactly.

use crate::ResidualError;
use crate::features::{CHANNELS, FrameInputs, HISTORY, ParticleState};
use crate::kernels::{
    Bound, Dense, GroupNorm, NormTape, Rows, Scalar, add_into, column_max, relu, relu_backward,
};
use crate::transfer::{self, Stencil};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
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

/// Widest layer a network may have: 32 times the default's widest, and a
/// bound on what a model file may ask to allocate (16.8 M weights a layer).
pub const MAX_LAYER_WIDTH: usize = 4096;

impl ResidualSpec {
    /// Checks the spec before anything is allocated for it: a kind with a
    /// network, positive widths up to [`MAX_LAYER_WIDTH`], groups dividing
    /// the encoder widths, a positive bound and grid.
    pub fn validate(&self) -> Result<(), ResidualError> {
        let invalid = |field: &str, problem: String| {
            Err(ResidualError::Input {
                field: field.into(),
                problem,
            })
        };
        if self.kind == ResidualKind::None {
            return invalid("kind", "`none` has no network".into());
        }
        let widths = self.size.encoder.iter().chain([&self.size.decoder]);
        if widths.clone().any(|&w| w == 0 || w > MAX_LAYER_WIDTH) {
            return invalid(
                "size",
                format!("every layer width must be between 1 and {MAX_LAYER_WIDTH}"),
            );
        }
        let groups = self.size.groups;
        if groups == 0 || self.size.encoder.iter().any(|w| w % groups != 0) {
            return invalid(
                "size.groups",
                format!("{groups} groups must divide every encoder width"),
            );
        }
        if !(self.alpha > 0.0 && self.grid_dx > 0.0 && self.domain_size > 0.0) {
            return invalid("alpha / grid_dx / domain_size", "must be positive".into());
        }
        Ok(())
    }

    /// How many weights a network of this spec has (after [`Self::validate`]).
    pub fn parameter_count(&self) -> Result<usize, ResidualError> {
        self.validate()?;
        Ok(Layout::new(self).total)
    }
}

/// Scale of the decoder's raw output before the bound. Adam's first steps
/// move every weight by about the learning rate whatever the gradient's
/// size; from a zero last layer that alone gave |Δv| ≈ 0.8 m/s (2.5 cm a
/// frame) and the train loss jumped 170× in a rope fit. Scaled by 1e-2,
/// early steps make cm/s corrections and the network grows into α.
pub const OUTPUT_SCALE: f64 = 1e-2;

/// Smallest B-spline weight sum a grid node's particle-to-node average
/// divides by. Nodes that only a particle's vanishing spline tail reaches
/// have a tiny weight sum: their feature is a ratio of two tiny numbers and
/// its derivative with respect to the sum (−a/b²) overflows f32 (NaN
/// gradients in a toy fit). Such nodes count as nearly empty.
pub const MIN_NODE_WEIGHT: f64 = 1e-6;

/// Fourier bands of the node-position encoding (method.md §5: L = 6).
pub const FOURIER_BANDS: usize = 6;
/// Columns of the node-position encoding: the position and a sine and a
/// cosine per band and axis.
pub const NODE_ENCODING: usize = 3 + 6 * FOURIER_BANDS;

/// The element type a network computes in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Precision {
    /// Rollouts and training.
    F32,
    /// Finite-difference gradient checks.
    F64,
}

/// The result of [`Residual::vjp`]: gradients of ⟨Δv, Δv̄⟩.
#[derive(Clone, Debug, PartialEq)]
pub struct ResidualGrads {
    /// Parameter gradient in [`Residual::parameters`] order.
    pub parameters: Vec<f64>,
    pub x_tilde: Vec<[f64; 3]>,
    pub v_tilde: Vec<[f64; 3]>,
    pub x_start: Vec<[f64; 3]>,
    /// (∂x, ∂v) of each history frame, newest first (the fit treats the
    /// history as data; a planner differentiating a whole rollout uses
    /// them).
    pub history: Vec<ParticleState>,
}

/// (∂x, ∂v) rows of each history frame, newest first.
type HistoryRows<T> = Vec<[Rows<T>; 2]>;

/// Where each named weight tensor sits in the flat parameter vector
/// (tensors sorted by name, each row-major).
#[derive(Clone, Debug, PartialEq)]
struct Layout {
    tensors: BTreeMap<String, (Vec<usize>, usize)>,
    total: usize,
}

impl Layout {
    fn new(spec: &ResidualSpec) -> Self {
        let mut shapes: BTreeMap<String, Vec<usize>> = BTreeMap::new();
        for (name, inputs, outputs) in layer_shapes(spec) {
            if name == "enc1" || name == "enc2" {
                shapes.insert(format!("{name}.norm.weight"), vec![outputs]);
                shapes.insert(format!("{name}.norm.bias"), vec![outputs]);
            }
            shapes.insert(format!("{name}.weight"), vec![outputs, inputs]);
            shapes.insert(format!("{name}.bias"), vec![outputs]);
        }
        let mut total = 0;
        let tensors = shapes
            .into_iter()
            .map(|(name, shape)| {
                let offset = total;
                total += shape.iter().product::<usize>();
                (name, (shape, offset))
            })
            .collect();
        Self { tensors, total }
    }

    fn range(&self, name: &str) -> std::ops::Range<usize> {
        let (shape, offset) = &self.tensors[name];
        *offset..offset + shape.iter().product::<usize>()
    }
}

#[derive(Clone, Debug)]
enum Weights {
    F32(Vec<f32>),
    F64(Vec<f64>),
}

/// A residual network with its weights.
#[derive(Clone, Debug)]
pub struct Residual {
    spec: ResidualSpec,
    layout: Layout,
    weights: Weights,
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

fn to_rows<T: Scalar>(values: &[[f64; 3]]) -> Rows<T> {
    Rows::from_values(
        values.iter().flatten().map(|v| T::lit(*v)),
        3 * values.len(),
        3,
    )
}

fn from_rows<T: Scalar>(m: &Rows<T>) -> Vec<[f64; 3]> {
    m.data
        .chunks(3)
        .map(|r| [r[0].widen(), r[1].widen(), r[2].widen()])
        .collect()
}

/// The network's view of its weights in one precision.
struct Net<'a, T> {
    spec: &'a ResidualSpec,
    layout: &'a Layout,
    weights: &'a [T],
}

/// Everything the backward pass needs of a forward pass.
struct Tape<T: Scalar> {
    x_tilde: Rows<T>,
    channels: Rows<T>,
    body: BodyTape<T>,
}

enum BodyTape<T: Scalar> {
    Mlp { hidden: [Rows<T>; 3], raw: Rows<T> },
    Pgnd(Box<GridTape<T>>),
}

struct GridTape<T: Scalar> {
    encoded: [Rows<T>; 2],
    norms: [NormTape<T>; 2],
    global: Vec<T>,
    global_at: Vec<usize>,
    feature: Rows<T>,
    stencil: Stencil,
    spline_weights: Rows<T>,
    node_feature: Rows<T>,
    weight_sums: Vec<T>,
    encoding: Rows<T>,
    decoded: [Rows<T>; 3],
    raw: Rows<T>,
    node_velocity: Rows<T>,
}

impl<'a, T: Scalar> Net<'a, T> {
    fn tensor(&self, name: &str) -> &'a [T] {
        &self.weights[self.layout.range(name)]
    }

    fn dense(&self, name: &str) -> Dense<'a, T> {
        let shape = &self.layout.tensors[&format!("{name}.weight")].0;
        Dense {
            weight: self.tensor(&format!("{name}.weight")),
            bias: self.tensor(&format!("{name}.bias")),
            inputs: shape[1],
            outputs: shape[0],
        }
    }

    fn norm(&self, name: &str) -> GroupNorm<'a, T> {
        GroupNorm {
            scale: self.tensor(&format!("{name}.norm.weight")),
            shift: self.tensor(&format!("{name}.norm.bias")),
            groups: self.spec.size.groups,
        }
    }

    fn bound(&self) -> Bound {
        Bound {
            alpha: self.spec.alpha,
            scale: OUTPUT_SCALE,
        }
    }

    /// The 27 input channels per particle: x̃, ṽ, x̃ − x_t and the history,
    /// positions centred on x̃'s centroid.
    fn channels(inputs: &FrameInputs) -> Rows<T> {
        let n = inputs.particle_count();
        let mut centroid = [0.0; 3];
        for x in &inputs.x_tilde {
            for a in 0..3 {
                centroid[a] += x[a] / n as f64;
            }
        }
        let centroid = centroid.map(T::lit);
        let mut m = Rows::zeros(n, CHANNELS);
        for (p, row) in m.data.chunks_mut(CHANNELS).enumerate() {
            let x = inputs.x_tilde[p].map(T::lit);
            let start = inputs.x_start[p].map(T::lit);
            for a in 0..3 {
                row[a] = x[a] - centroid[a];
                row[3 + a] = T::lit(inputs.v_tilde[p][a]);
                row[6 + a] = x[a] - start[a];
            }
            for (k, (hx, hv)) in inputs.history.iter().enumerate() {
                for a in 0..3 {
                    row[9 + 6 * k + a] = T::lit(hx[p][a]) - centroid[a];
                    row[12 + 6 * k + a] = T::lit(hv[p][a]);
                }
            }
        }
        m
    }

    /// (∂x, ∂v) of each history frame (newest first) from the channels'
    /// gradient.
    fn history_backward(grad: &Rows<T>) -> HistoryRows<T> {
        let n = grad.rows();
        (0..HISTORY)
            .map(|k| {
                let mut out = [Rows::zeros(n, 3), Rows::zeros(n, 3)];
                for p in 0..n {
                    let g = grad.row(p);
                    for a in 0..3 {
                        out[0].data[3 * p + a] = g[9 + 6 * k + a];
                        out[1].data[3 * p + a] = g[12 + 6 * k + a];
                    }
                }
                out
            })
            .collect()
    }

    /// (∂x̃, ∂ṽ, ∂x_t) from the channels' gradient (the centroid is x̃'s).
    fn channels_backward(grad: &Rows<T>) -> [Rows<T>; 3] {
        let n = grad.rows();
        let mut out = [0, 1, 2].map(|_| Rows::zeros(n, 3));
        let mut centroid = [T::zero(); 3];
        for p in 0..n {
            let g = grad.row(p);
            for a in 0..3 {
                let mut centred = g[a];
                for k in 0..HISTORY {
                    centred = centred + g[9 + 6 * k + a];
                }
                centroid[a] = centroid[a] - centred;
                out[0].data[3 * p + a] = g[a] + g[6 + a];
                out[1].data[3 * p + a] = g[3 + a];
                out[2].data[3 * p + a] = -g[6 + a];
            }
        }
        let share = T::lit(1.0 / n as f64);
        for row in out[0].data.chunks_mut(3) {
            for a in 0..3 {
                row[a] = row[a] + centroid[a] * share;
            }
        }
        out
    }

    /// Fourier encoding of each node's position in the domain.
    fn node_encoding(&self, stencil: &Stencil) -> Rows<T> {
        let s = self.spec;
        let mut m = Rows::zeros(stencil.nodes(), NODE_ENCODING);
        for (node, row) in stencil.cells.iter().zip(m.data.chunks_mut(NODE_ENCODING)) {
            let q = [0, 1, 2].map(|a| node[a] as f64 * s.grid_dx / s.domain_size);
            let mut values = q.to_vec();
            for band in 0..FOURIER_BANDS {
                let frequency = (1u32 << band) as f64 * std::f64::consts::PI;
                values.extend(q.map(|c| (frequency * c).sin()));
                values.extend(q.map(|c| (frequency * c).cos()));
            }
            for (r, v) in row.iter_mut().zip(values) {
                *r = T::lit(v);
            }
        }
        m
    }

    fn forward(&self, inputs: &FrameInputs) -> (Rows<T>, Tape<T>) {
        let channels = Self::channels(inputs);
        let x_tilde = to_rows::<T>(&inputs.x_tilde);
        let (dv, body) = match self.spec.kind {
            ResidualKind::Pgnd => {
                let (dv, tape) = self.grid_forward(&x_tilde, &channels, inputs);
                (dv, BodyTape::Pgnd(Box::new(tape)))
            }
            ResidualKind::Mlp | ResidualKind::None => {
                // `Residual::new` refuses `None`.
                let mut h1 = self.dense("mlp1").forward(&[&channels], None);
                relu(&mut h1);
                let mut h2 = self.dense("mlp2").forward(&[&h1], None);
                relu(&mut h2);
                let mut h3 = self.dense("mlp3").forward(&[&h2, &channels], None);
                relu(&mut h3);
                let raw = self.dense("mlp4").forward(&[&h3], None);
                let dv = self.bound().forward(&raw);
                (
                    dv,
                    BodyTape::Mlp {
                        hidden: [h1, h2, h3],
                        raw,
                    },
                )
            }
        };
        (
            dv,
            Tape {
                x_tilde,
                channels,
                body,
            },
        )
    }

    fn grid_forward(
        &self,
        x_tilde: &Rows<T>,
        channels: &Rows<T>,
        inputs: &FrameInputs,
    ) -> (Rows<T>, GridTape<T>) {
        let s = self.spec;
        let e2 = s.size.encoder[1];
        let (mut h1, norm1) = self
            .norm("enc1")
            .forward(&self.dense("enc1").forward(&[channels], None));
        relu(&mut h1);
        let (mut h2, norm2) = self
            .norm("enc2")
            .forward(&self.dense("enc2").forward(&[&h1], None));
        relu(&mut h2);
        // [h, max-pool(h)]·Wᵀ + b: the pooled half is the same for every
        // particle, so it is folded into the bias.
        let (global, global_at) = column_max(&h2);
        let enc3 = self.dense("enc3");
        let bias: Vec<T> = (0..enc3.outputs)
            .map(|o| {
                let w = &enc3.weight[o * enc3.inputs + e2..(o + 1) * enc3.inputs];
                w.iter()
                    .zip(&global)
                    .fold(enc3.bias[o], |acc, (a, b)| acc + *a * *b)
            })
            .collect();
        let feature = enc3.forward(&[&h2], Some(&bias));

        let stencil = Stencil::new(&inputs.x_tilde, s.grid_origin, s.grid_dx);
        let spline_weights = transfer::spline_weights(x_tilde, &stencil, s.grid_origin, s.grid_dx);
        let (node_feature, weight_sums) =
            transfer::node_means(&feature, &spline_weights, &stencil, MIN_NODE_WEIGHT);
        let encoding = self.node_encoding(&stencil);
        let mut d1 = self
            .dense("dec1")
            .forward(&[&node_feature, &encoding], None);
        relu(&mut d1);
        let mut d2 = self.dense("dec2").forward(&[&d1], None);
        relu(&mut d2);
        let mut d3 = self
            .dense("dec3")
            .forward(&[&d2, &node_feature, &encoding], None);
        relu(&mut d3);
        let raw = self.dense("dec4").forward(&[&d3], None);
        let node_velocity = self.bound().forward(&raw);
        let dv = transfer::to_particles(&node_velocity, &spline_weights, &stencil);
        (
            dv,
            GridTape {
                encoded: [h1, h2],
                norms: [norm1, norm2],
                global,
                global_at,
                feature,
                stencil,
                spline_weights,
                node_feature,
                weight_sums,
                encoding,
                decoded: [d1, d2, d3],
                raw,
                node_velocity,
            },
        )
    }

    /// Adds ∂L/∂W and ∂L/∂b of layer `name` to the flat gradient.
    fn dense_backward(
        &self,
        name: &str,
        blocks: &[&Rows<T>],
        grad: &Rows<T>,
        wanted: &[bool],
        flat: &mut [T],
    ) -> Vec<Option<Rows<T>>> {
        let layer = self.dense(name);
        let mut weight_grad = vec![T::zero(); layer.weight.len()];
        let mut bias_grad = vec![T::zero(); layer.bias.len()];
        let out = layer.backward(blocks, grad, wanted, &mut weight_grad, &mut bias_grad);
        self.add_gradient(flat, &format!("{name}.weight"), &weight_grad);
        self.add_gradient(flat, &format!("{name}.bias"), &bias_grad);
        out
    }

    /// Adds `values` to tensor `name`'s slice of the flat gradient.
    fn add_gradient(&self, flat: &mut [T], name: &str, values: &[T]) {
        add_into(&mut flat[self.layout.range(name)], values);
    }

    fn norm_backward(
        &self,
        name: &str,
        tape: &NormTape<T>,
        grad: &Rows<T>,
        flat: &mut [T],
    ) -> Rows<T> {
        let norm = self.norm(name);
        let mut scale = vec![T::zero(); norm.scale.len()];
        let mut shift = vec![T::zero(); norm.shift.len()];
        let out = norm.backward(tape, grad, &mut scale, &mut shift);
        self.add_gradient(flat, &format!("{name}.norm.weight"), &scale);
        self.add_gradient(flat, &format!("{name}.norm.bias"), &shift);
        out
    }

    /// The flat parameter gradient, (∂x̃, ∂ṽ, ∂x_t) and the history's
    /// (∂x, ∂v) of ⟨Δv, `grad`⟩.
    fn backward(&self, tape: &Tape<T>, grad: &Rows<T>) -> (Vec<T>, [Rows<T>; 3], HistoryRows<T>) {
        let mut flat = vec![T::zero(); self.layout.total];
        let (d_channels, d_x_weights) = match &tape.body {
            BodyTape::Mlp { hidden, raw } => {
                let [h1, h2, h3] = hidden;
                let d_raw = self.bound().backward(raw, grad);
                let mut d3 = block_gradient(
                    self.dense_backward("mlp4", &[h3], &d_raw, &[true], &mut flat),
                    0,
                );
                relu_backward(h3, &mut d3);
                let mut mlp3_inputs = self.dense_backward(
                    "mlp3",
                    &[h2, &tape.channels],
                    &d3,
                    &[true, true],
                    &mut flat,
                );
                let mut d2 = take_block_gradient(&mut mlp3_inputs, 0);
                let d_channels_direct = take_block_gradient(&mut mlp3_inputs, 1);
                relu_backward(h2, &mut d2);
                let mut d1 = block_gradient(
                    self.dense_backward("mlp2", &[h1], &d2, &[true], &mut flat),
                    0,
                );
                relu_backward(h1, &mut d1);
                let mut d_channels = block_gradient(
                    self.dense_backward("mlp1", &[&tape.channels], &d1, &[true], &mut flat),
                    0,
                );
                add_into(&mut d_channels.data, &d_channels_direct.data);
                (d_channels, None)
            }
            BodyTape::Pgnd(g) => {
                let (dc, dx) =
                    self.grid_backward(g, &tape.x_tilde, &tape.channels, grad, &mut flat);
                (dc, Some(dx))
            }
        };
        let mut inputs = Self::channels_backward(&d_channels);
        if let Some(dx) = d_x_weights {
            add_into(&mut inputs[0].data, &dx.data);
        }
        (flat, inputs, Self::history_backward(&d_channels))
    }

    /// Backward through decoder, transfers and encoder: (∂channels, ∂x̃
    /// through the spline weights).
    fn grid_backward(
        &self,
        g: &GridTape<T>,
        x_tilde: &Rows<T>,
        channels: &Rows<T>,
        grad: &Rows<T>,
        flat: &mut [T],
    ) -> (Rows<T>, Rows<T>) {
        let s = self.spec;
        let e2 = s.size.encoder[1];
        let (d_node_velocity, mut d_spline_weights) =
            transfer::to_particles_backward(&g.node_velocity, &g.spline_weights, &g.stencil, grad);
        let d_raw = self.bound().backward(&g.raw, &d_node_velocity);
        let [d1, d2, d3] = &g.decoded;
        let mut dd3 = block_gradient(self.dense_backward("dec4", &[d3], &d_raw, &[true], flat), 0);
        relu_backward(d3, &mut dd3);
        let mut dec3_inputs = self.dense_backward(
            "dec3",
            &[d2, &g.node_feature, &g.encoding],
            &dd3,
            &[true, true, false],
            flat,
        );
        let mut dd2 = take_block_gradient(&mut dec3_inputs, 0);
        let mut d_node_feature = take_block_gradient(&mut dec3_inputs, 1);
        relu_backward(d2, &mut dd2);
        let mut dd1 = block_gradient(self.dense_backward("dec2", &[d1], &dd2, &[true], flat), 0);
        relu_backward(d1, &mut dd1);
        let from_dec1 = block_gradient(
            self.dense_backward(
                "dec1",
                &[&g.node_feature, &g.encoding],
                &dd1,
                &[true, false],
                flat,
            ),
            0,
        );
        add_into(&mut d_node_feature.data, &from_dec1.data);
        let (d_feature, d_spline_weights_means) = transfer::node_means_backward(
            &g.feature,
            &g.spline_weights,
            &g.stencil,
            MIN_NODE_WEIGHT,
            &g.node_feature,
            &g.weight_sums,
            &d_node_feature,
        );
        add_into(&mut d_spline_weights.data, &d_spline_weights_means.data);
        let d_x = transfer::spline_weights_backward(
            x_tilde,
            &g.stencil,
            s.grid_origin,
            s.grid_dx,
            &d_spline_weights,
        );

        // enc3 with its pooled half folded into the bias.
        let [h1, h2] = &g.encoded;
        let mut dh2 = block_gradient(
            self.dense_backward("enc3", &[h2], &d_feature, &[true], flat),
            0,
        );
        let enc3 = self.dense("enc3");
        // enc3's bias gradient, which `dense_backward` just wrote (the bias
        // gets no other contribution), is the pooled half's too.
        let bias_grad = flat[self.layout.range("enc3.bias")].to_vec();
        let weight_range = self.layout.range("enc3.weight");
        for o in 0..enc3.outputs {
            for c in 0..e2 {
                let at = weight_range.start + o * enc3.inputs + e2 + c;
                flat[at] = flat[at] + bias_grad[o] * g.global[c];
            }
        }
        for c in 0..e2 {
            let d_global = (0..enc3.outputs).fold(T::zero(), |acc, o| {
                acc + enc3.weight[o * enc3.inputs + e2 + c] * bias_grad[o]
            });
            let at = g.global_at[c] * e2 + c;
            dh2.data[at] = dh2.data[at] + d_global;
        }
        relu_backward(h2, &mut dh2);
        let dz2 = self.norm_backward("enc2", &g.norms[1], &dh2, flat);
        let mut dh1 = block_gradient(self.dense_backward("enc2", &[h1], &dz2, &[true], flat), 0);
        relu_backward(h1, &mut dh1);
        let dz1 = self.norm_backward("enc1", &g.norms[0], &dh1, flat);
        let d_channels = block_gradient(
            self.dense_backward("enc1", &[channels], &dz1, &[true], flat),
            0,
        );
        (d_channels, d_x)
    }
}

/// The 27 input channels of every particle (row-major, particles × 27):
/// x̃, ṽ, x̃ − x_t and the history, positions centred on x̃'s centroid.
pub fn input_channels(inputs: &FrameInputs) -> Vec<f64> {
    std::mem::take(&mut Net::<f64>::channels(inputs).data)
}

/// The adjoints of x̃, ṽ, x_t and of the history's (x, v), newest first,
/// from the adjoint of [`input_channels`]' matrix.
pub fn input_channels_backward(grad: Vec<f64>) -> ([Vec<[f64; 3]>; 3], Vec<ParticleState>) {
    let rows = grad.len() / CHANNELS;
    let grad = Rows::from_values(grad, rows * CHANNELS, CHANNELS);
    let [x, v, s] = Net::<f64>::channels_backward(&grad);
    let history = Net::<f64>::history_backward(&grad)
        .iter()
        .map(|[hx, hv]| (from_rows(hx), from_rows(hv)))
        .collect();
    ([from_rows(&x), from_rows(&v), from_rows(&s)], history)
}

/// [`take_block_gradient`] from a list not needed afterwards.
fn block_gradient<T: Scalar>(mut blocks: Vec<Option<Rows<T>>>, i: usize) -> Rows<T> {
    take_block_gradient(&mut blocks, i)
}

/// Block `i`'s gradient from `Dense::backward`'s list (one asked for).
fn take_block_gradient<T: Scalar>(blocks: &mut [Option<Rows<T>>], i: usize) -> Rows<T> {
    blocks[i].take().expect("the gradient of a wanted block")
}

impl Residual {
    /// A freshly initialised network: PyTorch's default uniform
    /// initialisation, except the last layer, which starts at zero so that
    /// an untrained residual changes nothing.
    pub fn new(spec: ResidualSpec, precision: Precision) -> Result<Self, ResidualError> {
        spec.validate()?;
        let layout = Layout::new(&spec);
        let mut values = vec![0.0; layout.total];
        let mut uniform = uniform_stream(spec.seed);
        let shapes = layer_shapes(&spec);
        let last = shapes.len() - 1;
        for (i, (name, inputs, _)) in shapes.into_iter().enumerate() {
            let bound = if i == last {
                0.0
            } else {
                1.0 / (inputs as f64).sqrt()
            };
            for tensor in ["weight", "bias"] {
                for v in &mut values[layout.range(&format!("{name}.{tensor}"))] {
                    *v = bound * (2.0 * uniform() - 1.0);
                }
            }
            if name == "enc1" || name == "enc2" {
                values[layout.range(&format!("{name}.norm.weight"))].fill(1.0);
            }
        }
        let weights = match precision {
            Precision::F32 => Weights::F32(values.iter().map(|v| *v as f32).collect()),
            Precision::F64 => Weights::F64(values),
        };
        Ok(Self {
            spec,
            layout,
            weights,
        })
    }

    pub fn spec(&self) -> &ResidualSpec {
        &self.spec
    }

    /// The element type the network computes in.
    pub fn precision(&self) -> Precision {
        match self.weights {
            Weights::F32(_) => Precision::F32,
            Weights::F64(_) => Precision::F64,
        }
    }

    fn net<'a, T>(&'a self, weights: &'a [T]) -> Net<'a, T> {
        Net {
            spec: &self.spec,
            layout: &self.layout,
            weights,
        }
    }

    /// Refuses what the grid transfer cannot index: particles beyond 1e9
    /// cells of the grid's origin, or more slots than u32 counts.
    fn check_grid(&self, inputs: &FrameInputs) -> Result<(), ResidualError> {
        const FARTHEST_CELL: f64 = 1e9;
        if inputs.particle_count() > (u32::MAX as usize) / 27 {
            return Err(ResidualError::Input {
                field: "x_tilde".into(),
                problem: format!(
                    "{} particles, at most {}",
                    inputs.particle_count(),
                    u32::MAX / 27
                ),
            });
        }
        let s = &self.spec;
        for (p, x) in inputs.x_tilde.iter().enumerate() {
            if (0..3).any(|a| ((x[a] - s.grid_origin[a]) / s.grid_dx).abs() >= FARTHEST_CELL) {
                return Err(ResidualError::Input {
                    field: "x_tilde".into(),
                    problem: format!("particle {p} is more than 1e9 cells from the grid"),
                });
            }
        }
        Ok(())
    }

    /// Δv for one frame (m/s, caller's order).
    pub fn predict(&self, inputs: &FrameInputs) -> Result<Vec<[f64; 3]>, ResidualError> {
        self.check_inputs(inputs)?;
        Ok(match &self.weights {
            Weights::F32(w) => from_rows(&self.net(w).forward(inputs).0),
            Weights::F64(w) => from_rows(&self.net(w).forward(inputs).0),
        })
    }

    /// Vector-Jacobian product: the gradients of ⟨Δv(inputs), `grad_dv`⟩
    /// with respect to the parameters, x̃, ṽ, x_t and the history.
    pub fn vjp(
        &self,
        inputs: &FrameInputs,
        grad_dv: &[[f64; 3]],
    ) -> Result<ResidualGrads, ResidualError> {
        self.check_inputs(inputs)?;
        if grad_dv.len() != inputs.particle_count() {
            return Err(ResidualError::Input {
                field: "grad_dv".into(),
                problem: "length differs from the particle count".into(),
            });
        }
        fn run<T: Scalar>(
            net: Net<'_, T>,
            inputs: &FrameInputs,
            grad_dv: &[[f64; 3]],
        ) -> ResidualGrads {
            let (_, tape) = net.forward(inputs);
            let (flat, [x, v, s], history) = net.backward(&tape, &to_rows(grad_dv));
            ResidualGrads {
                parameters: flat.iter().map(|g| g.widen()).collect(),
                x_tilde: from_rows(&x),
                v_tilde: from_rows(&v),
                x_start: from_rows(&s),
                history: history
                    .iter()
                    .map(|[hx, hv]| (from_rows(hx), from_rows(hv)))
                    .collect(),
            }
        }
        Ok(match &self.weights {
            Weights::F32(w) => run(self.net(w), inputs, grad_dv),
            Weights::F64(w) => run(self.net(w), inputs, grad_dv),
        })
    }

    pub fn parameter_count(&self) -> usize {
        self.layout.total
    }

    /// The shape and the slice of [`Residual::parameters`] of weight tensor
    /// `name` (`enc1.weight`: outputs × inputs, `enc1.bias`,
    /// `enc1.norm.weight`, …), for other backends running the same layers.
    pub fn tensor(&self, name: &str) -> Option<(Vec<usize>, std::ops::Range<usize>)> {
        let (shape, _) = self.layout.tensors.get(name)?;
        Some((shape.clone(), self.layout.range(name)))
    }

    /// Checks `inputs` as [`Residual::predict`] does: sizes, finiteness and
    /// the grid's reach.
    pub fn check_inputs(&self, inputs: &FrameInputs) -> Result<(), ResidualError> {
        inputs.validate()?;
        self.check_grid(inputs)
    }

    /// All weights as one flat vector (tensors sorted by name).
    pub fn parameters(&self) -> Result<Vec<f64>, ResidualError> {
        Ok(match &self.weights {
            Weights::F32(w) => w.iter().map(|v| f64::from(*v)).collect(),
            Weights::F64(w) => w.clone(),
        })
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
        let finite = match &self.weights {
            Weights::F32(_) => values.iter().all(|v| (*v as f32).is_finite()),
            Weights::F64(_) => values.iter().all(|v| v.is_finite()),
        };
        if !finite {
            return Err(ResidualError::Input {
                field: "parameters".into(),
                problem: "not finite".into(),
            });
        }
        match &mut self.weights {
            Weights::F32(w) => w.iter_mut().zip(values).for_each(|(w, v)| *w = *v as f32),
            Weights::F64(w) => w.copy_from_slice(values),
        }
        Ok(())
    }

    /// Writes the weights as safetensors in the network's precision (to a
    /// temporary name, then renamed).
    pub fn save(&self, path: &Path) -> Result<(), ResidualError> {
        let file_err = |e: &dyn std::fmt::Display| ResidualError::File {
            path: path.to_path_buf(),
            problem: format!("writing weights: {e}"),
        };
        let (dtype, bytes): (safetensors::Dtype, Vec<u8>) = match &self.weights {
            Weights::F32(w) => (
                safetensors::Dtype::F32,
                w.iter().flat_map(|v| v.to_le_bytes()).collect(),
            ),
            Weights::F64(w) => (
                safetensors::Dtype::F64,
                w.iter().flat_map(|v| v.to_le_bytes()).collect(),
            ),
        };
        let element = dtype.bitsize() / 8;
        let mut views = Vec::with_capacity(self.layout.tensors.len());
        for (name, (shape, _)) in &self.layout.tensors {
            let range = self.layout.range(name);
            let view = safetensors::tensor::TensorView::new(
                dtype,
                shape.clone(),
                &bytes[range.start * element..range.end * element],
            )
            .map_err(|e| file_err(&e))?;
            views.push((name.clone(), view));
        }
        let mut tmp = path.as_os_str().to_owned();
        tmp.push(".tmp");
        let tmp = std::path::PathBuf::from(tmp);
        let written = safetensors::serialize_to_file(views, None, &tmp)
            .map_err(|e| file_err(&e))
            .and_then(|()| std::fs::rename(&tmp, path).map_err(|e| file_err(&e)));
        if written.is_err() {
            // Nothing half-written stays behind.
            let _ = std::fs::remove_file(&tmp);
        }
        written
    }

    /// Loads weights saved by [`Residual::save`] (f32 or f64) for `spec`,
    /// checking every tensor's name and shape.
    pub fn load(
        spec: ResidualSpec,
        path: &Path,
        precision: Precision,
    ) -> Result<Self, ResidualError> {
        let mut residual = Self::new(spec, precision)?;
        let file_err = |problem: String| ResidualError::File {
            path: path.to_path_buf(),
            problem,
        };
        let bytes = std::fs::read(path).map_err(|e| file_err(format!("reading weights: {e}")))?;
        let loaded = safetensors::SafeTensors::deserialize(&bytes)
            .map_err(|e| file_err(format!("reading weights: {e}")))?;
        let mut values = vec![0.0; residual.layout.total];
        for (name, (shape, _)) in &residual.layout.tensors {
            let tensor = loaded
                .tensor(name)
                .map_err(|_| file_err(format!("tensor `{name}` is missing")))?;
            if tensor.shape() != shape.as_slice() {
                return Err(file_err(format!(
                    "tensor `{name}` has shape {:?}, expected {shape:?}",
                    tensor.shape()
                )));
            }
            let data = tensor.data();
            let target = &mut values[residual.layout.range(name)];
            let element = tensor.dtype().bitsize() / 8;
            if data.len() != target.len() * element {
                return Err(file_err(format!(
                    "tensor `{name}` holds {} bytes, expected {}",
                    data.len(),
                    target.len() * element
                )));
            }
            match tensor.dtype() {
                safetensors::Dtype::F32 => {
                    for (t, b) in target.iter_mut().zip(data.chunks_exact(4)) {
                        *t = f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]]));
                    }
                }
                safetensors::Dtype::F64 => {
                    for (t, b) in target.iter_mut().zip(data.chunks_exact(8)) {
                        *t = f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]);
                    }
                }
                other => {
                    return Err(file_err(format!(
                        "tensor `{name}` is {other:?}, expected F32 or F64"
                    )));
                }
            }
        }
        if loaded.len() != residual.layout.tensors.len() {
            return Err(file_err(format!(
                "{} tensors, expected {}",
                loaded.len(),
                residual.layout.tensors.len()
            )));
        }
        residual
            .set_parameters(&values)
            .map_err(|e| file_err(format!("{e}")))?;
        Ok(residual)
    }
}
