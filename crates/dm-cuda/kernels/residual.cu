// The neural residual's layers (dm-residual: kernels.rs, transfer.rs,
// network.rs), forward passes. Matrices are row-major `rows × width`.
// Node sums use atomic adds, so f32 results agree with the CPU's to
// round-off, not bitwise.

#define GEMM_TILE 64
#define GEMM_DEPTH 16
#define GEMM_THREADS 256
#define REDUCE_ROWS 256
#define RESIDUAL_STENCIL 27

// tile[kk][i] = X[(first + i)·along + (k0 + kk)·across] for a GEMM_DEPTH ×
// GEMM_TILE tile of the operand X (zero outside `count` and `k_end`);
// neighbouring threads read neighbouring addresses along whichever index
// has the unit stride.
__device__ __forceinline__ void gemm_load_tile(
    real tile[GEMM_DEPTH][GEMM_TILE + 1], const real* __restrict__ X, long long along,
    long long across, int first, int count, int k0, int k_end)
{
    for (int l = threadIdx.x; l < GEMM_TILE * GEMM_DEPTH; l += GEMM_THREADS) {
        int kk, ii;
        if (across == 1) { kk = l % GEMM_DEPTH; ii = l / GEMM_DEPTH; }
        else { ii = l % GEMM_TILE; kk = l / GEMM_TILE; }
        const int i = first + ii, k = k0 + kk;
        tile[kk][ii] = (i < count && k < k_end) ? X[i * along + k * across] : (real)0;
    }
}

// C[m, n] = (C[m, n] if `accumulate`) + Σ_k A(m, k)·B(k, n), with A(m, k)
// at A[m·a_m + k·a_k] and B(k, n) at B[k·b_k + n·b_n]: any transpose of a
// row-major operand, and a column block of one, without copying. Blocks
// (x: M tiles, y: N tiles, z: slices of `k_slice` along K); with more than
// one slice the slices add atomically into C, which then accumulates.
extern "C" __global__ void residual_gemm(
    int M, int N, int K,
    const real* __restrict__ A, long long a_m, long long a_k,
    const real* __restrict__ B, long long b_k, long long b_n,
    real* __restrict__ C, long long ldc, int accumulate, int k_slice)
{
    __shared__ real As[GEMM_DEPTH][GEMM_TILE + 1];
    __shared__ real Bs[GEMM_DEPTH][GEMM_TILE + 1];
    const int tx = threadIdx.x % 16, ty = threadIdx.x / 16;
    const int m0 = blockIdx.x * GEMM_TILE, n0 = blockIdx.y * GEMM_TILE;
    const int k_begin = blockIdx.z * k_slice;
    const int k_end = min(K, k_begin + k_slice);
    real acc[4][4];
    for (int i = 0; i < 4; ++i)
        for (int j = 0; j < 4; ++j) acc[i][j] = (real)0;
    for (int k0 = k_begin; k0 < k_end; k0 += GEMM_DEPTH) {
        gemm_load_tile(As, A, a_m, a_k, m0, M, k0, k_end);
        gemm_load_tile(Bs, B, b_n, b_k, n0, N, k0, k_end);
        __syncthreads();
        for (int kk = 0; kk < GEMM_DEPTH; ++kk) {
            real a[4], b[4];
            for (int i = 0; i < 4; ++i) a[i] = As[kk][ty + 16 * i];
            for (int j = 0; j < 4; ++j) b[j] = Bs[kk][tx + 16 * j];
            for (int i = 0; i < 4; ++i)
                for (int j = 0; j < 4; ++j) acc[i][j] += a[i] * b[j];
        }
        __syncthreads();
    }
    for (int i = 0; i < 4; ++i) {
        const int m = m0 + ty + 16 * i;
        if (m >= M) continue;
        for (int j = 0; j < 4; ++j) {
            const int n = n0 + tx + 16 * j;
            if (n >= N) continue;
            real* out = C + m * ldc + n;
            if (gridDim.z > 1) atomicAdd(out, acc[i][j]);
            else *out = accumulate ? *out + acc[i][j] : acc[i][j];
        }
    }
}

// Every row of `y` (rows × width) set to `row`.
extern "C" __global__ void residual_fill_rows(real* __restrict__ y, const real* __restrict__ row, long long rows, int width) {
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= rows * width) return;
    y[i] = row[i % width];
}

extern "C" __global__ void residual_relu(real* __restrict__ y, long long count) {
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= count) return;
    y[i] = max(y[i], (real)0);
}

// out[c] += Σ_r a[r, c] (· b[r, c] when `b` is given): REDUCE_ROWS rows
// per thread, the threads' sums added atomically.
extern "C" __global__ void residual_column_sums(
    const real* __restrict__ a, const real* __restrict__ b, int has_b,
    long long rows, int width, real* __restrict__ out)
{
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    long long chunks = (rows + REDUCE_ROWS - 1) / REDUCE_ROWS;
    if (i >= chunks * width) return;
    const int c = (int)(i % width);
    const long long first = (i / width) * REDUCE_ROWS;
    const long long last = min(rows, first + REDUCE_ROWS);
    real sum = (real)0;
    for (long long r = first; r < last; ++r) {
        real v = a[r * width + c];
        sum += has_b ? v * b[r * width + c] : v;
    }
    atomicAdd(out + c, sum);
}

// Per-group sums in double over all rows of a group's channels:
// Σ a (· b when given), or Σ (a − sums[g]/count)² when `centre` is given
// (the variance's numerator from the mean's sums).
extern "C" __global__ void residual_group_sums(
    const real* __restrict__ a, const real* __restrict__ b, int has_b,
    const double* __restrict__ centre, int has_centre, double count,
    long long rows, int width, int groups, double* __restrict__ sums)
{
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    long long chunks = (rows + REDUCE_ROWS - 1) / REDUCE_ROWS;
    if (i >= chunks * width) return;
    const int c = (int)(i % width);
    const int g = c / (width / groups);
    const long long first = (i / width) * REDUCE_ROWS;
    const long long last = min(rows, first + REDUCE_ROWS);
    const double mean = has_centre ? centre[g] / count : 0.0;
    double sum = 0.0;
    for (long long r = first; r < last; ++r) {
        double v = (double)a[r * width + c];
        if (has_b) v *= (double)b[r * width + c];
        if (has_centre) v = (v - mean) * (v - mean);
        sum += v;
    }
    atomicAdd(sums + g, sum);
}

// GroupNorm's 1/σ of group g from the sums of values and of squared
// deviations (kernels.rs: NORM_EPSILON).
__device__ __forceinline__ real group_inverse_std(const double* square_sums, int g, double count) {
    return (real)(1.0 / sqrt(square_sums[g] / count + 1e-5));
}

// GroupNorm: x̂ = (x − mean)/σ per group, y = x̂·scale + shift per channel.
extern "C" __global__ void residual_norm_forward(
    const real* __restrict__ x, long long rows, int width, int groups,
    const double* __restrict__ sums, const double* __restrict__ square_sums, double count,
    const real* __restrict__ scale, const real* __restrict__ shift,
    real* __restrict__ normalised, real* __restrict__ y)
{
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= rows * width) return;
    const int c = (int)(i % width);
    const int g = c / (width / groups);
    const real mean = (real)(sums[g] / count);
    const real n = (x[i] - mean) * group_inverse_std(square_sums, g, count);
    normalised[i] = n;
    y[i] = n * scale[c] + shift[c];
}

// The largest value of each column and the first row holding it (one
// block per column).
extern "C" __global__ void residual_column_max(
    const real* __restrict__ m, long long rows, int width,
    real* __restrict__ best, int* __restrict__ best_at)
{
    __shared__ real values[GEMM_THREADS];
    __shared__ long long at[GEMM_THREADS];
    const int c = blockIdx.x;
    real v = m[c];
    long long r_best = 0;
    for (long long r = threadIdx.x; r < rows; r += blockDim.x) {
        real x = m[r * width + c];
        if (x > v || (x == v && r < r_best)) { v = x; r_best = r; }
    }
    values[threadIdx.x] = v;
    at[threadIdx.x] = r_best;
    __syncthreads();
    for (int stride = blockDim.x / 2; stride > 0; stride >>= 1) {
        if (threadIdx.x < stride) {
            real o = values[threadIdx.x + stride];
            long long o_at = at[threadIdx.x + stride];
            if (o > values[threadIdx.x] || (o == values[threadIdx.x] && o_at < at[threadIdx.x])) {
                values[threadIdx.x] = o;
                at[threadIdx.x] = o_at;
            }
        }
        __syncthreads();
    }
    if (threadIdx.x == 0) {
        best[c] = values[0];
        best_at[c] = (int)at[0];
    }
}

// out[o] = bias[o] + Σ_c W[o, offset + c]·pooled[c]: the max-pooled half of
// the encoder's last layer is the same for every particle and folds into
// its bias.
extern "C" __global__ void residual_pooled_bias(
    const real* __restrict__ weight, const real* __restrict__ bias,
    const real* __restrict__ pooled, int outputs, int inputs, int offset,
    real* __restrict__ out)
{
    int o = blockIdx.x * blockDim.x + threadIdx.x;
    if (o >= outputs) return;
    real acc = bias[o];
    for (int c = 0; c < inputs - offset; ++c) acc += weight[o * inputs + offset + c] * pooled[c];
    out[o] = acc;
}

// Marks every node of each particle's 3×3×3 stencil in the dense box
// (`lo`, `dims`) of cells; `base` is each particle's lowest stencil cell.
extern "C" __global__ void residual_mark_nodes(
    const int* __restrict__ base, int n,
    int lo0, int lo1, int lo2, int d0, int d1, int d2, unsigned* __restrict__ used)
{
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= (long long)n * RESIDUAL_STENCIL) return;
    const int p = (int)(i / RESIDUAL_STENCIL), s = (int)(i % RESIDUAL_STENCIL);
    const int c0 = base[3 * p] + s / 9 - lo0;
    const int c1 = base[3 * p + 1] + (s / 3) % 3 - lo1;
    const int c2 = base[3 * p + 2] + s % 3 - lo2;
    used[((long long)c0 * d1 + c1) * d2 + c2] = 1u;
}

// Numbers the used cells in cell order (from the scan of `used`): each
// used cell's node id, and each node's cell; the last thread writes the
// node count.
extern "C" __global__ void residual_number_nodes(
    const unsigned* __restrict__ used, const unsigned* __restrict__ scanned,
    const unsigned* __restrict__ chunk_sums, long long cells,
    int* __restrict__ node_id, long long* __restrict__ node_cell, int* __restrict__ count)
{
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= cells) return;
    const int id = (int)(scanned[i] + chunk_sums[i / SCAN_CHUNK]);
    if (used[i]) {
        node_id[i] = id;
        node_cell[id] = i;
    }
    if (i == cells - 1) *count = id + (int)used[i];
}

// The node id of every stencil slot p·27 + s.
extern "C" __global__ void residual_stencil_slots(
    const int* __restrict__ base, int n,
    int lo0, int lo1, int lo2, int d0, int d1, int d2,
    const int* __restrict__ node_id, int* __restrict__ node_of)
{
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= (long long)n * RESIDUAL_STENCIL) return;
    const int p = (int)(i / RESIDUAL_STENCIL), s = (int)(i % RESIDUAL_STENCIL);
    const int c0 = base[3 * p] + s / 9 - lo0;
    const int c1 = base[3 * p + 1] + (s / 3) % 3 - lo1;
    const int c2 = base[3 * p + 2] + s % 3 - lo2;
    node_of[i] = node_id[((long long)c0 * d1 + c1) * d2 + c2];
}

// Fourier encoding of each node's position in the domain: q = cell·dx/L,
// then sin and cos of 2^b·π·q for b < bands (network.rs: node_encoding).
extern "C" __global__ void residual_node_encoding(
    const long long* __restrict__ node_cell, int nodes,
    int lo0, int lo1, int lo2, int d0, int d1, int d2,
    double cell_to_unit, int bands, real* __restrict__ out)
{
    int node = blockIdx.x * blockDim.x + threadIdx.x;
    if (node >= nodes) return;
    const long long cell = node_cell[node];
    const long long local[3] = {cell / ((long long)d1 * d2), (cell / d2) % d1, cell % d2};
    const int lo[3] = {lo0, lo1, lo2};
    const int width = 3 + 6 * bands;
    real* row = out + (long long)node * width;
    double q[3];
    for (int a = 0; a < 3; ++a) {
        q[a] = (double)(local[a] + lo[a]) * cell_to_unit;
        row[a] = (real)q[a];
    }
    for (int b = 0; b < bands; ++b) {
        const double frequency = (double)(1 << b) * 3.14159265358979323846;
        for (int a = 0; a < 3; ++a) {
            row[3 + 6 * b + a] = (real)sin(frequency * q[a]);
            row[6 + 6 * b + a] = (real)cos(frequency * q[a]);
        }
    }
}

// Quadratic B-spline weights of the three offsets at the fractional grid
// coordinate f (relative to the base cell), and their derivatives.
__device__ __forceinline__ void residual_spline(real f, real* w, real* dw) {
    const real a = (real)1.5 - f, b = f - (real)1, c = f - (real)0.5;
    w[0] = (real)0.5 * a * a;
    w[1] = (real)0.75 - b * b;
    w[2] = (real)0.5 * c * c;
    dw[0] = -a;
    dw[1] = -(b + b);
    dw[2] = c;
}

__device__ __forceinline__ void residual_particle_splines(
    const real* x, const int* base, int p, real o0, real o1, real o2, real dx,
    real w[3][3], real dw[3][3])
{
    const real origin[3] = {o0, o1, o2};
    for (int a = 0; a < 3; ++a) {
        const real f = (x[3 * p + a] - origin[a]) / dx - (real)base[3 * p + a];
        residual_spline(f, w[a], dw[a]);
    }
}

// The 27 stencil weights of each particle (particles × 27).
extern "C" __global__ void residual_spline_weights(
    const real* __restrict__ x, const int* __restrict__ base, int n,
    real o0, real o1, real o2, real dx, real* __restrict__ w)
{
    int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= n) return;
    real ws[3][3], dws[3][3];
    residual_particle_splines(x, base, p, o0, o1, o2, dx, ws, dws);
    int s = 0;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            for (int k = 0; k < 3; ++k) w[(long long)p * RESIDUAL_STENCIL + s++] = ws[0][i] * ws[1][j] * ws[2][k];
}

// Each node's Σ w·f over the particle rows reaching it (`totals`, cleared
// first) and Σ w (`weight_sums`, cleared first); one thread per slot and
// channel.
extern "C" __global__ void residual_node_sums(
    const real* __restrict__ features, int width, const real* __restrict__ w,
    const int* __restrict__ node_of, int n,
    real* __restrict__ totals, real* __restrict__ weight_sums)
{
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= (long long)n * RESIDUAL_STENCIL * width) return;
    const long long slot = i / width;
    const int c = (int)(i % width);
    const long long p = slot / RESIDUAL_STENCIL;
    const int node = node_of[slot];
    const real weight = w[slot];
    atomicAdd(totals + (long long)node * width + c, weight * features[p * width + c]);
    if (c == 0) atomicAdd(weight_sums + node, weight);
}

// totals /= max(weight sum, floor), node by node: the nodes' weighted means.
extern "C" __global__ void residual_node_divide(
    real* __restrict__ totals, const real* __restrict__ weight_sums, int nodes, int width, real floor)
{
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= (long long)nodes * width) return;
    totals[i] /= max(weight_sums[i / width], floor);
}

// Each particle's weighted sum of its stencil's node rows (one thread per
// particle and channel).
extern "C" __global__ void residual_to_particles(
    const real* __restrict__ node_values, int width, const real* __restrict__ w,
    const int* __restrict__ node_of, int n, real* __restrict__ out)
{
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= (long long)n * width) return;
    const long long p = i / width;
    const int c = (int)(i % width);
    real acc = (real)0;
    for (int s = 0; s < RESIDUAL_STENCIL; ++s) {
        const long long slot = p * RESIDUAL_STENCIL + s;
        acc += w[slot] * node_values[(long long)node_of[slot] * width + c];
    }
    out[i] = acc;
}

// The bound α·tanh(|y'|)·y'/|y'| of each 3-vector row, y' = k·y
// (kernels.rs: Bound, BOUND_EPSILON).
__device__ __forceinline__ real residual_bound_radius(const real* y, real k, real* scaled) {
    real squared = (real)0;
    for (int a = 0; a < 3; ++a) {
        scaled[a] = y[a] * k;
        squared += scaled[a] * scaled[a];
    }
    return sqrt(squared + (real)1e-12);
}

extern "C" __global__ void residual_bound(
    const real* __restrict__ y, int rows, real alpha, real k, real* __restrict__ out)
{
    int r = blockIdx.x * blockDim.x + threadIdx.x;
    if (r >= rows) return;
    real scaled[3];
    const real radius = residual_bound_radius(y + 3 * r, k, scaled);
    const real factor = alpha * tanh(radius) / radius;
    for (int a = 0; a < 3; ++a) out[3 * r + a] = factor * scaled[a];
}
