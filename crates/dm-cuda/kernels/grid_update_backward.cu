// Backward twin of grid_update.cu (grid_update_backward.rs): per node
// with mass, ū_pre = Π ū through the walls and the floor (Coulomb slip or
// stick taken from the forward values), then P̄ = γ ū_pre / m and
// m̄ = −γ ū_pre · P / m². Gravity's adjoint dt γ Σ ū_pre and friction's
// Σ v_n (t̂·ū) over sliding floor nodes are summed into `params`
// (gravity xyz, friction).

__device__ v3 floor_adjoint(const v3& up, real friction, const v3& v, real vn, const v3& g, real& friction_share) {
    v3 projected = v3_sub(g, v3_scale(up, v3_dot(up, g)));
    friction_share = (real)0;
    if (friction <= (real)0) return projected;
    v3 vt = v3_sub(v, v3_scale(up, vn));
    real speed = v3_norm(vt);
    if (speed <= friction * (-vn)) return v3_zero();
    v3 t = v3_div(vt, speed);
    real along = v3_dot(t, g);
    friction_share = vn * along;
    return v3_add(v3_add(projected, v3_scale(up, friction * along)),
                  v3_scale(v3_sub(projected, v3_scale(t, along)), friction * vn / speed));
}

__device__ v3 boundaries_adjoint(const Consts& k, const int idx[3], v3 v, const v3& g, real& friction_share) {
    bool wall_kept[3];
    for (int a = 0; a < 3; ++a) {
        wall_kept[a] = true;
        if ((idx[a] < k.wall_cells && v.x[a] < (real)0) || (idx[a] + k.wall_cells >= k.res && v.x[a] > (real)0)) {
            v.x[a] = (real)0;
            wall_kept[a] = false;
        }
    }
    v3 gv = g;
    friction_share = (real)0;
    if (k.has_floor) {
        v3 up = v3_load(k.floor_up);
        real vn = v3_dot(v, up);
        v3 pos;
        for (int a = 0; a < 3; ++a) pos.x[a] = k.origin[a] + (real)idx[a] * k.dx;
        if (v3_dot(pos, up) <= k.floor_limit && vn < (real)0) {
            gv = floor_adjoint(up, k.floor_friction, v, vn, gv, friction_share);
        }
    }
    for (int a = 0; a < 3; ++a) if (!wall_kept[a]) gv.x[a] = (real)0;
    return gv;
}

extern "C" __global__ void grid_update_backward(
    Consts k, const real* __restrict__ pre, const real* __restrict__ grad_u,
    real* __restrict__ grad_pre, real* __restrict__ params)
{
    long long node = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    long long total = (long long)k.res * k.res * k.res;
    real share[4] = {(real)0, (real)0, (real)0, (real)0};
    if (node < total) {
        const real* lanes = pre + 4 * node;
        real m = lanes[3];
        real out[4] = {(real)0, (real)0, (real)0, (real)0};
        if (m > k.empty_node_mass) {
            v3 momentum = lanes_xyz(lanes);
            v3 u;
            for (int a = 0; a < 3; ++a) u.x[a] = (momentum.x[a] / m + k.gravity[a] * k.dt) * k.grid_damping;
            int idx[3] = {(int)(node / ((long long)k.res * k.res)), (int)((node / k.res) % k.res), (int)(node % k.res)};
            real friction_share;
            v3 gu = boundaries_adjoint(k, idx, u, lanes_xyz(grad_u + 4 * node), friction_share);
            for (int a = 0; a < 3; ++a) {
                out[a] = gu.x[a] * (k.grid_damping / m);
                share[a] = gu.x[a] * (k.dt * k.grid_damping);
            }
            out[3] = -v3_dot(gu, momentum) * k.grid_damping / (m * m);
            share[3] = friction_share;
        }
        for (int l = 0; l < 4; ++l) grad_pre[4 * node + l] = out[l];
    }
    // A warp's shares summed before one atomic add per lane.
    for (int l = 0; l < 4; ++l) {
        real s = share[l];
        for (int offset = 16; offset > 0; offset >>= 1) s += __shfl_down_sync(FULL_MASK, s, offset);
        if ((threadIdx.x & 31) == 0 && s != (real)0) atomicAdd(params + l, s);
    }
}
