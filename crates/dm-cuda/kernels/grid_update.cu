// Stage 3 (grid_update.rs): momentum to velocity, gravity, grid damping,
// slip walls at the domain faces and the floor with Coulomb friction.
// Nodes lighter than the empty mass become zero.

__device__ v3 apply_boundaries(const Consts& k, int idx[3], v3 v) {
    for (int a = 0; a < 3; ++a) {
        if ((idx[a] < k.wall_cells && v.x[a] < (real)0) || (idx[a] + k.wall_cells >= k.res && v.x[a] > (real)0)) {
            v.x[a] = (real)0;
        }
    }
    if (k.has_floor) {
        v3 up = v3_load(k.floor_up);
        v3 pos;
        for (int a = 0; a < 3; ++a) pos.x[a] = k.origin[a] + (real)idx[a] * k.dx;
        if (v3_dot(pos, up) <= k.floor_limit) {
            real vn = v3_dot(v, up);
            if (vn < (real)0) {
                v3 vt = v3_sub(v, v3_scale(up, vn));
                if (k.floor_friction > (real)0) {
                    real speed = v3_norm(vt);
                    real slow = k.floor_friction * (-vn);
                    vt = speed > slow ? v3_scale(vt, (speed - slow) / speed) : v3_zero();
                }
                v = vt;
            }
        }
    }
    return v;
}

extern "C" __global__ void grid_update(Consts k, real* __restrict__ grid) {
    long long node = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    long long total = (long long)k.res * k.res * k.res;
    if (node >= total) return;
    real* lanes = grid + 4 * node;
    real m = lanes[3];
    if (m <= k.empty_node_mass) {
        lanes[0] = lanes[1] = lanes[2] = lanes[3] = (real)0;
        return;
    }
    v3 u;
    for (int a = 0; a < 3; ++a) u.x[a] = (lanes[a] / m + k.gravity[a] * k.dt) * k.grid_damping;
    int idx[3] = {(int)(node / ((long long)k.res * k.res)), (int)((node / k.res) % k.res), (int)(node % k.res)};
    v3 v = apply_boundaries(k, idx, u);
    lanes[0] = v.x[0];
    lanes[1] = v.x[1];
    lanes[2] = v.x[2];
}
