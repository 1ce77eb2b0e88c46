// The neural residual's layers, backward twins of residual.cu's.

// grad ·= [out > 0] (ReLU's adjoint from its output).
extern "C" __global__ void residual_relu_backward(const real* __restrict__ out, real* __restrict__ grad, long long count) {
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= count) return;
    if (!(out[i] > (real)0)) grad[i] = (real)0;
}

// out[r, c] = grad[r, c]·scale[c] (GroupNorm's ∂L/∂x̂).
extern "C" __global__ void residual_scale_columns(
    const real* __restrict__ grad, const real* __restrict__ scale, long long rows, int width,
    real* __restrict__ out)
{
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= rows * width) return;
    out[i] = grad[i] * scale[i % width];
}

// GroupNorm's ∂L/∂x = σ⁻¹·(dx̂ − mean(dx̂) − x̂·mean(dx̂·x̂)) per group, in
// place over dx̂; `d_sums` and `dn_sums` are the group sums of dx̂ and of
// dx̂·x̂.
extern "C" __global__ void residual_norm_backward(
    real* __restrict__ d_normalised, const real* __restrict__ normalised,
    long long rows, int width, int groups, const double* __restrict__ square_sums,
    const double* __restrict__ d_sums, const double* __restrict__ dn_sums, double count)
{
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= rows * width) return;
    const int g = (int)(i % width) / (width / groups);
    const real mean_d = (real)(d_sums[g] / count);
    const real mean_dn = (real)(dn_sums[g] / count);
    d_normalised[i] = group_inverse_std(square_sums, g, count) * (d_normalised[i] - mean_d - normalised[i] * mean_dn);
}

// The pooled half of the encoder's last layer: ∂W[o, offset + c] +=
// ∂b[o]·pooled[c], and ∂L/∂pooled[c] = Σ_o W[o, offset + c]·∂b[o] added to
// the row that held the column's maximum (`d_rows`, rows × (inputs − offset)).
extern "C" __global__ void residual_pooled_backward(
    const real* __restrict__ weight, const real* __restrict__ bias_grad,
    const real* __restrict__ pooled, const int* __restrict__ pooled_at,
    int outputs, int inputs, int offset,
    real* __restrict__ weight_grad, real* __restrict__ d_rows)
{
    const int width = inputs - offset;
    int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= outputs * width) return;
    const int o = i / width, c = i % width;
    weight_grad[o * inputs + offset + c] += bias_grad[o] * pooled[c];
    if (o == 0) {
        real d_pooled = (real)0;
        for (int q = 0; q < outputs; ++q) d_pooled += weight[q * inputs + offset + c] * bias_grad[q];
        d_rows[(long long)pooled_at[c] * width + c] += d_pooled;
    }
}

// ∂L/∂x (particles × 3) of the stencil weights from ∂L/∂w (particles × 27).
extern "C" __global__ void residual_spline_weights_backward(
    const real* __restrict__ x, const int* __restrict__ base, int n,
    real o0, real o1, real o2, real dx, const real* __restrict__ grad, real* __restrict__ out)
{
    int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= n) return;
    real w[3][3], dw[3][3];
    residual_particle_splines(x, base, p, o0, o1, o2, dx, w, dw);
    const real inverse_dx = (real)1 / dx;
    real d[3] = {(real)0, (real)0, (real)0};
    int s = 0;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 3; ++k) {
                const real g = grad[(long long)p * RESIDUAL_STENCIL + s++];
                d[0] += g * dw[0][i] * w[1][j] * w[2][k] * inverse_dx;
                d[1] += g * w[0][i] * dw[1][j] * w[2][k] * inverse_dx;
                d[2] += g * w[0][i] * w[1][j] * dw[2][k] * inverse_dx;
            }
    for (int a = 0; a < 3; ++a) out[3 * p + a] = d[a];
}

// Node means' adjoint, node by node and in place: ∂L/∂(Σ w·f) = g/S, and
// ∂L/∂S = −Σ_c g_c·mean_c / S where S is above the floor (else 0). The
// features' adjoint, Σ_s w[p, s]·∂L/∂(Σ w·f)[node(p, s)], is
// residual_to_particles of it.
extern "C" __global__ void residual_node_means_backward_nodes(
    real* __restrict__ d_total, const real* __restrict__ means,
    const real* __restrict__ weight_sums, int nodes, int width, real floor,
    real* __restrict__ d_sum)
{
    int node = blockIdx.x * blockDim.x + threadIdx.x;
    if (node >= nodes) return;
    const real sum = weight_sums[node];
    const real divisor = max(sum, floor);
    real* g = d_total + (long long)node * width;
    const real* mean = means + (long long)node * width;
    real along = (real)0;
    for (int c = 0; c < width; ++c) along += g[c] * mean[c];
    d_sum[node] = sum > floor ? -along / divisor : (real)0;
    for (int c = 0; c < width; ++c) g[c] /= divisor;
}

// ∂L/∂w[p, s] += Σ_c f[p, c]·d_total[node, c] + ∂L/∂S[node] (one thread
// per slot).
extern "C" __global__ void residual_node_means_backward_weights(
    const real* __restrict__ features, const int* __restrict__ node_of,
    const real* __restrict__ d_total, const real* __restrict__ d_sum,
    int width, int n, real* __restrict__ d_w)
{
    long long slot = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (slot >= (long long)n * RESIDUAL_STENCIL) return;
    const long long p = slot / RESIDUAL_STENCIL;
    const int node = node_of[slot];
    const real* f = features + p * width;
    const real* dt = d_total + (long long)node * width;
    real along = (real)0;
    for (int c = 0; c < width; ++c) along += f[c] * dt[c];
    d_w[slot] += along + d_sum[node];
}

// The adjoint of residual_to_particles: ∂L/∂node rows added atomically
// (`d_nodes`, cleared first) and ∂L/∂w[p, s] = ⟨node row, grad[p]⟩
// (overwritten); one thread per slot.
extern "C" __global__ void residual_to_particles_backward(
    const real* __restrict__ node_values, int width, const real* __restrict__ w,
    const int* __restrict__ node_of, const real* __restrict__ grad, int n,
    real* __restrict__ d_nodes, real* __restrict__ d_w)
{
    long long slot = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (slot >= (long long)n * RESIDUAL_STENCIL) return;
    const long long p = slot / RESIDUAL_STENCIL;
    const long long node = node_of[slot];
    const real weight = w[slot];
    real along = (real)0;
    for (int c = 0; c < width; ++c) {
        const real g = grad[p * width + c];
        atomicAdd(d_nodes + node * width + c, weight * g);
        along += node_values[node * width + c] * g;
    }
    d_w[slot] = along;
}

// ∂L/∂y of the bound from ∂L/∂(bounded y), per 3-vector row.
extern "C" __global__ void residual_bound_backward(
    const real* __restrict__ y, const real* __restrict__ grad, int rows, real alpha, real k,
    real* __restrict__ out)
{
    int r = blockIdx.x * blockDim.x + threadIdx.x;
    if (r >= rows) return;
    real scaled[3];
    const real radius = residual_bound_radius(y + 3 * r, k, scaled);
    const real t = tanh(radius);
    const real q = t / radius;
    // q(r) = tanh r / r: q' = (1 − tanh² r)/r − tanh r / r².
    const real dq = ((real)1 - t * t) / radius - t / (radius * radius);
    const real* g = grad + 3 * r;
    const real along = scaled[0] * g[0] + scaled[1] * g[1] + scaled[2] * g[2];
    for (int a = 0; a < 3; ++a) out[3 * r + a] = k * alpha * (q * g[a] + dq / radius * along * scaled[a]);
}
