//! The network's layers, each forward kernel with its backward twin beside
//! it. Matrices are row-major `Vec`s, one row per particle or grid node.
//!
//! Work is split into fixed row ranges (never by thread count) and every
//! sum across rows adds the ranges' partial sums in range order, so a
//! result does not depend on how many threads ran it.

use ndarray::linalg::general_mat_mul;
use ndarray::{ArrayView2, ArrayViewMut2, s};
use rayon::prelude::*;

/// Rows per parallel task of a matrix product.
const ROWS_PER_TASK: usize = 128;
/// Rows per partial sum of a reduction over rows (weight gradients,
/// normalisation statistics).
const ROWS_PER_PARTIAL: usize = 512;

/// The element type the network runs in: f32 for rollouts and training,
/// f64 for the gradient checks.
pub trait Scalar:
    ndarray::LinalgScalar + num_traits::Float + Send + Sync + std::fmt::Debug + 'static
{
    fn lit(value: f64) -> Self;
    fn widen(self) -> f64;
    /// Runs `f` on this thread's pool of spare matrix buffers.
    fn with_pool<R>(f: impl FnOnce(&mut BufferPool<Self>) -> R) -> R;
}

thread_local! {
    static POOL_F32: std::cell::RefCell<BufferPool<f32>> = const { std::cell::RefCell::new(BufferPool::new()) };
    static POOL_F64: std::cell::RefCell<BufferPool<f64>> = const { std::cell::RefCell::new(BufferPool::new()) };
}

impl Scalar for f32 {
    fn lit(value: f64) -> Self {
        value as f32
    }
    fn widen(self) -> f64 {
        f64::from(self)
    }
    fn with_pool<R>(f: impl FnOnce(&mut BufferPool<Self>) -> R) -> R {
        POOL_F32.with(|pool| f(&mut pool.borrow_mut()))
    }
}

impl Scalar for f64 {
    fn lit(value: f64) -> Self {
        value
    }
    fn widen(self) -> f64 {
        self
    }
    fn with_pool<R>(f: impl FnOnce(&mut BufferPool<Self>) -> R) -> R {
        POOL_F64.with(|pool| f(&mut pool.borrow_mut()))
    }
}

/// Buffers of dropped matrices, kept for the next frame's matrices of the
/// same sizes. A frame allocates ~40 matrices of up to a few MB; fresh
/// ones each time cost a quarter of the network's time in page faults.
#[derive(Debug)]
pub struct BufferPool<T> {
    spare: Vec<Vec<T>>,
    bytes: usize,
}

/// Most bytes a thread's pool keeps.
const POOL_BYTES: usize = 128 << 20;
/// Buffers smaller than this go back to the allocator.
const POOLED_MIN_BYTES: usize = 64 << 10;

impl<T> BufferPool<T> {
    const fn new() -> Self {
        Self {
            spare: Vec::new(),
            bytes: 0,
        }
    }

    /// The smallest spare buffer holding `len` elements, emptied.
    fn take(&mut self, len: usize) -> Option<Vec<T>> {
        let best = (0..self.spare.len())
            .filter(|&i| self.spare[i].capacity() >= len)
            .min_by_key(|&i| self.spare[i].capacity())?;
        let mut buffer = self.spare.swap_remove(best);
        self.bytes -= buffer.capacity() * size_of::<T>();
        buffer.clear();
        Some(buffer)
    }

    fn give(&mut self, buffer: Vec<T>) {
        let bytes = buffer.capacity() * size_of::<T>();
        if bytes >= POOLED_MIN_BYTES && self.bytes + bytes <= POOL_BYTES {
            self.bytes += bytes;
            self.spare.push(buffer);
        }
    }
}

/// A row-major matrix of `rows × width`.
#[derive(Debug, PartialEq)]
pub struct Rows<T: Scalar> {
    pub data: Vec<T>,
    pub width: usize,
}

impl<T: Scalar> Drop for Rows<T> {
    fn drop(&mut self) {
        let buffer = std::mem::take(&mut self.data);
        T::with_pool(|pool| pool.give(buffer));
    }
}

impl<T: Scalar> Clone for Rows<T> {
    fn clone(&self) -> Self {
        let mut copy = Self::uninitialised(self.data.len(), self.width);
        copy.data.extend_from_slice(&self.data);
        copy
    }
}

impl<T: Scalar> Rows<T> {
    /// An empty matrix with room for `len` elements.
    fn uninitialised(len: usize, width: usize) -> Self {
        let data = T::with_pool(|pool| pool.take(len)).unwrap_or_else(|| Vec::with_capacity(len));
        Self { data, width }
    }

    pub fn zeros(rows: usize, width: usize) -> Self {
        let mut m = Self::uninitialised(rows * width, width);
        m.data.resize(rows * width, T::zero());
        m
    }

    /// A matrix holding the `len` `values` (row-major).
    pub fn from_values(values: impl IntoIterator<Item = T>, len: usize, width: usize) -> Self {
        let mut m = Self::uninitialised(len, width);
        m.data.extend(values);
        m
    }

    pub fn rows(&self) -> usize {
        self.data.len().checked_div(self.width).unwrap_or(0)
    }

    pub fn row(&self, r: usize) -> &[T] {
        &self.data[r * self.width..(r + 1) * self.width]
    }

    fn view(&self, first: usize, count: usize) -> ArrayView2<'_, T> {
        ArrayView2::from_shape(
            (count, self.width),
            &self.data[first * self.width..(first + count) * self.width],
        )
        .expect("a row range of a matrix is a matrix")
    }
}

fn matrix_mut<T>(data: &mut [T], width: usize) -> ArrayViewMut2<'_, T> {
    let rows = data.len() / width;
    ArrayViewMut2::from_shape((rows, width), data).expect("whole rows")
}

/// A weight matrix (outputs × inputs, PyTorch's `Linear` layout) and bias.
#[derive(Clone, Copy, Debug)]
pub struct Dense<'a, T> {
    pub weight: &'a [T],
    pub bias: &'a [T],
    pub inputs: usize,
    pub outputs: usize,
}

impl<'a, T: Scalar> Dense<'a, T> {
    fn weight_view(&self) -> ArrayView2<'a, T> {
        ArrayView2::from_shape((self.outputs, self.inputs), self.weight).expect("weight shape")
    }

    /// y = [x₁ x₂ …]·Wᵀ + b for inputs given as column blocks (the
    /// concatenation is never built); `bias` replaces b when given. The
    /// blocks may cover only W's first columns (the caller folds the rest,
    /// constant over rows, into `bias`).
    pub fn forward(&self, blocks: &[&Rows<T>], bias: Option<&[T]>) -> Rows<T> {
        let rows = blocks[0].rows();
        debug_assert!(blocks.iter().map(|b| b.width).sum::<usize>() <= self.inputs);
        let bias = bias.unwrap_or(self.bias);
        let mut y = Rows::zeros(rows, self.outputs);
        let weight = self.weight_view();
        y.data
            .par_chunks_mut(ROWS_PER_TASK * self.outputs)
            .enumerate()
            .for_each(|(task, chunk)| {
                let first = task * ROWS_PER_TASK;
                for row in chunk.chunks_mut(self.outputs) {
                    row.copy_from_slice(bias);
                }
                let count = chunk.len() / self.outputs;
                let mut out = matrix_mut(chunk, self.outputs);
                let mut column = 0;
                for block in blocks {
                    let w = weight.slice(s![.., column..column + block.width]);
                    general_mat_mul(
                        T::one(),
                        &block.view(first, count),
                        &w.t(),
                        T::one(),
                        &mut out,
                    );
                    column += block.width;
                }
            });
        y
    }

    /// The adjoints of [`Dense::forward`] for `grad` = ∂L/∂y: ∂L/∂W and
    /// ∂L/∂b (added to `weight_grad` and `bias_grad`), and ∂L/∂xᵢ for the
    /// blocks `wanted` marks.
    pub fn backward(
        &self,
        blocks: &[&Rows<T>],
        grad: &Rows<T>,
        wanted: &[bool],
        weight_grad: &mut [T],
        bias_grad: &mut [T],
    ) -> Vec<Option<Rows<T>>> {
        let rows = grad.rows();
        let weight = self.weight_view();
        let partials: Vec<(Vec<T>, Vec<T>)> = (0..rows.div_ceil(ROWS_PER_PARTIAL))
            .into_par_iter()
            .map(|part| {
                let first = part * ROWS_PER_PARTIAL;
                let count = ROWS_PER_PARTIAL.min(rows - first);
                let g = grad.view(first, count);
                let mut w = vec![T::zero(); self.outputs * self.inputs];
                let mut wv = matrix_mut(&mut w, self.inputs);
                let mut column = 0;
                for block in blocks {
                    let mut target = wv.slice_mut(s![.., column..column + block.width]);
                    general_mat_mul(
                        T::one(),
                        &g.t(),
                        &block.view(first, count),
                        T::zero(),
                        &mut target,
                    );
                    column += block.width;
                }
                let mut b = vec![T::zero(); self.outputs];
                for row in g.rows() {
                    for (acc, v) in b.iter_mut().zip(row) {
                        *acc = *acc + *v;
                    }
                }
                (w, b)
            })
            .collect();
        for (w, b) in &partials {
            add_into(weight_grad, w);
            add_into(bias_grad, b);
        }
        let mut column = 0;
        blocks
            .iter()
            .zip(wanted)
            .map(|(block, &want)| {
                let columns = column..column + block.width;
                column += block.width;
                want.then(|| {
                    let mut dx = Rows::zeros(rows, block.width);
                    let w = weight.slice(s![.., columns.clone()]);
                    dx.data
                        .par_chunks_mut(ROWS_PER_TASK * block.width)
                        .enumerate()
                        .for_each(|(task, chunk)| {
                            let count = chunk.len() / block.width;
                            let g = grad.view(task * ROWS_PER_TASK, count);
                            let mut out = matrix_mut(chunk, block.width);
                            general_mat_mul(T::one(), &g, &w, T::zero(), &mut out);
                        });
                    dx
                })
            })
            .collect()
    }
}

/// target += values, element by element.
pub(crate) fn add_into<T: Scalar>(target: &mut [T], values: &[T]) {
    for (t, v) in target.iter_mut().zip(values) {
        *t = *t + *v;
    }
}

/// Column sums of `m` (summed in fixed row ranges, in order).
pub fn column_sums<T: Scalar>(m: &Rows<T>) -> Vec<T> {
    let mut total = vec![T::zero(); m.width];
    for part in m.data.chunks(ROWS_PER_PARTIAL * m.width) {
        let mut sums = vec![T::zero(); m.width];
        for row in part.chunks(m.width) {
            add_into(&mut sums, row);
        }
        add_into(&mut total, &sums);
    }
    total
}

/// max(x, 0) in place.
pub fn relu<T: Scalar>(m: &mut Rows<T>) {
    m.data.par_iter_mut().for_each(|v| *v = v.max(T::zero()));
}

/// Backward of [`relu`] given its output: the gradient passes where the
/// output is positive.
pub fn relu_backward<T: Scalar>(output: &Rows<T>, grad: &mut Rows<T>) {
    grad.data
        .par_iter_mut()
        .zip(&output.data)
        .for_each(|(g, y)| {
            if *y <= T::zero() {
                *g = T::zero();
            }
        });
}

/// Per-point GroupNorm: the `rows × channels` matrix is one sample whose
/// channels fall into `groups` groups; each group is normalised with the
/// mean and (biased) variance over all its rows and channels, then scaled
/// and shifted per channel (PyTorch's `GroupNorm` on a (1, c, n) tensor).
#[derive(Clone, Copy, Debug)]
pub struct GroupNorm<'a, T> {
    pub scale: &'a [T],
    pub shift: &'a [T],
    pub groups: usize,
}

/// What [`GroupNorm::backward`] needs of the forward pass.
#[derive(Clone, Debug)]
pub struct NormTape<T: Scalar> {
    normalised: Rows<T>,
    inverse_std: Vec<T>,
}

const NORM_EPSILON: f64 = 1e-5;

impl<T: Scalar> GroupNorm<'_, T> {
    fn group_of(&self, channels: usize) -> impl Fn(usize) -> usize + use<T> {
        let per_group = channels / self.groups;
        move |c| c / per_group
    }

    /// Per-group sums of `f(value, channel)` over all rows, in f64.
    fn group_sums(&self, m: &Rows<T>, f: impl Fn(T, usize) -> f64 + Sync) -> Vec<f64> {
        let group = self.group_of(m.width);
        let partials: Vec<Vec<f64>> = m
            .data
            .par_chunks(ROWS_PER_PARTIAL * m.width)
            .map(|part| {
                let mut sums = vec![0.0; self.groups];
                for row in part.chunks(m.width) {
                    for (c, v) in row.iter().enumerate() {
                        sums[group(c)] += f(*v, c);
                    }
                }
                sums
            })
            .collect();
        let mut total = vec![0.0; self.groups];
        for p in &partials {
            for (t, v) in total.iter_mut().zip(p) {
                *t += v;
            }
        }
        total
    }

    pub fn forward(&self, x: &Rows<T>) -> (Rows<T>, NormTape<T>) {
        let count = (x.rows() * (x.width / self.groups)) as f64;
        let mean: Vec<f64> = self
            .group_sums(x, |v, _| v.widen())
            .iter()
            .map(|s| s / count)
            .collect();
        let group = self.group_of(x.width);
        let variance = self.group_sums(x, |v, c| (v.widen() - mean[group(c)]).powi(2));
        let inverse_std: Vec<T> = variance
            .iter()
            .map(|s| T::lit(1.0 / (s / count + NORM_EPSILON).sqrt()))
            .collect();
        let mean: Vec<T> = mean.into_iter().map(T::lit).collect();
        let mut normalised = x.clone();
        let mut y = x.clone();
        let width = x.width;
        normalised
            .data
            .par_chunks_mut(width)
            .zip(y.data.par_chunks_mut(width))
            .for_each(|(n, out)| {
                for c in 0..width {
                    let g = group(c);
                    n[c] = (n[c] - mean[g]) * inverse_std[g];
                    out[c] = n[c] * self.scale[c] + self.shift[c];
                }
            });
        (
            y,
            NormTape {
                normalised,
                inverse_std,
            },
        )
    }

    /// ∂L/∂x from ∂L/∂y; ∂L/∂scale and ∂L/∂shift are added to the slices.
    pub fn backward(
        &self,
        tape: &NormTape<T>,
        grad: &Rows<T>,
        scale_grad: &mut [T],
        shift_grad: &mut [T],
    ) -> Rows<T> {
        let width = grad.width;
        let group = self.group_of(width);
        let count = (grad.rows() * (width / self.groups)) as f64;
        let mut product = grad.clone();
        product
            .data
            .par_iter_mut()
            .zip(&tape.normalised.data)
            .for_each(|(g, n)| *g = *g * *n);
        add_into(scale_grad, &column_sums(&product));
        add_into(shift_grad, &column_sums(grad));
        // dx̂ = dy·scale; dx = σ⁻¹·(dx̂ − mean(dx̂) − x̂·mean(dx̂·x̂)) per group.
        let mut d_normalised = grad.clone();
        d_normalised.data.par_chunks_mut(width).for_each(|row| {
            for (c, v) in row.iter_mut().enumerate() {
                *v = *v * self.scale[c];
            }
        });
        let mean_d: Vec<T> = self
            .group_sums(&d_normalised, |v, _| v.widen())
            .iter()
            .map(|s| T::lit(s / count))
            .collect();
        let normalised = &tape.normalised;
        let mean_dn: Vec<T> = {
            let mut both = d_normalised.clone();
            both.data
                .par_iter_mut()
                .zip(&normalised.data)
                .for_each(|(d, n)| *d = *d * *n);
            self.group_sums(&both, |v, _| v.widen())
                .iter()
                .map(|s| T::lit(s / count))
                .collect()
        };
        d_normalised
            .data
            .par_chunks_mut(width)
            .zip(normalised.data.par_chunks(width))
            .for_each(|(d, n)| {
                for c in 0..width {
                    let g = group(c);
                    d[c] = tape.inverse_std[g] * (d[c] - mean_d[g] - n[c] * mean_dn[g]);
                }
            });
        d_normalised
    }
}

/// The largest value of each column and the first row holding it.
pub fn column_max<T: Scalar>(m: &Rows<T>) -> (Vec<T>, Vec<usize>) {
    let mut best = m.row(0).to_vec();
    let mut at = vec![0; m.width];
    for r in 1..m.rows() {
        for (c, v) in m.row(r).iter().enumerate() {
            if *v > best[c] {
                best[c] = *v;
                at[c] = r;
            }
        }
    }
    (best, at)
}

/// The bound of each 3-vector row y: α·tanh(|y'|)·y'/|y'| with y' = k·y,
/// a vector no longer than α.
#[derive(Clone, Copy, Debug)]
pub struct Bound {
    pub alpha: f64,
    pub scale: f64,
}

/// |y'|² is offset by this before the square root (a zero row stays finite).
const BOUND_EPSILON: f64 = 1e-12;

impl Bound {
    /// y' = k·y and |y'| (offset so that a zero row stays finite).
    fn scaled<T: Scalar>(&self, row: &[T]) -> ([T; 3], T) {
        let scaled = [0, 1, 2].map(|a| row[a] * T::lit(self.scale));
        let squared = scaled.iter().fold(T::zero(), |s, v| s + *v * *v);
        (scaled, (squared + T::lit(BOUND_EPSILON)).sqrt())
    }

    pub fn forward<T: Scalar>(&self, y: &Rows<T>) -> Rows<T> {
        let mut out = y.clone();
        out.data.par_chunks_mut(3).for_each(|row| {
            let (scaled, radius) = self.scaled(row);
            let factor = T::lit(self.alpha) * radius.tanh() / radius;
            for a in 0..3 {
                row[a] = factor * scaled[a];
            }
        });
        out
    }

    /// ∂L/∂y from ∂L/∂(bounded y).
    pub fn backward<T: Scalar>(&self, y: &Rows<T>, grad: &Rows<T>) -> Rows<T> {
        let mut out = grad.clone();
        out.data
            .par_chunks_mut(3)
            .zip(y.data.par_chunks(3))
            .for_each(|(g, row)| {
                let k = T::lit(self.scale);
                let (scaled, radius) = self.scaled(row);
                let t = radius.tanh();
                let q = t / radius;
                // q(r) = tanh r / r: q' = (1 − tanh² r)/r − tanh r / r².
                let dq = (T::one() - t * t) / radius - t / (radius * radius);
                let along = scaled[0] * g[0] + scaled[1] * g[1] + scaled[2] * g[2];
                let alpha = T::lit(self.alpha);
                for a in 0..3 {
                    g[a] = k * alpha * (q * g[a] + dq / radius * along * scaled[a]);
                }
            });
        out
    }
}
