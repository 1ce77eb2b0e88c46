// Stage 1 and 2 of a substep, fused: each particle's stress and impulse
// (stress.rs), scattered to its 27 stencil nodes (p2g.rs). Lanes of a
// node: momentum xyz, mass.
//
// Threads take the particles in cell order (sort.cu), so the particles of
// one cell sit side by side in a warp: they share their 27 nodes, and a
// segmented warp reduction adds their contributions before the first
// lane of each cell adds the sum. The particles of a thread block share
// a small box of nodes: when it fits in shared memory, the sums go there
// and each touched node then reaches the grid once; otherwise straight
// into the grid. Adding 27 x 4 values per particle into the same few
// global nodes would serialise on them.

#define P2G_TILE_NODES 1024

__device__ __forceinline__ void particle_impulse(
    const Consts& k, int p,
    const real* __restrict__ vs, const real* __restrict__ fs, const real* __restrict__ cs,
    const real* __restrict__ mass, const real* __restrict__ volume,
    const real* __restrict__ mu, const real* __restrict__ lambda,
    const real* __restrict__ weights, int has_accel, const real* __restrict__ accel,
    m3& affine, v3& momentum)
{
    v3 v = v3_load(vs + 3 * p);
    m3 f = m3_load(fs + 9 * p);
    m3 c = m3_load(cs + 9 * p);
    real m = mass[p];
    m3 tau;
    if (k.pure_neo_hookean) {
        tau = neo_hookean_kirchhoff(f, m3_transpose(f), m3_det(f), mu[p], lambda[p]);
    } else {
        real w[3] = {weights[3 * p], weights[3 * p + 1], weights[3 * p + 2]};
        tau = mixture_kirchhoff(f, mu[p], lambda[p], w);
    }
    real stress_scale = -k.dt * (real)4 * k.inv_dx * k.inv_dx * volume[p];
    affine = m3_add(m3_scale(tau, stress_scale), m3_scale(c, m));
    v3 a = v3_zero();
    if (has_accel) a = v3_load(accel + 3 * p);
    if (k.drag_linear != (real)0 || k.drag_quadratic != (real)0) {
        a = v3_sub(a, v3_scale(v, k.drag_linear + k.drag_quadratic * v3_norm(v)));
    }
    momentum = v3_scale(v3_add(v, v3_scale(a, k.dt)), m);
}

// Adds w_i (momentum + affine (x_i − x_p)) to lanes 0-2 and w_i m to lane
// 3 of the 27 stencil nodes of each valid thread's particle, threads in
// cell order (`key`: the cell; invalid threads are at the end). Every
// thread of the block must call it.
__device__ __forceinline__ void scatter_sorted(
    const Consts& k, bool valid, const Stencil& st, unsigned key,
    const v3& momentum, const m3& affine, real m, real* __restrict__ grid)
{
    __shared__ real tile[P2G_TILE_NODES * 4];
    __shared__ int box_lo[3], box_hi[3];
    if (threadIdx.x < 3) {
        box_lo[threadIdx.x] = 1 << 30;
        box_hi[threadIdx.x] = -1;
    }
    __syncthreads();
    if (valid) {
        for (int a = 0; a < 3; ++a) {
            atomicMin(&box_lo[a], st.base[a]);
            atomicMax(&box_hi[a], st.base[a] + 2);
        }
    }
    __syncthreads();
    int lo[3] = {box_lo[0], box_lo[1], box_lo[2]};
    int extent[3] = {box_hi[0] - lo[0] + 1, box_hi[1] - lo[1] + 1, box_hi[2] - lo[2] + 1};
    int tile_nodes = extent[0] * extent[1] * extent[2];
    bool use_tile = box_hi[0] >= 0 && tile_nodes <= P2G_TILE_NODES;
    if (use_tile) {
        for (int t = threadIdx.x; t < tile_nodes * 4; t += blockDim.x) tile[t] = (real)0;
        __syncthreads();
    }
    // Segments: runs of lanes with the same cell (same 27 nodes).
    int lane = threadIdx.x & 31;
    unsigned previous = __shfl_up_sync(FULL_MASK, key, 1);
    bool head = lane == 0 || previous != key;
    unsigned heads = __ballot_sync(FULL_MASK, head);
    unsigned later_heads = lane == 31 ? 0u : heads & ~((2u << lane) - 1u);
    int segment_end = later_heads ? __ffs(later_heads) - 2 : 31;
    bool reduce = heads != FULL_MASK;
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
            real wij = st.w[0][i] * st.w[1][j];
            for (int kk = 0; kk < 3; ++kk) {
                real w = wij * st.w[2][kk];
                v3 offset;
                offset.x[0] = ((real)i - st.frac[0]) * k.dx;
                offset.x[1] = ((real)j - st.frac[1]) * k.dx;
                offset.x[2] = ((real)kk - st.frac[2]) * k.dx;
                v3 q = v3_add(momentum, m3_mul_v(affine, offset));
                real lanes[4] = {w * q.x[0], w * q.x[1], w * q.x[2], w * m};
                if (reduce) {
                    for (int stride = 1; stride < 32; stride <<= 1) {
                        for (int c = 0; c < 4; ++c) {
                            real other = __shfl_down_sync(FULL_MASK, lanes[c], stride);
                            if (lane + stride <= segment_end) lanes[c] += other;
                        }
                    }
                }
                if (head && valid) {
                    real* node;
                    if (use_tile) {
                        int ti = ((st.base[0] + i - lo[0]) * extent[1] + (st.base[1] + j - lo[1])) * extent[2]
                               + (st.base[2] + kk - lo[2]);
                        node = tile + 4 * ti;
                    } else {
                        node = grid + 4 * node_index(k.res, st.base[0] + i, st.base[1] + j, st.base[2] + kk);
                    }
                    for (int c = 0; c < 4; ++c) atomicAdd(node + c, lanes[c]);
                }
            }
        }
    }
    if (use_tile) {
        __syncthreads();
        for (int t = threadIdx.x; t < tile_nodes; t += blockDim.x) {
            const real* src = tile + 4 * t;
            // No particle's stencil reached it.
            if (src[0] == (real)0 && src[1] == (real)0 && src[2] == (real)0 && src[3] == (real)0) continue;
            int ti = t / (extent[1] * extent[2]);
            int tj = (t / extent[2]) % extent[1];
            int tk = t % extent[2];
            real* node = grid + 4 * node_index(k.res, lo[0] + ti, lo[1] + tj, lo[2] + tk);
            for (int c = 0; c < 4; ++c) atomicAdd(node + c, src[c]);
        }
    }
}

// The stencil and cell key of the particle a thread takes in cell order.
__device__ __forceinline__ bool sorted_particle(
    const Consts& k, int n, const unsigned* __restrict__ order, const unsigned* __restrict__ keys,
    const real* __restrict__ xs, int& p, Stencil& st, unsigned& key)
{
    int i_sorted = blockIdx.x * blockDim.x + threadIdx.x;
    bool valid = i_sorted < n;
    p = valid ? (int)order[i_sorted] : 0;
    key = 0xffffffffu;
    if (valid) {
        st = make_stencil(k, v3_load(xs + 3 * p));
        key = keys[p];
    } else {
        for (int a = 0; a < 3; ++a) {
            st.base[a] = 0;
            st.frac[a] = (real)0;
            st.w[a][0] = st.w[a][1] = st.w[a][2] = (real)0;
        }
    }
    return valid;
}

extern "C" __global__ void p2g(
    Consts k, int n, const unsigned* __restrict__ order, const unsigned* __restrict__ keys,
    const real* __restrict__ xs, const real* __restrict__ vs,
    const real* __restrict__ fs, const real* __restrict__ cs,
    const real* __restrict__ mass, const real* __restrict__ volume,
    const real* __restrict__ mu, const real* __restrict__ lambda,
    const real* __restrict__ weights, int has_accel, const real* __restrict__ accel,
    real* __restrict__ grid)
{
    int p;
    Stencil st;
    unsigned key;
    bool valid = sorted_particle(k, n, order, keys, xs, p, st, key);
    m3 affine = m3_zero();
    v3 momentum = v3_zero();
    real m = (real)0;
    if (valid) {
        particle_impulse(k, p, vs, fs, cs, mass, volume, mu, lambda, weights, has_accel, accel, affine, momentum);
        m = mass[p];
    }
    scatter_sorted(k, valid, st, key, momentum, affine, m, grid);
}
