// Counting sort of the particles by the cell holding their stencil base,
// every substep, so P2G can add up the particles of one cell within a
// warp before touching memory. Keys number the cells block by block
// (4³-cell blocks, cells inside a block), so the particles of one thread
// block of P2G also share a small box of nodes.

#define SORT_BLOCK 4
// A block of the scan: SCAN_THREADS threads, each adding SCAN_ITEMS
// consecutive values on its own before the threads scan their sums, so a
// chunk of SCAN_CHUNK values passes few barriers.
#define SCAN_THREADS 256
#define SCAN_ITEMS 4
#define SCAN_CHUNK (SCAN_THREADS * SCAN_ITEMS)

__device__ __forceinline__ unsigned cell_key(const Consts& k, const v3& x) {
    int nb = (k.res + SORT_BLOCK - 1) / SORT_BLOCK;
    int b[3], c[3];
    for (int a = 0; a < 3; ++a) {
        int base = stencil_base((x.x[a] - k.origin[a]) * k.inv_dx, k.res);
        b[a] = base / SORT_BLOCK;
        c[a] = base % SORT_BLOCK;
    }
    unsigned block = ((unsigned)b[0] * nb + b[1]) * nb + b[2];
    return block * (SORT_BLOCK * SORT_BLOCK * SORT_BLOCK) + (c[0] * SORT_BLOCK + c[1]) * SORT_BLOCK + c[2];
}

// Each particle's key and its rank among the particles of its cell.
extern "C" __global__ void cell_count(
    Consts k, int n, const real* __restrict__ xs,
    unsigned* __restrict__ keys, unsigned* __restrict__ ranks, unsigned* __restrict__ counts)
{
    int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= n) return;
    unsigned key = cell_key(k, v3_load(xs + 3 * p));
    keys[p] = key;
    ranks[p] = atomicAdd(&counts[key], 1u);
}

// Exclusive scan of one value per thread over a block of SCAN_THREADS;
// `total` receives the block's sum.
__device__ unsigned block_exclusive_scan(unsigned value, unsigned* total) {
    __shared__ unsigned warp_sums[SCAN_THREADS / 32];
    int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
    unsigned x = value;
    for (int offset = 1; offset < 32; offset <<= 1) {
        unsigned y = __shfl_up_sync(FULL_MASK, x, offset);
        if (lane >= offset) x += y;
    }
    if (lane == 31) warp_sums[warp] = x;
    __syncthreads();
    if (warp == 0) {
        unsigned s = lane < SCAN_THREADS / 32 ? warp_sums[lane] : 0u;
        for (int offset = 1; offset < 32; offset <<= 1) {
            unsigned y = __shfl_up_sync(FULL_MASK, s, offset);
            if (lane >= offset) s += y;
        }
        if (lane < SCAN_THREADS / 32) warp_sums[lane] = s;
    }
    __syncthreads();
    unsigned before = warp > 0 ? warp_sums[warp - 1] : 0u;
    *total = warp_sums[SCAN_THREADS / 32 - 1];
    __syncthreads();
    return before + x - value;
}

// Exclusive scan in place of the SCAN_CHUNK values of `data` from `start`
// (those at or past `n` count as 0 and are left alone); returns their sum.
__device__ unsigned chunk_exclusive_scan(unsigned* __restrict__ data, int start, int n) {
    const int first = start + threadIdx.x * SCAN_ITEMS;
    unsigned items[SCAN_ITEMS];
    unsigned own = 0;
    for (int j = 0; j < SCAN_ITEMS; ++j) {
        items[j] = first + j < n ? data[first + j] : 0u;
        own += items[j];
    }
    unsigned total;
    unsigned before = block_exclusive_scan(own, &total);
    for (int j = 0; j < SCAN_ITEMS; ++j) {
        if (first + j < n) data[first + j] = before;
        before += items[j];
    }
    return total;
}

// Scans each chunk of SCAN_CHUNK counts in place; chunk sums to `sums`.
extern "C" __global__ void scan_chunks(unsigned* __restrict__ data, int n, unsigned* __restrict__ sums) {
    unsigned total = chunk_exclusive_scan(data, blockIdx.x * SCAN_CHUNK, n);
    if (threadIdx.x == 0) sums[blockIdx.x] = total;
}

// Scans the chunk sums in place (one block, chunk after chunk).
extern "C" __global__ void scan_sums(unsigned* __restrict__ sums, int m) {
    unsigned carry = 0;
    for (int start = 0; start < m; start += SCAN_CHUNK) {
        // Each thread adds the carry to the values it has just written.
        unsigned total = chunk_exclusive_scan(sums, start, m);
        const int first = start + threadIdx.x * SCAN_ITEMS;
        for (int j = 0; j < SCAN_ITEMS; ++j)
            if (first + j < m) sums[first + j] += carry;
        carry += total;
    }
}

// The slot order sorted by key: particle p goes to start(key) + rank.
extern "C" __global__ void scatter_order(
    int n, const unsigned* __restrict__ keys, const unsigned* __restrict__ ranks,
    const unsigned* __restrict__ starts, const unsigned* __restrict__ sums, unsigned* __restrict__ order)
{
    int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= n) return;
    unsigned key = keys[p];
    order[starts[key] + sums[key / SCAN_CHUNK] + ranks[p]] = (unsigned)p;
}
