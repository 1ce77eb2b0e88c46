//! The neural residual on the GPU: dm-residual's networks (PNPGD and the
//! per-particle MLP), forward pass and vector-Jacobian product, layer by
//! layer as CUDA kernels (`kernels/residual.cu`, `residual_backward.cu`).
//!
//! Like the CPU network it takes a frame's inputs from the host and hands
//! Δv (or the gradients) back to it; the weights stay on the device. The
//! input channels and their adjoint are formed on the host (27 numbers a
//! particle), everything between on the device. Grid nodes are numbered in
//! cell order (the CPU numbers them by first use), and node sums use atomic
//! adds: f32 results agree with the CPU's to round-off.

use crate::device::CudaDevice;
use crate::error::CudaError;
use crate::kernels::RESIDUAL_ENTRY_POINTS;
use crate::launch::{SCAN_CHUNK, SCAN_THREADS, launch_for};
use crate::world::DeviceReal;
use cudarc::driver::{
    CudaFunction, CudaSlice, CudaStream, CudaView, CudaViewMut, LaunchConfig, PushKernelArg,
};
use dm_residual::network::{
    FOURIER_BANDS, MIN_NODE_WEIGHT, NODE_ENCODING, OUTPUT_SCALE, input_channels,
    input_channels_backward,
};
use dm_residual::{CHANNELS, FrameInputs, Residual, ResidualError, ResidualGrads, ResidualKind};
use std::collections::HashMap;
use std::sync::Arc;

/// Nodes of one particle's stencil.
const STENCIL: usize = 27;
/// residual.cu's GEMM_TILE and GEMM_THREADS.
const GEMM_TILE: usize = 64;
const GEMM_THREADS: u32 = 256;
/// residual.cu's REDUCE_ROWS.
const REDUCE_ROWS: usize = 256;
/// The largest box of cells the nodes are numbered in (12 bytes a cell:
/// marks, their scan and node ids, 768 MiB at most).
const MAX_STENCIL_CELLS: usize = 1 << 26;
/// The MPM module's entry points the residual uses too (the scan).
const SCAN_ENTRY_POINTS: [&str; 2] = ["scan_chunks", "scan_sums"];

/// A residual network with its weights on the GPU.
#[derive(Debug)]
pub struct CudaResidual<T: DeviceReal> {
    device: Arc<CudaDevice>,
    functions: HashMap<&'static str, CudaFunction>,
    /// Spec, weight layout and input checks; its weights mirror the device's.
    network: Residual,
    weights: CudaSlice<T>,
}

/// Offsets of one dense layer's tensors in the flat weight vector.
#[derive(Clone, Copy, Debug)]
struct Layer {
    weight: usize,
    bias: usize,
    inputs: usize,
    outputs: usize,
}

/// Offsets of one GroupNorm's scale and shift.
#[derive(Clone, Copy, Debug)]
struct Norm {
    scale: usize,
    shift: usize,
}

/// A matrix operand of [`Ops::gemm`]: element (i, j) at i·rows + j·columns.
struct Operand<'a, T> {
    data: CudaView<'a, T>,
    rows: i64,
    columns: i64,
}

/// A row-major matrix (`rows × width`), as a GEMM operand.
fn row_major<T>(data: CudaView<'_, T>, width: usize) -> Operand<'_, T> {
    Operand {
        data,
        rows: width as i64,
        columns: 1,
    }
}

/// The transpose of a row-major matrix (`rows × width`).
fn transposed<T>(data: CudaView<'_, T>, width: usize) -> Operand<'_, T> {
    Operand {
        data,
        rows: 1,
        columns: width as i64,
    }
}

/// What GroupNorm's backward pass needs of its forward pass.
#[derive(Debug)]
struct NormTape<T> {
    normalised: CudaSlice<T>,
    square_sums: CudaSlice<f64>,
}

/// The particles' stencils: base cells, node numbering and slot → node.
#[derive(Debug)]
struct DeviceStencil {
    /// The grid the base cells are counted on.
    origin: [f64; 3],
    dx: f64,
    base: CudaSlice<i32>,
    node_of: CudaSlice<i32>,
    node_cell: CudaSlice<i64>,
    nodes: usize,
    lo: [i32; 3],
    dims: [i32; 3],
}

/// Everything the backward pass needs of a forward pass.
#[derive(Debug)]
struct Tape<T> {
    x_tilde: CudaSlice<T>,
    channels: CudaSlice<T>,
    body: Body<T>,
}

#[derive(Debug)]
enum Body<T> {
    Mlp(Box<MlpTape<T>>),
    Pgnd(Box<GridTape<T>>),
}

#[derive(Debug)]
struct MlpTape<T> {
    hidden: [CudaSlice<T>; 3],
    raw: CudaSlice<T>,
}

#[derive(Debug)]
struct GridTape<T> {
    encoded: [CudaSlice<T>; 2],
    norms: [NormTape<T>; 2],
    pooled: CudaSlice<T>,
    pooled_at: CudaSlice<i32>,
    feature: CudaSlice<T>,
    stencil: DeviceStencil,
    spline_weights: CudaSlice<T>,
    node_feature: CudaSlice<T>,
    weight_sums: CudaSlice<T>,
    encoding: CudaSlice<T>,
    decoded: [CudaSlice<T>; 3],
    raw: CudaSlice<T>,
    node_velocity: CudaSlice<T>,
}

/// The launches of the residual's kernels on one stream.
struct Ops<'a> {
    stream: &'a Arc<CudaStream>,
    functions: &'a HashMap<&'static str, CudaFunction>,
}

/// Launches kernel `$name` over `$config` with `$args` (references to
/// locals and buffers) in the kernel's parameter order.
macro_rules! launch {
    ($ops:expr, $name:literal, $config:expr, [$($arg:expr),* $(,)?]) => {{
        let mut builder = $ops.stream.launch_builder($ops.function($name));
        $(builder.arg($arg);)*
        // SAFETY: each call lists the arguments in the order and of the
        // types of the kernel's signature (kernels/residual*.cu, sort.cu),
        // and its launch shape covers only what its buffers hold.
        unsafe { builder.launch($config) }.map(drop).map_err(CudaError::from)
    }};
}

/// Launch shape of `blocks` blocks of GEMM_THREADS.
fn blocks_of(grid: (u32, u32, u32), threads: u32) -> LaunchConfig {
    LaunchConfig {
        grid_dim: grid,
        block_dim: (threads, 1, 1),
        shared_mem_bytes: 0,
    }
}

/// Waits for a call's stream when the call returns, an error included: its
/// kernels read the weights, which must outlive them (buffers carry no
/// events, docs/gpu.md "Streams").
struct WaitOnExit<'a>(&'a Arc<CudaStream>);

impl Drop for WaitOnExit<'_> {
    fn drop(&mut self) {
        // A failed wait leaves the context failed; the next call reports it.
        let _ = self.0.synchronize();
    }
}

impl<T: DeviceReal> CudaResidual<T> {
    /// `network` (its spec and weights) on `device`; compiles the kernels
    /// of T's precision on first use.
    pub fn new(device: Arc<CudaDevice>, network: &Residual) -> Result<Self, CudaError> {
        let module = device.module(T::PRECISION)?;
        let mut functions = HashMap::new();
        for name in RESIDUAL_ENTRY_POINTS.iter().chain(&SCAN_ENTRY_POINTS) {
            functions.insert(*name, module.load_function(name)?);
        }
        let host: Vec<T> = network.parameters()?.into_iter().map(T::lit).collect();
        let weights = device.stream().clone_htod(&host)?;
        // Each call reads the weights from a stream of its own.
        device.stream().synchronize()?;
        Ok(Self {
            device,
            functions,
            network: network.clone(),
            weights,
        })
    }

    pub fn parameter_count(&self) -> usize {
        self.network.parameter_count()
    }

    /// Replaces all weights (in `Residual::parameters` order).
    pub fn set_parameters(&mut self, values: &[f64]) -> Result<(), CudaError> {
        self.network.set_parameters(values)?;
        let host: Vec<T> = values.iter().map(|v| T::lit(*v)).collect();
        self.device.stream().memcpy_htod(&host, &mut self.weights)?;
        self.device.stream().synchronize()?;
        Ok(())
    }

    /// Δv for one frame (m/s, caller's order).
    pub fn predict(&self, inputs: &FrameInputs) -> Result<Vec<[f64; 3]>, CudaError> {
        self.network.check_inputs(inputs)?;
        check_size(inputs.particle_count())?;
        let device = self.device.with_own_stream()?;
        let _finished = WaitOnExit(device.stream());
        let ops = self.ops(&device);
        let (dv, _) = self.forward(&ops, inputs)?;
        Ok(triples(&ops.stream.clone_dtoh(&dv)?))
    }

    /// The gradients of ⟨Δv(inputs), `grad_dv`⟩ with respect to the
    /// weights, x̃, ṽ, x_t and the history (as `Residual::vjp`).
    pub fn vjp(
        &self,
        inputs: &FrameInputs,
        grad_dv: &[[f64; 3]],
    ) -> Result<ResidualGrads, CudaError> {
        self.network.check_inputs(inputs)?;
        if grad_dv.len() != inputs.particle_count() {
            return Err(ResidualError::Input {
                field: "grad_dv".into(),
                problem: "length differs from the particle count".into(),
            }
            .into());
        }
        check_size(inputs.particle_count())?;
        let device = self.device.with_own_stream()?;
        let _finished = WaitOnExit(device.stream());
        let ops = self.ops(&device);
        let (_, tape) = self.forward(&ops, inputs)?;
        let grad = ops.stream.clone_htod(&flatten::<T>(grad_dv))?;
        let mut flat = ops.stream.alloc_zeros::<T>(self.parameter_count())?;
        let n = inputs.particle_count();
        let (d_channels, d_x) = self.backward(&ops, &tape, &grad, n, &mut flat)?;
        let d_channels: Vec<f64> = ops
            .stream
            .clone_dtoh(&d_channels)?
            .iter()
            .map(|v| v.to_f64())
            .collect();
        let ([mut x_tilde, v_tilde, x_start], history) = input_channels_backward(d_channels);
        if let Some(d_x) = d_x {
            for (x, d) in x_tilde
                .iter_mut()
                .zip(triples(&ops.stream.clone_dtoh(&d_x)?))
            {
                for a in 0..3 {
                    x[a] += d[a];
                }
            }
        }
        Ok(ResidualGrads {
            parameters: ops
                .stream
                .clone_dtoh(&flat)?
                .iter()
                .map(|v| v.to_f64())
                .collect(),
            x_tilde,
            v_tilde,
            x_start,
            history,
        })
    }

    /// The launches on `device`'s stream: each call has a stream of its
    /// own, so callers on several host threads (MPPI's samples) do not
    /// wait for each other's copies.
    fn ops<'a>(&'a self, device: &'a CudaDevice) -> Ops<'a> {
        Ops {
            stream: device.stream(),
            functions: &self.functions,
        }
    }

    fn offset(&self, name: &str) -> Result<(Vec<usize>, usize), CudaError> {
        self.network
            .tensor(name)
            .map(|(shape, range)| (shape, range.start))
            .ok_or_else(|| CudaError::Unsupported(format!("the network has no tensor `{name}`")))
    }

    fn layer(&self, name: &str) -> Result<Layer, CudaError> {
        let (shape, weight) = self.offset(&format!("{name}.weight"))?;
        let (_, bias) = self.offset(&format!("{name}.bias"))?;
        Ok(Layer {
            weight,
            bias,
            inputs: shape[1],
            outputs: shape[0],
        })
    }

    fn norm(&self, name: &str) -> Result<Norm, CudaError> {
        Ok(Norm {
            scale: self.offset(&format!("{name}.norm.weight"))?.1,
            shift: self.offset(&format!("{name}.norm.bias"))?.1,
        })
    }

    fn forward(
        &self,
        ops: &Ops<'_>,
        inputs: &FrameInputs,
    ) -> Result<(CudaSlice<T>, Tape<T>), CudaError> {
        let n = inputs.particle_count();
        let channels: Vec<T> = input_channels(inputs).into_iter().map(T::lit).collect();
        let channels = ops.stream.clone_htod(&channels)?;
        let x_tilde = ops.stream.clone_htod(&flatten::<T>(&inputs.x_tilde))?;
        let w = &self.weights;
        let (dv, body) = match self.network.spec().kind {
            ResidualKind::Pgnd => {
                let (dv, tape) = self.grid_forward(ops, inputs, &x_tilde, &channels)?;
                (dv, Body::Pgnd(Box::new(tape)))
            }
            ResidualKind::Mlp | ResidualKind::None => {
                // `Residual::new` refuses `None`.
                let mut h1 =
                    ops.dense(w, self.layer("mlp1")?, &[(&channels, CHANNELS)], n, None)?;
                ops.relu(&mut h1)?;
                let h = self.layer("mlp2")?.outputs;
                let mut h2 = ops.dense(w, self.layer("mlp2")?, &[(&h1, h)], n, None)?;
                ops.relu(&mut h2)?;
                let mut h3 = ops.dense(
                    w,
                    self.layer("mlp3")?,
                    &[(&h2, h), (&channels, CHANNELS)],
                    n,
                    None,
                )?;
                ops.relu(&mut h3)?;
                let raw = ops.dense(w, self.layer("mlp4")?, &[(&h3, h)], n, None)?;
                let dv = ops.bound(&raw, n, self.network.spec().alpha)?;
                let tape = MlpTape {
                    hidden: [h1, h2, h3],
                    raw,
                };
                (dv, Body::Mlp(Box::new(tape)))
            }
        };
        Ok((
            dv,
            Tape {
                x_tilde,
                channels,
                body,
            },
        ))
    }

    fn grid_forward(
        &self,
        ops: &Ops<'_>,
        inputs: &FrameInputs,
        x_tilde: &CudaSlice<T>,
        channels: &CudaSlice<T>,
    ) -> Result<(CudaSlice<T>, GridTape<T>), CudaError> {
        let spec = self.network.spec();
        let w = &self.weights;
        let n = inputs.particle_count();
        let [e1, e2, e3] = spec.size.encoder;
        let h = spec.size.decoder;
        let groups = spec.size.groups;
        let z1 = ops.dense(w, self.layer("enc1")?, &[(channels, CHANNELS)], n, None)?;
        let (mut h1, norm1) = ops.norm_forward(w, self.norm("enc1")?, &z1, n, e1, groups)?;
        ops.relu(&mut h1)?;
        let z2 = ops.dense(w, self.layer("enc2")?, &[(&h1, e1)], n, None)?;
        let (mut h2, norm2) = ops.norm_forward(w, self.norm("enc2")?, &z2, n, e2, groups)?;
        ops.relu(&mut h2)?;
        // [h, max-pool(h)]·Wᵀ + b: the pooled half folds into the bias.
        let (pooled, pooled_at) = ops.column_max(&h2, n, e2)?;
        let enc3 = self.layer("enc3")?;
        let bias = ops.pooled_bias(w, enc3, &pooled, e2)?;
        let feature = ops.dense(w, enc3, &[(&h2, e2)], n, Some(&bias))?;

        let stencil = ops.stencil(inputs, spec.grid_origin, spec.grid_dx)?;
        let nodes = stencil.nodes;
        let spline_weights = ops.spline_weights(x_tilde, &stencil, n)?;
        let (node_feature, weight_sums) =
            ops.node_means(&feature, e3, &spline_weights, &stencil, n)?;
        let encoding = ops.node_encoding(&stencil, spec.grid_dx / spec.domain_size)?;
        let node_in = [(&node_feature, e3), (&encoding, NODE_ENCODING)];
        let mut d1 = ops.dense(w, self.layer("dec1")?, &node_in, nodes, None)?;
        ops.relu(&mut d1)?;
        let mut d2 = ops.dense(w, self.layer("dec2")?, &[(&d1, h)], nodes, None)?;
        ops.relu(&mut d2)?;
        let mut d3 = ops.dense(
            w,
            self.layer("dec3")?,
            &[(&d2, h), node_in[0], node_in[1]],
            nodes,
            None,
        )?;
        ops.relu(&mut d3)?;
        let raw = ops.dense(w, self.layer("dec4")?, &[(&d3, h)], nodes, None)?;
        let node_velocity = ops.bound(&raw, nodes, spec.alpha)?;
        let dv = ops.to_particles(&node_velocity, 3, &spline_weights, &stencil, n)?;
        Ok((
            dv,
            GridTape {
                encoded: [h1, h2],
                norms: [norm1, norm2],
                pooled,
                pooled_at,
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
        ))
    }

    /// ∂L/∂channels and, for PNPGD, ∂L/∂x̃ through the spline weights; the
    /// weights' gradient is added to `flat`.
    fn backward(
        &self,
        ops: &Ops<'_>,
        tape: &Tape<T>,
        grad: &CudaSlice<T>,
        n: usize,
        flat: &mut CudaSlice<T>,
    ) -> Result<(CudaSlice<T>, Option<CudaSlice<T>>), CudaError> {
        let w = &self.weights;
        let alpha = self.network.spec().alpha;
        match &tape.body {
            Body::Mlp(tape_mlp) => {
                let MlpTape { hidden, raw } = tape_mlp.as_ref();
                let [h1, h2, h3] = hidden;
                let h = self.layer("mlp2")?.outputs;
                let d_raw = ops.bound_backward(raw, grad, n, alpha)?;
                let mlp4 = self.layer("mlp4")?;
                ops.dense_parameter_grads(mlp4, &[(h3, h)], &d_raw, n, flat)?;
                let mut d3 = ops.dense_input_grad(w, mlp4, 0, h, &d_raw, n)?;
                ops.relu_backward(h3, &mut d3)?;
                let mlp3 = self.layer("mlp3")?;
                ops.dense_parameter_grads(
                    mlp3,
                    &[(h2, h), (&tape.channels, CHANNELS)],
                    &d3,
                    n,
                    flat,
                )?;
                let mut d2 = ops.dense_input_grad(w, mlp3, 0, h, &d3, n)?;
                let mut d_channels = ops.dense_input_grad(w, mlp3, h, CHANNELS, &d3, n)?;
                ops.relu_backward(h2, &mut d2)?;
                let mlp2 = self.layer("mlp2")?;
                ops.dense_parameter_grads(mlp2, &[(h1, h)], &d2, n, flat)?;
                let mut d1 = ops.dense_input_grad(w, mlp2, 0, h, &d2, n)?;
                ops.relu_backward(h1, &mut d1)?;
                let mlp1 = self.layer("mlp1")?;
                ops.dense_parameter_grads(mlp1, &[(&tape.channels, CHANNELS)], &d1, n, flat)?;
                ops.dense_input_grad_into(w, mlp1, 0, CHANNELS, &d1, n, &mut d_channels, true)?;
                Ok((d_channels, None))
            }
            Body::Pgnd(g) => {
                let (d_channels, d_x) = self.grid_backward(ops, g, tape, grad, n, flat)?;
                Ok((d_channels, Some(d_x)))
            }
        }
    }

    fn grid_backward(
        &self,
        ops: &Ops<'_>,
        g: &GridTape<T>,
        tape: &Tape<T>,
        grad: &CudaSlice<T>,
        n: usize,
        flat: &mut CudaSlice<T>,
    ) -> Result<(CudaSlice<T>, CudaSlice<T>), CudaError> {
        let spec = self.network.spec();
        let w = &self.weights;
        let [e1, e2, e3] = spec.size.encoder;
        let h = spec.size.decoder;
        let groups = spec.size.groups;
        let nodes = g.stencil.nodes;
        let (d_node_velocity, mut d_spline_weights) =
            ops.to_particles_backward(&g.node_velocity, 3, &g.spline_weights, &g.stencil, grad, n)?;
        let d_raw = ops.bound_backward(&g.raw, &d_node_velocity, nodes, spec.alpha)?;
        let [d1, d2, d3] = &g.decoded;
        let node_in = [(&g.node_feature, e3), (&g.encoding, NODE_ENCODING)];

        let dec4 = self.layer("dec4")?;
        ops.dense_parameter_grads(dec4, &[(d3, h)], &d_raw, nodes, flat)?;
        let mut dd3 = ops.dense_input_grad(w, dec4, 0, h, &d_raw, nodes)?;
        ops.relu_backward(d3, &mut dd3)?;
        let dec3 = self.layer("dec3")?;
        ops.dense_parameter_grads(dec3, &[(d2, h), node_in[0], node_in[1]], &dd3, nodes, flat)?;
        let mut dd2 = ops.dense_input_grad(w, dec3, 0, h, &dd3, nodes)?;
        let mut d_node_feature = ops.dense_input_grad(w, dec3, h, e3, &dd3, nodes)?;
        ops.relu_backward(d2, &mut dd2)?;
        let dec2 = self.layer("dec2")?;
        ops.dense_parameter_grads(dec2, &[(d1, h)], &dd2, nodes, flat)?;
        let mut dd1 = ops.dense_input_grad(w, dec2, 0, h, &dd2, nodes)?;
        ops.relu_backward(d1, &mut dd1)?;
        let dec1 = self.layer("dec1")?;
        ops.dense_parameter_grads(dec1, &node_in, &dd1, nodes, flat)?;
        ops.dense_input_grad_into(w, dec1, 0, e3, &dd1, nodes, &mut d_node_feature, true)?;

        let d_feature = ops.node_means_backward(
            &g.feature,
            e3,
            &g.spline_weights,
            &g.stencil,
            &g.node_feature,
            &g.weight_sums,
            d_node_feature,
            n,
            &mut d_spline_weights,
        )?;
        let d_x = ops.spline_weights_backward(&tape.x_tilde, &g.stencil, n, &d_spline_weights)?;

        // enc3 with its pooled half folded into the bias.
        let [h1, h2] = &g.encoded;
        let enc3 = self.layer("enc3")?;
        ops.dense_parameter_grads(enc3, &[(h2, e2)], &d_feature, n, flat)?;
        let mut dh2 = ops.dense_input_grad(w, enc3, 0, e2, &d_feature, n)?;
        // enc3's bias gradient, just written (it has no other share), is
        // the pooled half's too.
        ops.pooled_backward(w, enc3, &g.pooled, &g.pooled_at, e2, flat, &mut dh2)?;
        ops.relu_backward(h2, &mut dh2)?;
        let dz2 = ops.norm_backward(
            w,
            self.norm("enc2")?,
            &g.norms[1],
            &dh2,
            n,
            e2,
            groups,
            flat,
        )?;
        let enc2 = self.layer("enc2")?;
        ops.dense_parameter_grads(enc2, &[(h1, e1)], &dz2, n, flat)?;
        let mut dh1 = ops.dense_input_grad(w, enc2, 0, e1, &dz2, n)?;
        ops.relu_backward(h1, &mut dh1)?;
        let dz1 = ops.norm_backward(
            w,
            self.norm("enc1")?,
            &g.norms[0],
            &dh1,
            n,
            e1,
            groups,
            flat,
        )?;
        let enc1 = self.layer("enc1")?;
        ops.dense_parameter_grads(enc1, &[(&tape.channels, CHANNELS)], &dz1, n, flat)?;
        let d_channels = ops.dense_input_grad(w, enc1, 0, CHANNELS, &dz1, n)?;
        Ok((d_channels, d_x))
    }
}

/// Rows of three as device scalars.
fn flatten<T: DeviceReal>(values: &[[f64; 3]]) -> Vec<T> {
    values.iter().flatten().map(|v| T::lit(*v)).collect()
}

/// Device scalars back into rows of three.
fn triples<T: DeviceReal>(values: &[T]) -> Vec<[f64; 3]> {
    values
        .chunks(3)
        .map(|r| [r[0].to_f64(), r[1].to_f64(), r[2].to_f64()])
        .collect()
}

/// Refuses particle counts whose stencil slots (27 a particle) the
/// kernels' int indices cannot number.
fn check_size(particles: usize) -> Result<(), CudaError> {
    if particles
        .checked_mul(STENCIL)
        .is_none_or(|slots| slots > i32::MAX as usize)
    {
        return Err(CudaError::Unsupported(format!(
            "{particles} particles: the GPU residual takes at most {}",
            i32::MAX as usize / STENCIL
        )));
    }
    Ok(())
}

fn count_i32(count: usize, what: &str) -> Result<i32, CudaError> {
    i32::try_from(count).map_err(|_| {
        CudaError::Unsupported(format!(
            "{count} {what} exceed the residual kernels' int indices"
        ))
    })
}

impl Ops<'_> {
    fn function(&self, name: &str) -> &CudaFunction {
        // Every name is one of RESIDUAL_ENTRY_POINTS or SCAN_ENTRY_POINTS,
        // all loaded by `CudaResidual::new`.
        &self.functions[name]
    }

    /// C (+)= A·B for an M × K operand A and a K × N operand B into the
    /// row-major C (row stride `ldc`). Long reductions over few output
    /// tiles (weight gradients) are split along K, the slices adding
    /// atomically: only when `accumulate`.
    #[allow(clippy::too_many_arguments)]
    fn gemm<T: DeviceReal>(
        &self,
        [m, n, k]: [usize; 3],
        a: Operand<'_, T>,
        b: Operand<'_, T>,
        c: &mut CudaViewMut<'_, T>,
        ldc: usize,
        accumulate: bool,
    ) -> Result<(), CudaError> {
        if m == 0 || n == 0 || k == 0 {
            return Ok(());
        }
        let tiles = m.div_ceil(GEMM_TILE) * n.div_ceil(GEMM_TILE);
        // About two blocks per multiprocessor of a large GPU, 256 values of K
        // or more per slice.
        let slices = if accumulate && tiles < 128 && k > 512 {
            (256 / tiles).clamp(1, k / 256)
        } else {
            1
        };
        let k_slice = k.div_ceil(slices).div_ceil(16) * 16;
        let slices = k.div_ceil(k_slice);
        let (m_i, n_i, k_i) = (
            count_i32(m, "rows")?,
            count_i32(n, "columns")?,
            count_i32(k, "terms")?,
        );
        let (ldc, accumulate_i, k_slice_i) = (ldc as i64, accumulate as i32, k_slice as i32);
        // M (rows, up to millions) on x, whose limit is 2³¹ − 1 blocks; N (a
        // layer's width) on y.
        let grid = (
            m.div_ceil(GEMM_TILE) as u32,
            n.div_ceil(GEMM_TILE) as u32,
            slices as u32,
        );
        launch!(
            self,
            "residual_gemm",
            blocks_of(grid, GEMM_THREADS),
            [
                &m_i,
                &n_i,
                &k_i,
                &a.data,
                &a.rows,
                &a.columns,
                &b.data,
                &b.rows,
                &b.columns,
                c,
                &ldc,
                &accumulate_i,
                &k_slice_i
            ]
        )?;
        Ok(())
    }

    /// y = [x₁ x₂ …]·Wᵀ + b (b replaced by `bias` when given) for inputs
    /// given as column blocks (buffer, width), `rows` rows each.
    fn dense<T: DeviceReal>(
        &self,
        weights: &CudaSlice<T>,
        layer: Layer,
        blocks: &[(&CudaSlice<T>, usize)],
        rows: usize,
        bias: Option<&CudaSlice<T>>,
    ) -> Result<CudaSlice<T>, CudaError> {
        let mut y = self.stream.alloc_zeros::<T>(rows * layer.outputs)?;
        let bias = match bias {
            Some(b) => b.slice(..),
            None => weights.slice(layer.bias..layer.bias + layer.outputs),
        };
        let (rows_i, width) = (rows as i64, layer.outputs as i32);
        launch!(
            self,
            "residual_fill_rows",
            launch_for(rows * layer.outputs),
            [&mut y, &bias, &rows_i, &width]
        )?;
        let mut column = 0;
        for (x, width) in blocks {
            let w = weights.slice(layer.weight + column..);
            self.gemm(
                [rows, layer.outputs, *width],
                row_major(x.slice(..), *width),
                transposed(w, layer.inputs),
                &mut y.slice_mut(..),
                layer.outputs,
                true,
            )?;
            column += width;
        }
        Ok(y)
    }

    /// ∂L/∂W and ∂L/∂b of a dense layer added to the flat gradient, for the
    /// blocks of its input (in column order) and `grad` = ∂L/∂y.
    fn dense_parameter_grads<T: DeviceReal>(
        &self,
        layer: Layer,
        blocks: &[(&CudaSlice<T>, usize)],
        grad: &CudaSlice<T>,
        rows: usize,
        flat: &mut CudaSlice<T>,
    ) -> Result<(), CudaError> {
        let mut column = 0;
        for (x, width) in blocks {
            self.gemm(
                [layer.outputs, *width, rows],
                transposed(grad.slice(..), layer.outputs),
                row_major(x.slice(..), *width),
                &mut flat.slice_mut(layer.weight + column..),
                layer.inputs,
                true,
            )?;
            column += width;
        }
        self.column_sums(
            grad,
            None,
            rows,
            layer.outputs,
            &mut flat.slice_mut(layer.bias..layer.bias + layer.outputs),
        )
    }

    /// ∂L/∂x of the input block at `column` (`width` wide) from `grad` =
    /// ∂L/∂y, in a new buffer.
    #[allow(clippy::too_many_arguments)]
    fn dense_input_grad<T: DeviceReal>(
        &self,
        weights: &CudaSlice<T>,
        layer: Layer,
        column: usize,
        width: usize,
        grad: &CudaSlice<T>,
        rows: usize,
    ) -> Result<CudaSlice<T>, CudaError> {
        let mut out = self.stream.alloc_zeros::<T>(rows * width)?;
        self.dense_input_grad_into(weights, layer, column, width, grad, rows, &mut out, false)?;
        Ok(out)
    }

    /// [`Self::dense_input_grad`] written into `out`, or added to it.
    #[allow(clippy::too_many_arguments)]
    fn dense_input_grad_into<T: DeviceReal>(
        &self,
        weights: &CudaSlice<T>,
        layer: Layer,
        column: usize,
        width: usize,
        grad: &CudaSlice<T>,
        rows: usize,
        out: &mut CudaSlice<T>,
        accumulate: bool,
    ) -> Result<(), CudaError> {
        self.gemm(
            [rows, width, layer.outputs],
            row_major(grad.slice(..), layer.outputs),
            row_major(weights.slice(layer.weight + column..), layer.inputs),
            &mut out.slice_mut(..),
            width,
            accumulate,
        )
    }

    fn relu<T: DeviceReal>(&self, y: &mut CudaSlice<T>) -> Result<(), CudaError> {
        let count = y.len();
        let count_i = count as i64;
        launch!(self, "residual_relu", launch_for(count), [y, &count_i])?;
        Ok(())
    }

    fn relu_backward<T: DeviceReal>(
        &self,
        out: &CudaSlice<T>,
        grad: &mut CudaSlice<T>,
    ) -> Result<(), CudaError> {
        let count = grad.len();
        let count_i = count as i64;
        launch!(
            self,
            "residual_relu_backward",
            launch_for(count),
            [out, grad, &count_i]
        )?;
        Ok(())
    }

    /// out[c] += Σ_r a[r, c] (· b[r, c]).
    fn column_sums<T: DeviceReal>(
        &self,
        a: &CudaSlice<T>,
        b: Option<&CudaSlice<T>>,
        rows: usize,
        width: usize,
        out: &mut CudaViewMut<'_, T>,
    ) -> Result<(), CudaError> {
        let has_b = b.is_some() as i32;
        // Never read without `b`; any buffer of the type.
        let b = b.unwrap_or(a);
        let (rows_i, width_i) = (rows as i64, width as i32);
        launch!(
            self,
            "residual_column_sums",
            launch_for(rows.div_ceil(REDUCE_ROWS) * width),
            [a, b, &has_b, &rows_i, &width_i, out]
        )?;
        Ok(())
    }

    /// Per-group sums (see residual_group_sums).
    #[allow(clippy::too_many_arguments)]
    fn group_sums<T: DeviceReal>(
        &self,
        a: &CudaSlice<T>,
        b: Option<&CudaSlice<T>>,
        centre: Option<&CudaSlice<f64>>,
        count: f64,
        rows: usize,
        width: usize,
        groups: usize,
    ) -> Result<CudaSlice<f64>, CudaError> {
        let mut sums = self.stream.alloc_zeros::<f64>(groups)?;
        let (has_b, has_centre) = (b.is_some() as i32, centre.is_some() as i32);
        let b = b.unwrap_or(a);
        let placeholder;
        let centre = match centre {
            Some(c) => c,
            None => {
                placeholder = self.stream.alloc_zeros::<f64>(1)?;
                &placeholder
            }
        };
        let (rows_i, width_i, groups_i) = (rows as i64, width as i32, groups as i32);
        launch!(
            self,
            "residual_group_sums",
            launch_for(rows.div_ceil(REDUCE_ROWS) * width),
            [
                a,
                b,
                &has_b,
                centre,
                &has_centre,
                &count,
                &rows_i,
                &width_i,
                &groups_i,
                &mut sums
            ]
        )?;
        Ok(sums)
    }

    /// GroupNorm of `x` (rows × width): (y, tape).
    fn norm_forward<T: DeviceReal>(
        &self,
        weights: &CudaSlice<T>,
        norm: Norm,
        x: &CudaSlice<T>,
        rows: usize,
        width: usize,
        groups: usize,
    ) -> Result<(CudaSlice<T>, NormTape<T>), CudaError> {
        let count = (rows * (width / groups)) as f64;
        let sums = self.group_sums(x, None, None, count, rows, width, groups)?;
        let square_sums = self.group_sums(x, None, Some(&sums), count, rows, width, groups)?;
        let mut normalised = self.stream.alloc_zeros::<T>(rows * width)?;
        let mut y = self.stream.alloc_zeros::<T>(rows * width)?;
        let scale = weights.slice(norm.scale..norm.scale + width);
        let shift = weights.slice(norm.shift..norm.shift + width);
        let (rows_i, width_i, groups_i) = (rows as i64, width as i32, groups as i32);
        launch!(
            self,
            "residual_norm_forward",
            launch_for(rows * width),
            [
                x,
                &rows_i,
                &width_i,
                &groups_i,
                &sums,
                &square_sums,
                &count,
                &scale,
                &shift,
                &mut normalised,
                &mut y
            ]
        )?;
        Ok((
            y,
            NormTape {
                normalised,
                square_sums,
            },
        ))
    }

    /// GroupNorm's ∂L/∂x from `grad` = ∂L/∂y; ∂scale and ∂shift are added
    /// to the flat gradient.
    #[allow(clippy::too_many_arguments)]
    fn norm_backward<T: DeviceReal>(
        &self,
        weights: &CudaSlice<T>,
        norm: Norm,
        tape: &NormTape<T>,
        grad: &CudaSlice<T>,
        rows: usize,
        width: usize,
        groups: usize,
        flat: &mut CudaSlice<T>,
    ) -> Result<CudaSlice<T>, CudaError> {
        let count = (rows * (width / groups)) as f64;
        self.column_sums(
            grad,
            Some(&tape.normalised),
            rows,
            width,
            &mut flat.slice_mut(norm.scale..norm.scale + width),
        )?;
        self.column_sums(
            grad,
            None,
            rows,
            width,
            &mut flat.slice_mut(norm.shift..norm.shift + width),
        )?;
        let mut d = self.stream.alloc_zeros::<T>(rows * width)?;
        let scale = weights.slice(norm.scale..norm.scale + width);
        let (rows_i, width_i, groups_i) = (rows as i64, width as i32, groups as i32);
        launch!(
            self,
            "residual_scale_columns",
            launch_for(rows * width),
            [grad, &scale, &rows_i, &width_i, &mut d]
        )?;
        let d_sums = self.group_sums(&d, None, None, count, rows, width, groups)?;
        let dn_sums =
            self.group_sums(&d, Some(&tape.normalised), None, count, rows, width, groups)?;
        launch!(
            self,
            "residual_norm_backward",
            launch_for(rows * width),
            [
                &mut d,
                &tape.normalised,
                &rows_i,
                &width_i,
                &groups_i,
                &tape.square_sums,
                &d_sums,
                &dn_sums,
                &count
            ]
        )?;
        Ok(d)
    }

    /// Each column's maximum and the first row holding it.
    fn column_max<T: DeviceReal>(
        &self,
        m: &CudaSlice<T>,
        rows: usize,
        width: usize,
    ) -> Result<(CudaSlice<T>, CudaSlice<i32>), CudaError> {
        let mut best = self.stream.alloc_zeros::<T>(width)?;
        let mut best_at = self.stream.alloc_zeros::<i32>(width)?;
        let (rows_i, width_i) = (rows as i64, width as i32);
        launch!(
            self,
            "residual_column_max",
            blocks_of((width as u32, 1, 1), GEMM_THREADS),
            [m, &rows_i, &width_i, &mut best, &mut best_at]
        )?;
        Ok((best, best_at))
    }

    /// The encoder's last bias with the pooled half of its input folded in.
    fn pooled_bias<T: DeviceReal>(
        &self,
        weights: &CudaSlice<T>,
        layer: Layer,
        pooled: &CudaSlice<T>,
        offset: usize,
    ) -> Result<CudaSlice<T>, CudaError> {
        let mut out = self.stream.alloc_zeros::<T>(layer.outputs)?;
        let w = weights.slice(layer.weight..layer.weight + layer.outputs * layer.inputs);
        let b = weights.slice(layer.bias..layer.bias + layer.outputs);
        let (outputs, inputs, offset_i) =
            (layer.outputs as i32, layer.inputs as i32, offset as i32);
        launch!(
            self,
            "residual_pooled_bias",
            launch_for(layer.outputs),
            [&w, &b, pooled, &outputs, &inputs, &offset_i, &mut out]
        )?;
        Ok(out)
    }

    /// The pooled half's adjoint (see residual_pooled_backward), after the
    /// layer's own gradients are in `flat`.
    #[allow(clippy::too_many_arguments)]
    fn pooled_backward<T: DeviceReal>(
        &self,
        weights: &CudaSlice<T>,
        layer: Layer,
        pooled: &CudaSlice<T>,
        pooled_at: &CudaSlice<i32>,
        offset: usize,
        flat: &mut CudaSlice<T>,
        d_rows: &mut CudaSlice<T>,
    ) -> Result<(), CudaError> {
        let w = weights.slice(layer.weight..layer.weight + layer.outputs * layer.inputs);
        // The bias gradient is read while the weight gradient is written:
        // a copy of the few bias values keeps the two borrows apart.
        let bias_grad = self
            .stream
            .clone_dtod(&flat.slice(layer.bias..layer.bias + layer.outputs))?;
        let mut weight_grad =
            flat.slice_mut(layer.weight..layer.weight + layer.outputs * layer.inputs);
        let (outputs, inputs, offset_i) =
            (layer.outputs as i32, layer.inputs as i32, offset as i32);
        launch!(
            self,
            "residual_pooled_backward",
            launch_for(layer.outputs * (layer.inputs - offset)),
            [
                &w,
                &bias_grad,
                pooled,
                pooled_at,
                &outputs,
                &inputs,
                &offset_i,
                &mut weight_grad,
                d_rows
            ]
        )?;
        Ok(())
    }

    /// The particles' stencils: base cells from the host's f64 positions
    /// (as the CPU network's), the nodes numbered on the device.
    fn stencil(
        &self,
        inputs: &FrameInputs,
        origin: [f64; 3],
        dx: f64,
    ) -> Result<DeviceStencil, CudaError> {
        let n = inputs.particle_count();
        let mut base = Vec::with_capacity(3 * n);
        let mut lo = [i64::MAX; 3];
        let mut hi = [i64::MIN; 3];
        for x in &inputs.x_tilde {
            for a in 0..3 {
                // `check_inputs` keeps every particle within 1e9 cells.
                let cell = ((x[a] - origin[a]) / dx - 0.5).floor() as i64;
                lo[a] = lo[a].min(cell);
                hi[a] = hi[a].max(cell + 2);
                base.push(cell as i32);
            }
        }
        let dims = [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize);
        let cells = dims
            .iter()
            .try_fold(1usize, |product, d| product.checked_mul(*d))
            .unwrap_or(usize::MAX);
        if cells > MAX_STENCIL_CELLS {
            return Err(CudaError::Unsupported(format!(
                "the particles' stencils span {}×{}×{} grid cells; the GPU residual numbers at most {MAX_STENCIL_CELLS}",
                dims[0], dims[1], dims[2]
            )));
        }
        let lo = lo.map(|c| c as i32);
        let dims = dims.map(|d| d as i32);
        let base = self.stream.clone_htod(&base)?;
        let n_i = n as i32;
        let mut used = self.stream.alloc_zeros::<u32>(cells)?;
        launch!(
            self,
            "residual_mark_nodes",
            launch_for(n * STENCIL),
            [
                &base, &n_i, &lo[0], &lo[1], &lo[2], &dims[0], &dims[1], &dims[2], &mut used
            ]
        )?;

        let mut scanned = self.stream.clone_dtod(&used)?;
        let chunks = cells.div_ceil(SCAN_CHUNK);
        let mut chunk_sums = self.stream.alloc_zeros::<u32>(chunks)?;
        let (cells_i, chunks_i) = (cells as i32, chunks as i32);
        let scan_block = |blocks: usize| blocks_of((blocks as u32, 1, 1), SCAN_THREADS);
        launch!(
            self,
            "scan_chunks",
            scan_block(chunks),
            [&mut scanned, &cells_i, &mut chunk_sums]
        )?;
        launch!(
            self,
            "scan_sums",
            scan_block(1),
            [&mut chunk_sums, &chunks_i]
        )?;

        let mut node_id = self.stream.alloc_zeros::<i32>(cells)?;
        let mut node_cell = self.stream.alloc_zeros::<i64>(cells.min(n * STENCIL))?;
        let mut count = self.stream.alloc_zeros::<i32>(1)?;
        let cells_l = cells as i64;
        launch!(
            self,
            "residual_number_nodes",
            launch_for(cells),
            [
                &used,
                &scanned,
                &chunk_sums,
                &cells_l,
                &mut node_id,
                &mut node_cell,
                &mut count
            ]
        )?;
        let nodes = self.stream.clone_dtoh(&count)?[0] as usize;

        let mut node_of = self.stream.alloc_zeros::<i32>(n * STENCIL)?;
        launch!(
            self,
            "residual_stencil_slots",
            launch_for(n * STENCIL),
            [
                &base,
                &n_i,
                &lo[0],
                &lo[1],
                &lo[2],
                &dims[0],
                &dims[1],
                &dims[2],
                &node_id,
                &mut node_of
            ]
        )?;
        Ok(DeviceStencil {
            origin,
            dx,
            base,
            node_of,
            node_cell,
            nodes,
            lo,
            dims,
        })
    }

    fn spline_weights<T: DeviceReal>(
        &self,
        x: &CudaSlice<T>,
        stencil: &DeviceStencil,
        n: usize,
    ) -> Result<CudaSlice<T>, CudaError> {
        let mut w = self.stream.alloc_zeros::<T>(n * STENCIL)?;
        let n_i = n as i32;
        let origin = stencil.origin.map(T::lit);
        let dx = T::lit(stencil.dx);
        launch!(
            self,
            "residual_spline_weights",
            launch_for(n),
            [
                x,
                &stencil.base,
                &n_i,
                &origin[0],
                &origin[1],
                &origin[2],
                &dx,
                &mut w
            ]
        )?;
        Ok(w)
    }

    fn spline_weights_backward<T: DeviceReal>(
        &self,
        x: &CudaSlice<T>,
        stencil: &DeviceStencil,
        n: usize,
        grad: &CudaSlice<T>,
    ) -> Result<CudaSlice<T>, CudaError> {
        let mut out = self.stream.alloc_zeros::<T>(3 * n)?;
        let n_i = n as i32;
        let origin = stencil.origin.map(T::lit);
        let dx = T::lit(stencil.dx);
        launch!(
            self,
            "residual_spline_weights_backward",
            launch_for(n),
            [
                x,
                &stencil.base,
                &n_i,
                &origin[0],
                &origin[1],
                &origin[2],
                &dx,
                grad,
                &mut out
            ]
        )?;
        Ok(out)
    }

    /// Each node's weighted mean of the particle rows reaching it, and the
    /// weight sums (network.rs: node_means).
    fn node_means<T: DeviceReal>(
        &self,
        features: &CudaSlice<T>,
        width: usize,
        w: &CudaSlice<T>,
        stencil: &DeviceStencil,
        n: usize,
    ) -> Result<(CudaSlice<T>, CudaSlice<T>), CudaError> {
        let nodes = stencil.nodes;
        let mut totals = self.stream.alloc_zeros::<T>(nodes * width)?;
        let mut sums = self.stream.alloc_zeros::<T>(nodes)?;
        let (width_i, n_i, nodes_i) = (width as i32, n as i32, nodes as i32);
        launch!(
            self,
            "residual_node_sums",
            launch_for(n * STENCIL * width),
            [
                features,
                &width_i,
                w,
                &stencil.node_of,
                &n_i,
                &mut totals,
                &mut sums
            ]
        )?;
        let floor = T::lit(MIN_NODE_WEIGHT);
        launch!(
            self,
            "residual_node_divide",
            launch_for(nodes * width),
            [&mut totals, &sums, &nodes_i, &width_i, &floor]
        )?;
        Ok((totals, sums))
    }

    /// The node means' adjoint: ∂L/∂features (returned) and ∂L/∂w (added
    /// to `d_w`) from ∂L/∂means (`d_means`, consumed).
    #[allow(clippy::too_many_arguments)]
    fn node_means_backward<T: DeviceReal>(
        &self,
        features: &CudaSlice<T>,
        width: usize,
        w: &CudaSlice<T>,
        stencil: &DeviceStencil,
        means: &CudaSlice<T>,
        sums: &CudaSlice<T>,
        mut d_means: CudaSlice<T>,
        n: usize,
        d_w: &mut CudaSlice<T>,
    ) -> Result<CudaSlice<T>, CudaError> {
        let nodes = stencil.nodes;
        let mut d_sum = self.stream.alloc_zeros::<T>(nodes)?;
        let (width_i, n_i, nodes_i) = (width as i32, n as i32, nodes as i32);
        let floor = T::lit(MIN_NODE_WEIGHT);
        launch!(
            self,
            "residual_node_means_backward_nodes",
            launch_for(nodes),
            [
                &mut d_means,
                means,
                sums,
                &nodes_i,
                &width_i,
                &floor,
                &mut d_sum
            ]
        )?;
        let d_features = self.to_particles(&d_means, width, w, stencil, n)?;
        launch!(
            self,
            "residual_node_means_backward_weights",
            launch_for(n * STENCIL),
            [
                features,
                &stencil.node_of,
                &d_means,
                &d_sum,
                &width_i,
                &n_i,
                d_w
            ]
        )?;
        Ok(d_features)
    }

    /// Fourier encoding of every node's position (nodes × NODE_ENCODING).
    fn node_encoding<T: DeviceReal>(
        &self,
        stencil: &DeviceStencil,
        cell_to_unit: f64,
    ) -> Result<CudaSlice<T>, CudaError> {
        let mut out = self
            .stream
            .alloc_zeros::<T>(stencil.nodes * NODE_ENCODING)?;
        let (nodes_i, bands) = (stencil.nodes as i32, FOURIER_BANDS as i32);
        launch!(
            self,
            "residual_node_encoding",
            launch_for(stencil.nodes),
            [
                &stencil.node_cell,
                &nodes_i,
                &stencil.lo[0],
                &stencil.lo[1],
                &stencil.lo[2],
                &stencil.dims[0],
                &stencil.dims[1],
                &stencil.dims[2],
                &cell_to_unit,
                &bands,
                &mut out
            ]
        )?;
        Ok(out)
    }

    fn to_particles<T: DeviceReal>(
        &self,
        node_values: &CudaSlice<T>,
        width: usize,
        w: &CudaSlice<T>,
        stencil: &DeviceStencil,
        n: usize,
    ) -> Result<CudaSlice<T>, CudaError> {
        let mut out = self.stream.alloc_zeros::<T>(n * width)?;
        let (width_i, n_i) = (width as i32, n as i32);
        launch!(
            self,
            "residual_to_particles",
            launch_for(n * width),
            [node_values, &width_i, w, &stencil.node_of, &n_i, &mut out]
        )?;
        Ok(out)
    }

    /// (∂L/∂node rows, ∂L/∂w) of `to_particles` from ∂L/∂out.
    fn to_particles_backward<T: DeviceReal>(
        &self,
        node_values: &CudaSlice<T>,
        width: usize,
        w: &CudaSlice<T>,
        stencil: &DeviceStencil,
        grad: &CudaSlice<T>,
        n: usize,
    ) -> Result<(CudaSlice<T>, CudaSlice<T>), CudaError> {
        let mut d_nodes = self.stream.alloc_zeros::<T>(stencil.nodes * width)?;
        let mut d_w = self.stream.alloc_zeros::<T>(n * STENCIL)?;
        let (width_i, n_i) = (width as i32, n as i32);
        launch!(
            self,
            "residual_to_particles_backward",
            launch_for(n * STENCIL),
            [
                node_values,
                &width_i,
                w,
                &stencil.node_of,
                grad,
                &n_i,
                &mut d_nodes,
                &mut d_w
            ]
        )?;
        Ok((d_nodes, d_w))
    }

    fn bound<T: DeviceReal>(
        &self,
        y: &CudaSlice<T>,
        rows: usize,
        alpha: f64,
    ) -> Result<CudaSlice<T>, CudaError> {
        let mut out = self.stream.alloc_zeros::<T>(3 * rows)?;
        let (rows_i, alpha, k) = (rows as i32, T::lit(alpha), T::lit(OUTPUT_SCALE));
        launch!(
            self,
            "residual_bound",
            launch_for(rows),
            [y, &rows_i, &alpha, &k, &mut out]
        )?;
        Ok(out)
    }

    fn bound_backward<T: DeviceReal>(
        &self,
        y: &CudaSlice<T>,
        grad: &CudaSlice<T>,
        rows: usize,
        alpha: f64,
    ) -> Result<CudaSlice<T>, CudaError> {
        let mut out = self.stream.alloc_zeros::<T>(3 * rows)?;
        let (rows_i, alpha, k) = (rows as i32, T::lit(alpha), T::lit(OUTPUT_SCALE));
        launch!(
            self,
            "residual_bound_backward",
            launch_for(rows),
            [y, grad, &rows_i, &alpha, &k, &mut out]
        )?;
        Ok(out)
    }
}
