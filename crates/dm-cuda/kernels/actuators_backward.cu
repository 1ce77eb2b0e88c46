// Backward twin of actuators.cu (actuators_backward.rs). Given ā_p:
// x̄_p −= k_p √n ā_p, v̄_p −= k_d √n ā_p; the gains get
// n^{-1/2} Σ_c ((x_c − x_p) − o_pc)·ā_p and n^{-1/2} Σ_c (v_c − v_p)·ā_p;
// anchor c gets x̄_c += k_p n^{-1/2} ā_p, v̄_c += k_d n^{-1/2} ā_p, which
// this substep's place in the frame turns into the adjoints of the
// frame's start and end anchors: from += (1 − along) x̄_c − v̄_c / Δt,
// to += along x̄_c + v̄_c / Δt (`anchor_ends`: from xyz then to xyz per
// anchor). Sums go to `gains` (kp, kd) and `anchor_ends` atomically.

extern "C" __global__ void actuator_accel_backward(
    Consts k, int n,
    const real* __restrict__ xs, const real* __restrict__ vs,
    const unsigned int* __restrict__ row_start, const unsigned int* __restrict__ anchor,
    const real* __restrict__ rest_offset,
    const real* __restrict__ anchor_x, const real* __restrict__ anchor_v,
    const real* __restrict__ grad_accel,
    real along, real frame_dt,
    real* __restrict__ grad_x, real* __restrict__ grad_v,
    real* __restrict__ gains, real* __restrict__ anchor_ends)
{
    int p = blockIdx.x * blockDim.x + threadIdx.x;
    real share[2] = {(real)0, (real)0};
    if (p < n) {
        unsigned int s = row_start[p], e = row_start[p + 1];
        if (e > s) {
            real count = (real)(e - s);
            real root = sqrt(count);
            v3 g = v3_load(grad_accel + 3 * p);
            v3 x = v3_load(xs + 3 * p);
            v3 v = v3_load(vs + 3 * p);
            v3_store(grad_x + 3 * p, v3_sub(v3_load(grad_x + 3 * p), v3_scale(g, k.kp * root)));
            v3_store(grad_v + 3 * p, v3_sub(v3_load(grad_v + 3 * p), v3_scale(g, k.kd * root)));
            v3 spring = v3_zero(), damper = v3_zero();
            for (unsigned int i = s; i < e; ++i) {
                unsigned int c = anchor[i];
                spring = v3_add(spring, v3_sub(v3_sub(v3_load(anchor_x + 3 * c), x), v3_load(rest_offset + 3 * i)));
                damper = v3_add(damper, v3_sub(v3_load(anchor_v + 3 * c), v));
                for (int a = 0; a < 3; ++a) {
                    real ga = g.x[a] / root;
                    real gx = k.kp * ga, gv = k.kd * ga / frame_dt;
                    atomicAdd(anchor_ends + 6 * c + a, ((real)1 - along) * gx - gv);
                    atomicAdd(anchor_ends + 6 * c + 3 + a, along * gx + gv);
                }
            }
            share[0] = v3_dot(spring, g) / root;
            share[1] = v3_dot(damper, g) / root;
        }
    }
    for (int l = 0; l < 2; ++l) {
        real sum = share[l];
        for (int offset = 16; offset > 0; offset >>= 1) sum += __shfl_down_sync(FULL_MASK, sum, offset);
        if ((threadIdx.x & 31) == 0 && sum != (real)0) atomicAdd(gains + l, sum);
    }
}

// Rigid hands overwrite their particles after the substep: those
// particles' x and v pass no adjoint back through it.
extern "C" __global__ void zero_coupled(
    int n, const unsigned int* __restrict__ row_start, real* __restrict__ grad_x, real* __restrict__ grad_v)
{
    int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= n || row_start[p + 1] == row_start[p]) return;
    v3_store(grad_x + 3 * p, v3_zero());
    v3_store(grad_v + 3 * p, v3_zero());
}
